"""The lost/found state machine on its own."""

from __future__ import annotations

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
)


def _run(scores: list[float], params: Params = PARAMS) -> tuple[list[str], list[float]]:
    monitor = LostMonitor(params)
    states, growth = [], []
    for s in scores:
        states.append(monitor.observe(s))
        growth.append(round(monitor.growth, 4))
    return states, growth


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
