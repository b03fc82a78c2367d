"""The picture's own motion between two frames, to move the search region with it.

A gust or a quick yaw moves the whole picture further in one frame than the network's search region
reaches (README, "Gusts"); the picture says by how much, even at night, where lamps and lit ground give
phase correlation a sharp peak. The frames are compared small and grey, so a read costs well under a
millisecond; a read whose peak is weak (a dark, flat or changing picture) is ignored.
"""

from __future__ import annotations

import cv2
import numpy as np

SMALL_WIDTH = 160  # px: wide enough for a 20-40 px step to be 5-10 px, small enough for < 0.5 ms


class PictureMotion:
    """Reads each frame's shift (frame px) against the previous one by phase correlation."""

    def __init__(self, min_response: float) -> None:
        self.min_response = min_response
        self._previous: np.ndarray | None = None
        self._window: np.ndarray | None = None

    def reset(self, image: np.ndarray) -> None:
        """Start again from this frame (a new target)."""
        self._previous = self._small(image)

    def shift(self, image: np.ndarray) -> tuple[float, float] | None:
        """The picture's shift from the previous frame to this one in frame px, or None when the
        correlation peak is below `min_response` (or the frame size changed); this frame becomes the
        previous one either way."""
        small = self._small(image)
        previous, self._previous = self._previous, small
        if previous is None or previous.shape != small.shape:
            return None
        if self._window is None or self._window.shape != small.shape:
            self._window = cv2.createHanningWindow((small.shape[1], small.shape[0]), cv2.CV_32F)
        (dx, dy), response = cv2.phaseCorrelate(previous, small, self._window)
        if not response >= self.min_response:
            return None
        factor = image.shape[1] / SMALL_WIDTH  # frame px per small px
        return dx * factor, dy * factor

    @staticmethod
    def _small(image: np.ndarray) -> np.ndarray:
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        h, w = grey.shape[:2]
        size = (SMALL_WIDTH, max(8, round(h * SMALL_WIDTH / w)))
        return cv2.resize(grey, size, interpolation=cv2.INTER_AREA).astype(np.float32)
