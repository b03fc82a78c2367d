"""A box that leaves its target for something of other colours (runtime/swap.py): swapped once the median of
its distances to the start box's colours passes the bound, back when it returns; silent on grey pictures,
for a target whose colours stay and for one whose colours wander from the start; and the tracker reports
such a frame 'uncertain'."""

from __future__ import annotations

import numpy as np
import pytest
from test_runtime_plausible import ScriptedBackend

from dadiff.runtime import Tracker
from dadiff.runtime.errors import InputError
from dadiff.runtime.swap import SwapCheck, colour_histogram

RED_OVER_BLUE = ((40, 40, 200), (200, 60, 30))  # BGR: a red jacket over blue jeans
GREEN_OVER_GREY = ((40, 180, 40), (128, 128, 128))
BOX = (100.0, 100.0, 30.0, 60.0)  # centre x, centre y, w, h


def _person(upper: tuple[int, int, int], lower: tuple[int, int, int], seed: int = 0) -> np.ndarray:
    """A 200 x 200 frame of noisy grey ground with a 30 x 60 figure at BOX: `upper` over `lower`."""
    rng = np.random.default_rng(seed)
    frame = rng.integers(60, 120, size=(200, 200, 3)).astype(np.uint8)
    figure = np.empty((60, 30, 3), np.int16)
    figure[:30], figure[30:] = upper, lower
    figure += rng.integers(-12, 13, size=figure.shape).astype(np.int16)
    frame[70:130, 85:115] = np.clip(figure, 0, 255).astype(np.uint8)
    return frame


def _verdicts(frames: list[np.ndarray]) -> list[bool]:
    check = SwapCheck(frames=9, distance=0.6)
    return [check.observe(frame, BOX) for frame in frames]


def test_a_target_whose_colours_stay_is_never_swapped() -> None:
    frames = [_person(*RED_OVER_BLUE, seed=i) for i in range(40)]
    assert not any(_verdicts(frames))


def test_a_box_on_other_colours_is_swapped_after_half_the_window_and_back_when_it_returns() -> None:
    frames = ([_person(*RED_OVER_BLUE, seed=i) for i in range(20)]
              + [_person(*GREEN_OVER_GREY, seed=i) for i in range(20, 40)]
              + [_person(*RED_OVER_BLUE, seed=i) for i in range(40, 60)])
    said = _verdicts(frames)
    assert not any(said[:24])  # after 10 frames that measure the wander, the median of 9 needs 5 on the others
    assert all(said[25:40])
    assert not any(said[45:])


def test_a_target_whose_own_colours_wander_raises_the_bound() -> None:
    """A dim figure whose colours change every frame (the hue of dark pixels is noise): most of its boxes lie
    over 0.6 from the start, which a fixed bound would call a swap; the first frames measure that wander."""

    def flicker(seed: int) -> np.ndarray:
        rng = np.random.default_rng(seed)
        upper, lower = (tuple(int(v) for v in rng.integers(0, 40, 3)) for _ in range(2))
        return _person(upper, lower, seed)

    frames = [flicker(i) for i in range(60)]
    start = colour_histogram(frames[0], BOX)
    distances = [float(np.sqrt(1 - np.sqrt(start * colour_histogram(f, BOX)).sum())) for f in frames[1:]]
    assert np.median(distances) > 0.7
    assert not any(_verdicts(frames))


def test_the_halves_count_a_figure_upside_down_as_other_colours() -> None:
    start = colour_histogram(_person(*RED_OVER_BLUE), BOX)
    flipped = colour_histogram(_person(*RED_OVER_BLUE[::-1]), BOX)
    assert start is not None and flipped is not None
    assert float(np.sqrt(1 - np.sqrt(start * flipped).sum())) > 0.6


def test_grey_pictures_and_boxes_off_the_frame_say_nothing() -> None:
    grey = [_person((90, 90, 90), (200, 200, 200), seed=i)[:, :, 0] for i in range(30)]
    assert not any(_verdicts(grey))
    assert colour_histogram(_person(*RED_OVER_BLUE), (900.0, 900.0, 30.0, 60.0)) is None
    assert colour_histogram(_person(*RED_OVER_BLUE), (float("nan"), 100.0, 30.0, 60.0)) is None


def test_the_tracker_reports_a_swapped_box_uncertain_unless_told_not_to(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(SwapCheck, "observe", lambda self, image, box: True)
    frame = _person(*RED_OVER_BLUE)
    states = {}
    for name, overrides in (("default", {}), ("off", {"swap_frames": 0}), ("released", {"lost_score": 0})):
        tracker = Tracker(ScriptedBackend([0.97], 20.0), overrides={"still_frames": 0, **overrides})
        tracker.init(frame, (85.0, 70.0, 30.0, 60.0))
        states[name] = [tracker.update(frame).state for _ in range(3)]
    assert states == {"default": ["uncertain"] * 3, "off": ["tracking"] * 3, "released": ["tracking"] * 3}


@pytest.mark.parametrize(("key", "value"), [("swap_frames", 2.5), ("swap_frames", -1), ("swap_distance", 1.5)])
def test_swap_settings_are_checked(key: str, value: float) -> None:
    with pytest.raises(InputError, match=key):
        Tracker(ScriptedBackend([0.9], 20.0), overrides={key: value})
