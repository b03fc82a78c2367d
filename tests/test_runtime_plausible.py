"""Plausibility of the tracker's output: bounded size changes, frame-covering boxes, a steady state."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dadiff.runtime import Tracker
from dadiff.runtime.config import Params
from dadiff.runtime.tracker import bound_size
from runtime_models import STRIDE8_META

CENTRE = (12, 12)  # the cell at the crop centre (point (0, 0))


class ScriptedBackend:
    """Every cell scores ~0 but the centre one, which scores `scores[k]` on search call k and proposes a
    box of `half` crop pixels either side of its point: no motion, a size the test chooses."""

    def __init__(self, scores: list[float], half: float) -> None:
        self.meta = dict(STRIDE8_META)
        self.scores, self.half, self.calls = scores, half, 0

    def template(self, z: np.ndarray) -> dict[str, np.ndarray]:
        return {"kcls0": np.ones(1, np.float32)}

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        score = self.scores[self.calls % len(self.scores)]
        self.calls += 1
        cls = np.zeros((1, 2, 25, 25), np.float32)
        cls[0, 1] = -20.0
        cls[0, 1][CENTRE] = math.log(score / (1 - score))
        loc = np.full((1, 4, 25, 25), self.half, np.float32)
        return cls, loc


FRAME = np.full((360, 480, 3), 90, np.uint8)


def _track(backend: ScriptedBackend, box: tuple[float, ...], frames: int, **overrides: object) -> list:
    tracker = Tracker(backend, overrides=overrides)
    tracker.init(FRAME, box)
    return [tracker.update(FRAME) for _ in range(frames)]


def _flips(states: list[str]) -> int:
    return sum(a != b for a, b in zip(states, states[1:], strict=False))


def _steady_half(w: float, h: float) -> float:
    """Half size in crop pixels of a w×h target, so that the box keeps its size (square targets)."""
    pad = (w + h) / 2
    return w * 127 / math.sqrt((w + pad) * (h + pad)) / 2


def test_static_scene_state_is_steady() -> None:
    # The same frame 100 times; the score flickers around uncertain_score as the crop shifts by a pixel.
    threshold = Params(lr=0.4, penalty_k=0.1, window_influence=0.4).uncertain_score
    scores = list(np.random.default_rng(1).uniform(threshold - 0.1, min(threshold + 0.1, 0.999), 100))
    results = _track(ScriptedBackend(scores, _steady_half(40, 40)), (200, 150, 40, 40), 100)
    assert _flips([r.state for r in results]) <= 2
    assert [r.score for r in results] == pytest.approx(scores, rel=1e-5)  # score stays the raw one
    released = _track(ScriptedBackend(scores, _steady_half(40, 40)), (200, 150, 40, 40), 100, lost_score=0)
    assert _flips([r.state for r in released]) > 20


def test_scale_change_per_frame_is_bounded() -> None:
    # The network proposes a box ~4x the current one on every frame, with full confidence.
    results = _track(ScriptedBackend([0.999], 120.0), (200, 150, 20, 16), 40)
    sizes = [(20.0, 16.0)] + [r.box[2:] for r in results]
    for (w0, h0), (w1, h1) in zip(sizes, sizes[1:], strict=False):
        assert 1 / 1.1 - 1e-9 <= w1 / w0 <= 1.1 + 1e-9 and 1 / 1.1 - 1e-9 <= h1 / h0 <= 1.1 + 1e-9
    w, h = sizes[-1]
    assert math.sqrt(w * h / (20 * 16)) == pytest.approx(8.0)  # stops at max_scale_change of the start
    assert results[-1].state == "uncertain" and results[-1].score > 0.99  # held at the limit: not trusted
    assert w / h / (20 / 16) <= 4.0 + 1e-9 and w <= 480 and h <= 360
    grown = _track(ScriptedBackend([0.999], 120.0), (200, 150, 20, 16), 40, lost_score=0)
    assert grown[-1].box[2:] == (480, 360)  # the released tracker grows to the frame


def test_box_grown_to_the_frame_is_not_tracking() -> None:
    # A large target: 8x its size would exceed the frame; the box is clipped to the frame, and a box
    # covering more than half of it is not a plausible track, however high the score.
    results = _track(ScriptedBackend([0.9999], 120.0), (100, 60, 120, 90), 60)
    covering = [r for r in results if r.box[2] * r.box[3] > 0.5 * 480 * 360]
    assert covering and all(r.state != "tracking" for r in covering)
    assert covering[-1].confidence < 0.05 and covering[-1].score > 0.999
    assert results[-1].box[2:] == (480, 360)  # never larger than the frame
    released = _track(ScriptedBackend([0.9999], 120.0), (100, 60, 120, 90), 60, lost_score=0)
    assert released[-1].state == "tracking"


def test_bound_size_keeps_both_bounds() -> None:
    p = Params(lr=0.4, penalty_k=0.1, window_influence=0.4)
    start = (20.0, 20.0)
    # at the scale limit already: growing further is refused, shrinking is allowed
    at_limit = (160.0, 160.0)
    assert bound_size((400.0, 400.0), at_limit, start, p) == pytest.approx((*at_limit, True))
    assert bound_size((100.0, 100.0), at_limit, start, p) == pytest.approx((160 / 1.1, 160 / 1.1, False))
    assert bound_size((30.0, 18.0), (25.0, 20.0), start, p) == pytest.approx((27.5, 20 / 1.1, False))  # step only
    # aspect: 4x the start's at most, however the network stretches it
    w, h = start
    for _ in range(50):
        w, h, held = bound_size((w * 3, h / 3), (w, h), start, p)
    assert (w / h) == pytest.approx(4.0) and math.sqrt(w * h) == pytest.approx(20.0) and held
