"""dadiff.runtime: torch-free tracker on onnxruntime (`Tracker.load(...)`, then `init` and `update`)."""

from .backend import Backend
from .config import Geometry, Params
from .errors import InputError, ModelError
from .onnx_backend import OnnxBackend
from .tracker import Tracker, TrackResult

__all__ = [
    "Backend",
    "Geometry",
    "InputError",
    "ModelError",
    "OnnxBackend",
    "Params",
    "TrackResult",
    "Tracker",
]
