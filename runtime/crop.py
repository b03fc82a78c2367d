"""Square crops around a point, equal to the released `get_subwindow` without padding the whole frame.

The released code pads the full frame with the mean colour whenever the window touches an edge (several ms
at 720p). Here only the window is padded: the part of it inside the frame is cut, given a border of that
colour with `cv2.copyMakeBorder` and resized with `cv2.resize`, the released steps on a window-sized
canvas (about 0.2 ms on a 2-core AVX2 CPU). A window much larger than the frame (a target grown huge)
would make that canvas large, so there one `cv2.remap` samples the output grid straight from the frame
instead: the grid `cv2.resize` uses on the cut window, clamped at the window edge, with a constant border;
it matches get_subwindow up to OpenCV's fixed-point rounding (1 level) at about 0.6 ms whatever the size.
A plain warpAffine would blend in the pixels just outside the window when upscaling (tens of levels on
the outermost rows).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

MAX_CANVAS_SIDE = 1024  # larger windows take the remap path: a padded canvas would be 3 MB or more


def context_side(w: float, h: float, context: float) -> float:
    """The side of the square window around a w x h target with `context` of its perimeter added (SiamFC's
    s_z): the template's window, and the search window's before it is scaled up to the search crop."""
    pad = context * (w + h)
    return math.sqrt((w + pad) * (h + pad))


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
    if side > MAX_CANVAS_SIDE:
        return _remap_subwindow(frame, centre, out_size, side, fill)
    h, w = frame.shape[:2]
    x0, y0 = window_origin(centre[0], side), window_origin(centre[1], side)
    x1, y1 = x0 + side, y0 + side
    ix0, iy0, ix1, iy1 = min(max(x0, 0), w), min(max(y0, 0), h), max(min(x1, w), 0), max(min(y1, h), 0)
    if ix0 >= ix1 or iy0 >= iy1:  # the window lies wholly off the frame: all fill
        return _remap_subwindow(frame, centre, out_size, side, fill)
    patch = frame[iy0:iy1, ix0:ix1]
    if (ix0, iy0, ix1, iy1) != (x0, y0, x1, y1):
        patch = cv2.copyMakeBorder(patch, iy0 - y0, y1 - iy1, ix0 - x0, x1 - ix1, cv2.BORDER_CONSTANT,
                                   value=tuple(fill))
    return patch if side == out_size else cv2.resize(patch, (out_size, out_size))


def _remap_subwindow(
    frame: np.ndarray, centre: tuple[float, float], out_size: int, side: int, fill: tuple[float, ...]
) -> np.ndarray:
    """`subwindow` sampled straight from the frame: no canvas, whatever the window's size."""
    xs = _grid(window_origin(centre[0], side), side, out_size)
    ys = _grid(window_origin(centre[1], side), side, out_size)
    map_x = np.broadcast_to(xs[None, :], (out_size, out_size))
    map_y = np.broadcast_to(ys[:, None], (out_size, out_size))
    border = tuple(fill) + (0.0,) * (4 - len(fill))
    return cv2.remap(
        frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=border
    )


def protocol_box(box: Sequence[float]) -> tuple[float, float, float, float]:
    """The box `dadiff-run --init`, the service's init and evaluation pass to `Tracker.init` for a box (x, y, w,
    h) as datasets and users give it: (x + 0.5, y + 0.5, w, h), the released test script's init (its centre x +
    w/2, as `init` takes the centre at x + (w - 1)/2)."""
    x, y, w, h = (float(v) for v in box)
    return (x + 0.5, y + 0.5, w, h)
