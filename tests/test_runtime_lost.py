"""The lost/found state machine on its own."""

from __future__ import annotations

import numpy as np
import pytest

from dadiff.runtime.config import Params
from dadiff.runtime.lost import LostMonitor

PARAMS = Params(
    lr=0.4,
    penalty_k=0.1,
    window_influence=0.4,
    uncertain_score=0.5,
    lost_score=0.25,
    lost_frames=3,
    search_growth=1.25,
    search_growth_max=2.5,
    score_smoothing=1.0,  # the raw score decides, one threshold: the lost/found logic on its own
    track_score=0.5,
)
SMOOTHED = Params(lr=0.4, penalty_k=0.1, window_influence=0.4)  # the runtime defaults


def _run(scores: list[float], params: Params = PARAMS) -> tuple[list[str], list[float]]:
    monitor = LostMonitor(params)
    states, growth = [], []
    for s in scores:
        states.append(monitor.observe(s))
        growth.append(round(monitor.growth, 4))
    return states, growth


def _flips(states: list[str]) -> int:
    return sum(a != b for a, b in zip(states, states[1:], strict=False))


def test_states_and_sawtooth_growth() -> None:
    states, growth = _run([0.9, 0.4, 0.1, 0.1, 0.1, 0.1, 0.3, 0.1, 0.1, 0.1, 0.1, 0.8])
    assert states == [
        "tracking",
        "uncertain",
        "uncertain",
        "uncertain",
        "lost",
        "lost",
        "lost",
        "lost",
        "lost",
        "lost",
        "lost",
        "tracking",
    ]
    # grows ×1.25 per lost frame, one frame at the 2.5 cap, then restarts from the normal size
    assert growth == [1, 1, 1, 1, 1.25, 1.5625, 1.9531, 2.4414, 2.5, 1.0, 1.25, 1.0]


def test_mid_scores_break_the_low_streak() -> None:
    states, _ = _run([0.1, 0.1, 0.3, 0.1, 0.1, 0.1])
    assert states == ["uncertain", "uncertain", "uncertain", "uncertain", "uncertain", "lost"]


def test_lost_score_zero_never_loses() -> None:
    params = Params(lr=0.4, penalty_k=0.1, window_influence=0.4, lost_score=0.0)
    states, growth = _run([0.0] * 20, params)
    assert set(states) == {"uncertain"} and set(growth) == {1.0}


@pytest.mark.parametrize("cap", [1.0, 1.2])
def test_growth_never_exceeds_the_cap(cap: float) -> None:
    params = Params(lr=0.4, penalty_k=0.1, window_influence=0.4, lost_frames=1, search_growth_max=cap)
    _, growth = _run([0.0] * 10, params)
    assert max(growth) <= cap


def test_scores_hovering_at_the_threshold_do_not_flip_the_state() -> None:
    # Frame-to-frame flicker between 0.35 and 0.65 around uncertain_score 0.5, as on a static scene.
    rng = np.random.default_rng(0)
    scores = list(rng.uniform(0.35, 0.65, 100))
    raw, _ = _run(scores, PARAMS)
    smoothed, _ = _run(scores, SMOOTHED)
    assert _flips(raw) > 20  # one threshold on the raw score flips at frame rate
    assert _flips(smoothed) <= 2


def test_hysteresis_enter_high_leave_low() -> None:
    monitor = LostMonitor(SMOOTHED)
    between = (SMOOTHED.uncertain_score + SMOOTHED.track_score) / 2  # 0.875: between leaving and entering
    for _ in range(40):
        monitor.observe(0.3)
    assert monitor.state == "uncertain" and monitor.confidence == pytest.approx(0.3, abs=1e-3)
    states = [monitor.observe(0.99) for _ in range(15)]
    assert states[:2] == ["uncertain"] * 2 and states[-1] == "tracking"  # entering waits for the confidence
    for _ in range(40):
        assert monitor.observe(between) == "tracking"  # keeps it: above the leaving threshold
    for _ in range(40):
        monitor.observe(0.3)
    for _ in range(40):  # but does not enter it: below the entering threshold
        assert monitor.observe(between) == "uncertain"


def test_found_again_moves_the_box_before_the_label_says_tracking() -> None:
    """`found_score` ends 'lost' (the tracker follows the target again); the label waits for the confidence."""
    monitor = LostMonitor(SMOOTHED)
    for _ in range(SMOOTHED.lost_frames):
        monitor.observe(0.1)
    assert monitor.state == "lost"
    assert SMOOTHED.found_score <= 0.6 < SMOOTHED.uncertain_score
    assert monitor.observe(0.6) == "uncertain" and monitor.growth == 1.0


def test_a_clear_failure_leaves_tracking_at_once() -> None:
    monitor = LostMonitor(SMOOTHED)
    for _ in range(10):
        monitor.observe(0.95)
    assert monitor.observe(0.1) == "uncertain"  # below lost_score: no smoothing delay
    assert monitor.confidence > 0.5


def test_implausible_box_is_never_tracking() -> None:
    monitor = LostMonitor(SMOOTHED)
    states = [monitor.observe(0.999, plausible=False) for _ in range(20)]
    assert set(states) == {"uncertain"} and monitor.confidence < 0.05
    assert monitor.growth == 1.0  # the box still follows the network: it may shrink back


def test_released_params_use_the_raw_score() -> None:
    params = Params(lr=0.4, penalty_k=0.1, window_influence=0.4, lost_score=0.0)
    states, _ = _run([0.9, 0.4, 0.9, 0.4], params)
    assert states == ["tracking", "uncertain", "tracking", "uncertain"]
