"""Frame checks, crop-to-tensor conversion, and a video decoded into memory."""

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
    if frame.ndim >= 2 and (frame.shape[0] == 0 or frame.shape[1] == 0):  # before cvtColor, which asserts on it
        raise InputError(f"frame is empty (shape {frame.shape})")
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    elif frame.ndim == 3 and frame.shape[2] == 4:
        frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR)
    if not (frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] == 3)):
        raise InputError(f"frame must be H×W or H×W×1 (grey), H×W×3 (BGR) or H×W×4 (BGRA), got shape {frame.shape}")
    if frame.shape[0] == 0 or frame.shape[1] == 0:
        raise InputError(f"frame is empty (shape {frame.shape})")
    return frame


def to_blob(patch: np.ndarray, channel_order: str = "BGR", out: np.ndarray | None = None) -> np.ndarray:
    """(1, 3, H, W) float32 from an H×W[×3] uint8 BGR (or grey) patch, in the model's channel order.

    With `out` (a (1, 3, H, W) float32 array) the values are written there and `out` is returned.
    """
    if patch.ndim == 2:
        planes = np.broadcast_to(patch[None], (3, *patch.shape))
    else:
        planes = (patch[:, :, ::-1] if channel_order == "RGB" else patch).transpose(2, 0, 1)
    if out is None:
        return np.ascontiguousarray(planes[None], dtype=np.float32)
    np.copyto(out[0], planes)
    return out


def decode_video(path: str, limit: int | None = None) -> list[np.ndarray]:
    """The first `limit` frames (all if None) of a video file as BGR uint8 arrays; fewer if it ends first,
    none if OpenCV cannot open it. Callers that need the frames again (benchmarks, labelling) keep them."""
    capture = cv2.VideoCapture(path)
    frames = []
    while limit is None or len(frames) < limit:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    return frames
