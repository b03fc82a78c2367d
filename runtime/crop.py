"""Square crops around a point, equal to the released `get_subwindow` without padding the whole frame.

The released code pads the full frame with the mean colour whenever the window touches an edge (several ms
at 720p). Here one `cv2.remap` samples the output grid straight from the frame with a constant border of
that colour. The sampling grid is the one `cv2.resize` uses on the cut window, including its clamping at
the window edge, so the result matches get_subwindow up to OpenCV's fixed-point rounding (1 level); a
plain warpAffine would blend in the pixels just outside the window when upscaling (tens of levels on the
outermost rows).
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def crop_side(size: float) -> int:
    """Window side in frame pixels: round half to even (Python/numpy `round`), at least 1."""
    return max(1, int(round(size)))


def mean_colour(frame: np.ndarray) -> tuple[float, ...]:
    """Per-channel mean truncated to an integer, as the released code stores it on a uint8 canvas."""
    channels = 1 if frame.ndim == 2 else frame.shape[2]
    return tuple(float(math.floor(v)) for v in cv2.mean(frame)[:channels])


def window_origin(centre: float, side: int) -> int:
    """First frame pixel of the window (released: floor(c - (side + 1) / 2 + 0.5))."""
    return int(math.floor(centre - (side + 1) / 2 + 0.5))


def _grid(origin: int, side: int, out_size: int) -> np.ndarray:
    """Frame coordinates cv2.resize samples when scaling `side` pixels to `out_size` (edge-clamped)."""
    k = side / out_size
    pos = (np.arange(out_size, dtype=np.float64) + 0.5) * k - 0.5
    return (origin + np.clip(pos, 0.0, side - 1)).astype(np.float32)


def subwindow(
    frame: np.ndarray, centre: tuple[float, float], out_size: int, side: int, fill: tuple[float, ...]
) -> np.ndarray:
    """Crop `side`×`side` frame pixels around `centre` (x, y), resized to `out_size`, padded with `fill`.

    Returns a uint8 array (out_size, out_size[, C]) like the frame.
    """
    xs = _grid(window_origin(centre[0], side), side, out_size)
    ys = _grid(window_origin(centre[1], side), side, out_size)
    map_x = np.broadcast_to(xs[None, :], (out_size, out_size))
    map_y = np.broadcast_to(ys[:, None], (out_size, out_size))
    border = tuple(fill) + (0.0,) * (4 - len(fill))
    return cv2.remap(
        frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=border
    )
