"""Whether the tracked box stands still on the ground around it: the lock a follow controller must not chase.

A Siamese tracker that loses its person often settles on a fixed look-alike (a sign post, a lamp, a board)
and scores it as high as the person: on uncut real footage the score does not tell on- from off-target
frames (docs/evaluation.md, "Reported state against the truth"). What a fixed thing cannot do is move against
the ground around it. The ring around the box (four box sides across, the box masked out) is
phase-correlated with the ring cut at the same place in an earlier frame; that shift is the ground's, the
camera's own motion included, so the box's displacement minus it is the box's motion on the ground. The
whole picture's shift is not used: moving people dominate it on a fixed camera (tens of pixels over a few
seconds on vtest), and a camera that follows its target keeps the target still in the picture while the
ground flows.

A box that has once moved on the ground and then stays within `travel` of its size (sqrt(w·h)) for
`frames` frames is called still, until it moves twice that far. The tracker reports it 'uncertain'
instead of 'tracking': a follow controller holds rather than chase a post. A person who stops is reported
the same way, which costs a follower nothing (there is nowhere to go), and a target chosen while it
stands (a parked car) stays 'tracking' until it has moved.

The ground's shift over the window is followed frame by frame (a read between consecutive frames) and then
corrected by one read between the ring of `frames` (and `frames` / 2) frames before and the current frame
cut where the followed shift puts it: summed frame-to-frame reads drift by a few hundredths of a box side a
frame, and one read across the window alone fails once the ground has flowed past the ring (a camera
following its target), where it would call the target still. A frame-to-frame read that fails (a weak
correlation peak: a flat or changed picture) counts as no shift, which the read across the window corrects;
where that read fails too, or lands further than a box side from the followed shift, the last verdict
stands. Reads miss by up to a few pixels when the picture jumps 2-3 px a frame: the check then stays
silent on some frames, towards 'tracking' as before.
"""

from __future__ import annotations

import math
from collections import deque

import cv2
import numpy as np

RING_SIDES = 4.0  # the ring spans this many box sides: enough ground to read, little of other walkers
RING_PIXELS = 64  # the ring is compared at this size
MASK_MARGIN = 1.2  # the masked-out box is this much larger than the box (its edges and blur)
MIN_RESPONSE = 0.1  # a weaker correlation peak is no read (a flat or changed picture)
LEAVE_FACTOR = 2.0  # a still box is still until it moves this many times `travel`: a read's miss does not flicker


class StillCheck:
    """Keeps the last `frames` + 1 boxes, the rings cut around them and the ground's summed shift, and
    compares each new frame with the frames `frames` and `frames` / 2 before it."""

    def __init__(self, frames: int, travel: float) -> None:
        self.frames, self.travel = frames, travel
        self._hann = cv2.createHanningWindow((RING_PIXELS, RING_PIXELS), cv2.CV_32F)
        self._window = np.empty_like(self._hann)
        self.reset()

    def reset(self) -> None:
        """A new target: no history, not yet seen moving."""
        # (box as centre x, centre y, w, h; its ring; the ground's summed shift since the window started)
        self._past: deque[tuple[tuple[float, float, float, float], np.ndarray | None, tuple[float, float]]] = (
            deque(maxlen=self.frames + 1))
        self._moved = False
        self._still = False

    def observe(self, image: np.ndarray, box: tuple[float, float, float, float]) -> bool:
        """Record this frame (BGR or grey) and the box (centre x, centre y, w, h) the tracker gave it; True
        when the box has stood still on the ground for the last `frames` frames after moving. The first call
        after `reset` is the start frame."""
        ring = self._cut(image, box)
        if not self._past:  # the start frame
            self._past.append((box, ring, (0.0, 0.0)))
            return False
        last_box, last_ring, summed = self._past[-1]
        # a step without a read counts as no shift: the read across the window below corrects it
        step = self._shift(last_ring, self._cut(image, last_box), last_box) or (0.0, 0.0)
        self._past.append((box, ring, (summed[0] + step[0], summed[1] + step[1])))
        if len(self._past) <= self.frames:
            return False
        allowed = self.travel * math.sqrt(max(box[2] * box[3], 1e-6))
        moves = [self._ground_move(image, lag) for lag in (self.frames, self.frames // 2 or 1)]
        if any(move is None for move in moves):
            return self._still  # no read across the window: the last verdict stands
        self._moved = self._moved or moves[0] >= allowed
        bound = allowed * (LEAVE_FACTOR if self._still else 1.0)  # hysteresis, as the score's states have
        self._still = self._moved and all(move < bound for move in moves)
        return self._still

    def _ground_move(self, image: np.ndarray, lag: int) -> float | None:
        """How far (frame px) the box moved against the ground over the last `lag` frames, or None."""
        box, _, summed = self._past[-1]
        old_box, old_ring, old_summed = self._past[-1 - lag]
        fx, fy = summed[0] - old_summed[0], summed[1] - old_summed[1]  # the followed shift
        where = (old_box[0] + fx, old_box[1] + fy, old_box[2], old_box[3])
        residual = self._shift(old_ring, self._cut(image, where), old_box)
        if residual is None or math.hypot(*residual) > max(old_box[2], old_box[3]):
            return None  # no read, or one further off than the followed shift ever drifts: a false peak
        return math.hypot(box[0] - old_box[0] - fx - residual[0], box[1] - old_box[1] - fy - residual[1])

    @staticmethod
    def _cut(image: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray | None:
        """The ring around `box`, RING_PIXELS square, grey float32; None for a box of no size."""
        cx, cy, w, h = box
        side = RING_SIDES * max(w, h)
        if not (side > 0 and math.isfinite(side) and math.isfinite(cx) and math.isfinite(cy)):
            return None
        s = RING_PIXELS / side  # ring pixels per frame pixel
        warp = np.float32([[s, 0, RING_PIXELS / 2 - s * cx], [0, s, RING_PIXELS / 2 - s * cy]])
        ring = cv2.warpAffine(image, warp, (RING_PIXELS, RING_PIXELS), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)
        if ring.ndim == 3:
            ring = cv2.cvtColor(ring, cv2.COLOR_BGR2GRAY)
        return ring.astype(np.float32)

    def _shift(self, before: np.ndarray | None, after: np.ndarray | None, box: tuple[float, float, float, float]
               ) -> tuple[float, float] | None:
        """The ground's shift (frame px) between two rings cut around `box`, or None if unreadable."""
        if before is None or after is None:
            return None
        s = RING_PIXELS / (RING_SIDES * max(box[2], box[3]))
        window = self._window
        np.copyto(window, self._hann)
        half_w, half_h, mid = MASK_MARGIN * box[2] * s / 2, MASK_MARGIN * box[3] * s / 2, RING_PIXELS / 2
        window[int(max(0, mid - half_h)):int(min(RING_PIXELS, mid + half_h + 1)),
               int(max(0, mid - half_w)):int(min(RING_PIXELS, mid + half_w + 1))] = 0
        (dx, dy), response = cv2.phaseCorrelate(before, after, window)
        if not (response >= MIN_RESPONSE and math.isfinite(dx) and math.isfinite(dy)):
            return None
        return dx / s, dy / s
