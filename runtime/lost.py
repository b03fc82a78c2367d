"""Lost/found state machine: labels each frame and decides how far the next search region reaches."""

from __future__ import annotations

from .config import Params

TRACKING, UNCERTAIN, LOST = "tracking", "uncertain", "lost"


class LostMonitor:
    """Turns per-frame scores into 'tracking' / 'uncertain' / 'lost' and a search-region growth factor.

    Lost and found follow the raw score: `lost_frames` consecutive scores below `lost_score` mean lost;
    while lost the search region grows by `search_growth` per frame up to `search_growth_max`, and after
    one frame at that cap starts again from the normal size (a sawtooth), until a score reaches
    `found_score` again. The restart matters because a wide region shows the target small, which a
    network may not detect: near and wide searches keep alternating.

    'tracking' versus 'uncertain' follows `confidence`, an EMA of the score (zero for an implausible box),
    with hysteresis: enter at `track_score`, leave below `uncertain_score`. The raw score flickers from frame
    to frame as the crop shifts by a pixel, and a follow controller should not switch at that rate. A raw
    score below `lost_score` is never 'tracking', so a clear failure shows at once. With `lost_score=0`
    (the released tracker) the label is the raw score against `uncertain_score` and nothing is lost.
    """

    def __init__(self, params: Params) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        """Forget the history (new target): the init box is taken as certain."""
        self.state = TRACKING
        self.growth = 1.0
        self.confidence = 1.0
        self._low = 0

    @property
    def lost(self) -> bool:
        return self.state == LOST

    def observe(self, score: float, plausible: bool = True) -> str:
        """Record one frame's best score (and whether its box is plausible) and return its state;
        `growth` then applies to the next crop."""
        p = self.params
        if p.released:
            self.confidence = score
            self.state = TRACKING if score >= p.uncertain_score else UNCERTAIN
            return self.state
        self._smooth(score if plausible else 0.0)
        if self._lost_step(score):
            return self.state
        self.state = TRACKING if plausible and score >= p.lost_score and self._confident() else UNCERTAIN
        return self.state

    def demote(self) -> str:
        """This frame is not 'tracking' whatever its score (a box standing still on the ground, runtime/still.py);
        'uncertain' instead, from which the next confident frame enters 'tracking' again."""
        if self.state == TRACKING:
            self.state = UNCERTAIN
        return self.state

    def _smooth(self, score: float) -> None:
        a = self.params.score_smoothing
        self.confidence = a * score + (1.0 - a) * self.confidence

    def _confident(self) -> bool:
        """Hysteresis on the confidence: staying in 'tracking' needs less than entering it."""
        p = self.params
        threshold = p.uncertain_score if self.state == TRACKING else max(p.track_score, p.uncertain_score)
        return self.confidence >= threshold

    def _lost_step(self, score: float) -> bool:
        """Advance the lost streak and the search growth; True when the frame is (still) lost."""
        p = self.params
        if score >= p.found_score:
            self._low, self.growth = 0, 1.0
            return False
        if self.state == LOST:
            self.growth = 1.0 if self.growth >= p.search_growth_max else min(
                self.growth * p.search_growth, p.search_growth_max)
            return True
        if score < p.lost_score:
            self._low += 1
            if self._low >= p.lost_frames:
                self.state = LOST
                self.growth = min(p.search_growth, p.search_growth_max)
                return True
        else:
            self._low = 0
        return False
