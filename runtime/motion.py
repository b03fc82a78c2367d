"""The picture's sudden motion between two frames, to move the search region with it.

A gust or a quick yaw moves the whole picture further in one frame than the network's search region
reaches (docs/lab-notebook.md, "Gusts"); the picture says by how much, even at night, where lamps and lit ground give
phase correlation a sharp peak. Only a sudden change can be the drone's accident: a drone following its
target sees the ground flow steadily under a target that stays put in the frame. So each shift is compared
with the picture's steady motion (the median of the last `TREND_READS` shifts, which a gust of a few frames
does not move), and only a jolt, a shift that departs from it by more than `JOLT_FRACTION` of the frame's
width, moves the tracker's search region (a second look where the target was, the surer one kept, loses
more under gusts than it saves: docs/lab-notebook.md, "Jolts").
The frames are compared small and grey, so a read costs well under a millisecond; a read whose peak is weak
(a dark, flat or changing picture) is ignored.
"""

from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np

SMALL_WIDTH = 160  # px: wide enough for a 20-40 px step to be 5-10 px, small enough for < 0.5 ms
MAX_SMALL_HEIGHT = 4 * SMALL_WIDTH  # a 3000 x 1 frame would make a 160 x 480000 one: seconds per read
JOLT_FRACTION = 0.02  # of the frame's width (12.8 px at 640): past the read's noise and a hover's sway
TREND_READS = 11  # a gust's 3-5 frames stay a minority


class PictureMotion:
    """Reads each frame's shift (frame px) against the previous one by phase correlation, and says how far
    it departs from the picture's steady motion."""

    def __init__(self, min_response: float) -> None:
        self.min_response = min_response
        self._previous: np.ndarray | None = None
        self._spare: np.ndarray | None = None  # the small frame before the previous one, reused as a buffer
        self._size: tuple[int, ...] = ()  # the previous frame's height and width
        self._window: np.ndarray | None = None
        self._reads: deque[tuple[float, float]] = deque(maxlen=TREND_READS)

    def reset(self, image: np.ndarray) -> None:
        """Start again from this frame (a new target): no trend yet."""
        self._previous, self._spare, self._size = self._small(image), self._previous, image.shape[:2]
        self._reads.clear()

    def jolt(self, image: np.ndarray) -> tuple[float, float] | None:
        """How far the picture jumped from the previous frame to this one beyond its steady motion, in frame
        px, or None for no jolt: a steady shift, the first read after `reset` (no steady motion known yet), a
        weak read or a changed frame size. This frame becomes the previous one either way."""
        read = self.shift(image)
        if read is None:
            return None
        if not self._reads:  # the first read: the steady motion starts from it
            self._reads.append(read)
            return None
        steady = np.median(self._reads, axis=0)
        self._reads.append(read)
        dx, dy = read[0] - steady[0], read[1] - steady[1]
        return (float(dx), float(dy)) if math.hypot(dx, dy) > JOLT_FRACTION * image.shape[1] else None

    def shift(self, image: np.ndarray) -> tuple[float, float] | None:
        """The picture's shift from the previous frame to this one in frame px, or None when the
        correlation peak is below `min_response` (or the frame size changed); this frame becomes the
        previous one either way."""
        small = self._small(image)
        previous, self._previous, self._spare = self._previous, small, self._previous
        size, self._size = self._size, image.shape[:2]
        if previous is None or size != self._size:
            self._reads.clear()  # shifts of another frame size are in other pixels
            return None
        if self._window is None or self._window.shape != small.shape:
            self._window = cv2.createHanningWindow((small.shape[1], small.shape[0]), cv2.CV_32F)
        (dx, dy), response = cv2.phaseCorrelate(previous, small, self._window)
        if not response >= self.min_response:
            return None
        return dx * image.shape[1] / small.shape[1], dy * image.shape[0] / small.shape[0]  # frame px per small px

    def _small(self, image: np.ndarray) -> np.ndarray:
        """The frame grey, `SMALL_WIDTH` wide, as float32 in the spare buffer (no allocation per frame)."""
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        h, w = grey.shape[:2]
        size = (SMALL_WIDTH, min(max(8, round(h * SMALL_WIDTH / w)), MAX_SMALL_HEIGHT))
        small = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
        if self._spare is None or self._spare.shape != small.shape:
            self._spare = np.empty(small.shape, np.float32)
        np.copyto(self._spare, small)
        return self._spare
