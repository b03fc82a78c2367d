"""Whether the box has left its target for something of other colours: the swap a follow controller must not chase.

On uncut real footage a Siamese tracker that loses its person at a crossing, or after the person leaves the
view, settles on the next walker and scores them as high as the person (docs/evaluation.md, "Reported state
against the truth"); the still check (runtime/still.py) cannot see it, because the new lock moves. What
usually differs is the clothes: the colours of the box's upper and lower half. The check keeps the hue and
saturation histograms of both halves of the start box (its inner part: the box's edges hold background) and
compares each frame's box with them (Bhattacharyya distance, 0 for the same colours, 1 for none in common).
The median over the last `frames` frames above the bound calls the box swapped, until it falls
`RETURN_MARGIN` below it again; the tracker then reports 'uncertain' instead of 'tracking', so a follow
controller holds.

The bound is `distance` or, where the picture makes the target's own colours wander further, `SELF_MARGIN`
above the median distance of the first `CALIBRATION_FRAMES` frames after the start (taken to be on the
target; the check says nothing before). In a dark, noisy picture the hue of dim pixels is noise, and the
same person's box lies 0.6-0.9 from its start (docs/evaluation.md): a fixed bound would call every frame a
swap. A swap within those first frames raises the bound and goes unseen.

Colour only: a grey or thermal picture has no hue, the histograms of every box agree and the check stays
silent; so does it between people dressed alike. A target that turns (an open jacket from the front and the
back) or walks under other light moves the distance as a swap does: the check then withholds 'tracking'
from some frames on the target (docs/evaluation.md gives both shares on uncut video).
"""

from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np

INNER = 0.6  # the middle of the box this much of its width and height: the target, not the ground beside it
HUE_BINS, SATURATION_BINS = 16, 8
HS_RANGES = [0, 180, 0, 256]  # OpenCV's 8-bit hue and saturation
RETURN_MARGIN = 0.1  # a swapped box is swapped until its median distance is this much under the bound
CALIBRATION_FRAMES = 10  # the frames after the start that measure how far the target's own colours wander
SELF_MARGIN = 0.2  # the bound is at least this much above that wander


def hue_saturation(hsv: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """The HUE_BINS x SATURATION_BINS histogram (counts) of an HSV image's pixels, those under `mask` only."""
    return cv2.calcHist([hsv], [0, 1], mask, [HUE_BINS, SATURATION_BINS], HS_RANGES)


def colour_histogram(image: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray | None:
    """Hue-saturation histograms of the upper and lower half of the inner part of `box` (centre x, centre y,
    w, h) in a BGR `image`, as one float32 vector summing to 1; None for a grey image or a box with no
    pixels in the frame."""
    if image.ndim != 3:
        return None
    cx, cy, w, h = box
    if not all(math.isfinite(v) for v in box):
        return None
    half_w, half_h = INNER * w / 2, INNER * h / 2
    x0, y0 = max(0, int(cx - half_w)), max(0, int(cy - half_h))
    x1, y1 = min(image.shape[1], int(cx + half_w) + 1), min(image.shape[0], int(cy + half_h) + 1)
    if x1 <= x0 or y1 <= y0:
        return None
    hsv = cv2.cvtColor(np.ascontiguousarray(image[y0:y1, x0:x1]), cv2.COLOR_BGR2HSV)
    middle = max(1, hsv.shape[0] // 2)
    halves = (hsv[:middle], hsv[middle:]) if hsv.shape[0] > 1 else (hsv, hsv)
    parts = [hue_saturation(half).ravel() for half in halves]
    return np.concatenate([part / (2 * part.sum()) for part in parts]).astype(np.float32)


class SwapCheck:
    """Keeps the start box's colours, the first CALIBRATION_FRAMES distances to them (the target's own
    wander) and the last `frames` after those."""

    def __init__(self, frames: int, distance: float) -> None:
        self.frames, self.distance = frames, distance
        self.reset()

    def reset(self) -> None:
        """A new target: no colours yet (the next `observe` is the start frame)."""
        self._start: np.ndarray | None = None
        self._started = False
        self._own: list[float] = []
        self._distances: deque[float] = deque(maxlen=self.frames)
        self._swapped = False

    def observe(self, image: np.ndarray, box: tuple[float, float, float, float]) -> bool:
        """Record this frame and its box (centre x, centre y, w, h); True while the box's colours have stayed
        away from the start box's. The first call after `reset` is the start frame."""
        colours = colour_histogram(image, box)
        if not self._started:
            self._start, self._started = colours, True
            return False
        if self._start is None or colours is None:
            return self._swapped  # a grey picture, or a box off the frame: nothing to compare, the verdict stands
        distance = cv2.compareHist(self._start, colours, cv2.HISTCMP_BHATTACHARYYA)
        if len(self._own) < CALIBRATION_FRAMES:
            self._own.append(distance)
            return False
        self._distances.append(distance)
        bound = max(self.distance, float(np.median(self._own)) + SELF_MARGIN)
        bound -= RETURN_MARGIN if self._swapped else 0.0  # hysteresis, as the still check has
        self._swapped = float(np.median(self._distances)) > bound
        return self._swapped
