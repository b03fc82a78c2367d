"""Frame checks and crop-to-tensor conversion."""

from __future__ import annotations

import cv2
import numpy as np

from .errors import InputError


def as_image(frame: object) -> np.ndarray:
    """A uint8 H×W (grey) or H×W×3 (BGR) view of `frame`; H×W×1 becomes H×W, H×W×4 drops alpha.

    Grey frames stay single-channel until after cropping, which is cheaper than converting the whole frame.
    """
    if not isinstance(frame, np.ndarray):
        raise InputError(f"frame must be a numpy array, got {type(frame).__name__}")
    if frame.dtype != np.uint8:
        raise InputError(f"frame must be uint8, got {frame.dtype}")
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    elif frame.ndim == 3 and frame.shape[2] == 4:
        frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR)
    if not (frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] == 3)):
        raise InputError(f"frame must be H×W (grey) or H×W×3 (BGR), got shape {frame.shape}")
    if frame.shape[0] == 0 or frame.shape[1] == 0:
        raise InputError(f"frame is empty (shape {frame.shape})")
    return frame


def to_blob(patch: np.ndarray, channel_order: str = "BGR") -> np.ndarray:
    """(1, 3, H, W) float32 from an H×W[×3] uint8 BGR (or grey) patch, in the model's channel order."""
    if patch.ndim == 2:
        patch = patch[:, :, None].repeat(3, axis=2)
    elif channel_order == "RGB":
        patch = patch[:, :, ::-1]
    return np.ascontiguousarray(patch.transpose(2, 0, 1)[None], dtype=np.float32)
