"""Lost/found state machine: labels each frame and decides how far the next search region reaches."""

from __future__ import annotations

from .config import Params

TRACKING, UNCERTAIN, LOST = "tracking", "uncertain", "lost"


class LostMonitor:
    """Turns per-frame scores into 'tracking' / 'uncertain' / 'lost' and a search-region growth factor.

    A score at or above `uncertain_score` means tracking. `lost_frames` consecutive scores below
    `lost_score` mean lost; while lost the search region grows by `search_growth` per frame up to
    `search_growth_max`, and after one frame at that cap starts again from the normal size (a sawtooth),
    until a score reaches `uncertain_score` again. The restart matters because a wide region shows the
    target small, which a network may not detect: near and wide searches keep alternating. Scores in
    between are 'uncertain' (and keep a lost tracker lost: recovery needs a confident frame).
    """

    def __init__(self, params: Params) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        """Forget the history (new target)."""
        self.state = TRACKING
        self.growth = 1.0
        self._low = 0

    @property
    def lost(self) -> bool:
        return self.state == LOST

    def observe(self, score: float) -> str:
        """Record one frame's best score and return its state; `growth` then applies to the next crop."""
        p = self.params
        if score >= p.uncertain_score:
            self._low = 0
            self.state, self.growth = TRACKING, 1.0
        elif self.state == LOST:
            if self.growth >= p.search_growth_max:
                self.growth = 1.0
            else:
                self.growth = min(self.growth * p.search_growth, p.search_growth_max)
        elif score < p.lost_score:
            self._low += 1
            if self._low >= p.lost_frames:
                self.state = LOST
                self.growth = min(p.search_growth, p.search_growth_max)
            else:
                self.state = UNCERTAIN
        else:
            self._low = 0
            self.state = UNCERTAIN
        return self.state
