"""dadiff.export."""

import dadiff.runtime  # noqa: F401  (sets onnxruntime's environment before any module here loads onnxruntime)
