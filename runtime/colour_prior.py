"""Which cells of the search region hold the target's colours rather than its surroundings': a prior on the
score map against a look-alike at a crossing.

A Siamese tracker scores another walker as high as its person (docs/evaluation.md, "Reported state against
the truth"); where they cross, the argmax jumps. What usually tells them apart is their clothes. At the start
the hue-saturation histogram of the target's box is counted against that of the ring around it (out to
`RING_SIDES` box sides, the box left out); a colour's share of the target, counts(target) / (counts(target) +
counts(ring)), says how much it speaks for the target. Each frame that table is read back into every fourth
pixel of the search crop, averaged over a box of the target's size around each cell's point, and divided by
its largest value; the tracker weights the cell's score by (1 − weight) + weight · that average when it picks
a cell (the reported score stays the network's). A grey picture, or a night whose noise leaves the target's
colours as common around it as on it, gives every cell about the same average, and the pick is the
network's. Off by default: its gain on the suite is about the seed spread (docs/evaluation.md).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .swap import HS_RANGES, hue_saturation

RING_SIDES = 3.0  # the ring reaches this many box sides across: the ground and whoever stands near
INNER = 0.8  # the target's colours are counted in the middle of the box this much of its width and height
SHRINK = 4  # the search crop is read back at this fraction of its side


class ColourPrior:
    """The target-against-ring colour table of the start box, and its reading on each search crop."""

    def __init__(self) -> None:
        self._table: np.ndarray | None = None

    def reset(self, image: np.ndarray, centre: tuple[float, float], size: tuple[float, float]) -> None:
        """Count the target's and its ring's colours in the start frame; nothing for a grey image."""
        self._table = None
        if image.ndim != 3 or not all(math.isfinite(v) for v in (*centre, *size)):
            return
        (cx, cy), (w, h) = centre, size
        half = RING_SIDES * max(w, h) / 2
        x0, y0 = max(0, int(cx - half)), max(0, int(cy - half))
        x1, y1 = min(image.shape[1], int(cx + half) + 1), min(image.shape[0], int(cy + half) + 1)
        if x1 <= x0 or y1 <= y0:
            return
        hsv = cv2.cvtColor(np.ascontiguousarray(image[y0:y1, x0:x1]), cv2.COLOR_BGR2HSV)
        box = np.zeros(hsv.shape[:2], np.uint8)
        inner = np.zeros_like(box)
        for mask, scale in ((box, 1.0), (inner, INNER)):
            bx0, by0 = int(cx - scale * w / 2) - x0, int(cy - scale * h / 2) - y0
            bx1, by1 = int(cx + scale * w / 2) - x0 + 1, int(cy + scale * h / 2) - y0 + 1
            mask[max(0, by0):max(0, by1), max(0, bx0):max(0, bx1)] = 255
        target, ring = hue_saturation(hsv, inner), hue_saturation(hsv, cv2.bitwise_not(box))
        if target.sum() == 0:
            return
        with np.errstate(invalid="ignore", divide="ignore"):
            share = np.where(target + ring > 0, target / (target + ring), 0.0)
        self._table = (255.0 * share).astype(np.float32)

    def weights(self, patch: np.ndarray, target: tuple[float, float], points: tuple[np.ndarray, np.ndarray],
                weight: float) -> np.ndarray | None:
        """(1 − weight) + weight · the target-colour average around each cell, or None where there is no table.

        `patch`: the search crop (uint8 BGR); `target`: the target's (w, h) in crop pixels; `points`: the
        cells' (x, y) relative to the crop's centre."""
        if self._table is None or patch.ndim != 3 or weight <= 0:
            return None
        # every SHRINK-th pixel each way: the cells lie 8 crop pixels apart and the box average smooths the
        # rest, for a sixteenth of the work (an averaging resize costs more than it saves)
        small = np.ascontiguousarray(patch[::SHRINK, ::SHRINK])
        side = small.shape[1]
        hsv = cv2.cvtColor(small, cv2.COLOR_BGR2HSV)
        likely = cv2.calcBackProject([hsv], [0, 1], self._table, HS_RANGES, 1.0).astype(np.float32)
        f = 1.0 / SHRINK  # small pixels per crop pixel
        kw, kh = (min(side, max(1, int(round(length * f)))) for length in target)
        mean = cv2.blur(likely, (kw, kh), borderType=cv2.BORDER_CONSTANT)
        xs = np.clip(np.round((points[0] + (patch.shape[1] - 1) / 2) * f), 0, side - 1).astype(int)
        ys = np.clip(np.round((points[1] + (patch.shape[0] - 1) / 2) * f), 0, side - 1).astype(int)
        cells = mean[ys, xs]
        top = float(cells.max())
        if top <= 0:
            return None
        return (1.0 - weight) + weight * cells / top
