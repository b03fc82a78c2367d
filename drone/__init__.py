"""dadiff.drone."""
