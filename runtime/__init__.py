"""dadiff.runtime: torch-free tracker on onnxruntime (`Tracker.load(...)`, then `init` and `update`).

This level is the onboard tracker and what it needs in flight; the commands (`commands/`), evaluation
(`evaluation/`) and data making (`datamaking/`) sit in subpackages that this level never imports. The names
below load on first use, so that code needing only the crop or data making (training on a machine without
onnxruntime, say) can import its modules without pulling onnxruntime in.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

# Set before onnxruntime loads: its telemetry stores a device id under $HOME and, where the home is not
# writable (the service's user), prints "Failed to persist telemetry device ID" on every run, --help too.
# The user's own setting wins.
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

_EXPORTS = {
    "Backend": ".backend",
    "Geometry": ".config",
    "Params": ".config",
    "InputError": ".errors",
    "ModelError": ".errors",
    "OnnxBackend": ".onnx_backend",
    "Tracker": ".tracker",
    "TrackResult": ".tracker",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name], __name__), name)
