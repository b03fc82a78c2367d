"""Moving the search region with the whole picture's jolts (`motion_compensation`, runtime/motion.py): the
read shift of a textured frame, no read on a flat one, a jolt only where the shift departs from the steady
motion, and the tracker's box carried along by a jolt unless told not to."""

from __future__ import annotations

import numpy as np
import pytest
from test_runtime_plausible import ScriptedBackend

from dadiff.runtime import Tracker
from dadiff.runtime.errors import InputError
from dadiff.runtime.motion import TREND_READS, PictureMotion


def _ground(seed: int = 0) -> np.ndarray:
    """A dark textured ground with a few bright lamps, larger than the frames cut from it."""
    rng = np.random.default_rng(seed)
    ground = (rng.random((600, 800)) * 40).astype(np.float32)
    ground = np.clip(np.kron(ground[::4, ::4], np.ones((4, 4))) + rng.normal(0, 3, (600, 800)), 0, 255)
    for x, y in rng.integers((50, 50), (750, 550), size=(12, 2)):
        ground[y - 6 : y + 6, x - 6 : x + 6] = 250
    return np.repeat(ground[..., None], 3, axis=2).astype(np.uint8)


def _view(ground: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """The 480 x 360 frame of a camera whose picture moved (dx, dy) px: the ground seen from 100 + (-dx, -dy)."""
    return np.ascontiguousarray(ground[100 - dy : 460 - dy, 100 - dx : 580 - dx])


@pytest.mark.parametrize(("dx", "dy"), [(24, -16), (-40, 8), (0, 0)])
def test_the_picture_shift_is_read_in_frame_pixels(dx: int, dy: int) -> None:
    ground, motion = _ground(), PictureMotion(0.2)
    motion.reset(_view(ground, 0, 0))
    read = motion.shift(_view(ground, dx, dy))
    assert read is not None and read == pytest.approx((dx, dy), abs=3.0)


def test_a_changed_picture_gives_no_read_and_a_flat_one_no_motion() -> None:
    rng = np.random.default_rng(1)
    motion = PictureMotion(0.2)
    motion.reset(rng.normal(90, 20, (360, 480, 3)).astype(np.uint8))
    assert motion.shift(rng.normal(90, 20, (360, 480, 3)).astype(np.uint8)) is None  # nothing in common
    flat = np.full((360, 480, 3), 90, np.uint8)
    motion.reset(flat)
    read = motion.shift(flat + rng.integers(0, 2, flat.shape, dtype=np.uint8))
    assert read is None or np.hypot(*read) < 1.0
    assert PictureMotion(0.2).shift(flat) is None  # nothing to compare with yet


def _jolts(steps: list[tuple[int, int]]) -> list[tuple[float, float] | None]:
    """What `jolt` says for a camera whose picture moves by each of `steps` in turn (frame px)."""
    ground, motion = _ground(), PictureMotion(0.2)
    x = y = 0
    motion.reset(_view(ground, x, y))
    out = []
    for dx, dy in steps:
        x, y = x + dx, y + dy
        out.append(motion.jolt(_view(ground, x, y)))
    return out


def test_a_steady_drift_is_no_jolt_and_a_gust_on_top_of_it_is() -> None:
    """A drone following its target drifts steadily: no jolt. A gust's 30 px steps on top of that drift
    are jolts of 30 px, the drift left out, and the drift after it is steady again."""
    drift = [(-4, 1)] * 14
    assert _jolts(drift) == [None] * 14
    read = _jolts(drift + [(-34, 1)] * 3 + drift[:4])
    for jolt in read[14:17]:
        assert jolt is not None and jolt == pytest.approx((-30, 0), abs=3.0)
    assert read[:14] == [None] * 14 and read[17:] == [None] * 4


def test_a_lasting_change_of_motion_stops_being_a_jolt() -> None:
    """A drone that turns back drifts the other way from then on: jolts for at most half the trend's
    reads, then steady."""
    read = _jolts([(6, 0)] * 12 + [(-6, 0)] * 12)
    jolts = [k for k, jolt in enumerate(read) if jolt is not None]
    assert jolts and jolts[0] == 12 and len(jolts) <= TREND_READS // 2 + 1


def test_a_new_frame_size_starts_the_steady_motion_again() -> None:
    """Shifts read at another frame size are in other pixels: after a size change the steady motion is
    learnt anew, and a steady drift at the new size is no jolt."""
    ground, motion = _ground(), PictureMotion(0.2)
    motion.reset(_view(ground, 0, 0))
    for x in range(-30, -150, -30):  # a steady 30 px a frame at 480 px wide
        assert motion.jolt(_view(ground, x, 0)) is None
    half = [np.ascontiguousarray(_view(ground, x, 0)[::2, ::2]) for x in (-150, -154, -158, -162)]
    assert [motion.jolt(frame) for frame in half] == [None] * 4  # 2 px a frame at 240 px wide


def test_the_tracker_moves_its_search_region_with_a_jolt_unless_told_not_to() -> None:
    """The scripted network always answers the crop's centre (it never finds anything by itself): by
    default the box follows a picture jolted 30 px after a still hover, with `motion_compensation=0` it
    stays, and the released tracker (lost_score 0) ignores the setting."""
    ground = _ground()
    box = (200.0, 150.0, 40.0, 40.0)

    def centre_after(**overrides: object) -> tuple[float, float]:
        tracker = Tracker(ScriptedBackend([0.95], 20.0), overrides=overrides)
        tracker.init(_view(ground, 0, 0), box)
        for _ in range(4):
            tracker.update(_view(ground, 0, 0))
        x, y, w, h = tracker.update(_view(ground, 30, -12)).box
        return x + w / 2, y + h / 2

    still = centre_after(motion_compensation=0)
    moved = centre_after()  # on by default
    assert moved == pytest.approx((still[0] + 30, still[1] - 12), abs=3.0)
    assert centre_after(lost_score=0) == pytest.approx(still)


def test_motion_compensation_is_checked() -> None:
    with pytest.raises(InputError, match="motion_compensation"):
        Tracker(ScriptedBackend([0.9], 20.0), overrides={"motion_compensation": 2})
