"""dadiff.export."""
