"""Moving the search region with the whole picture (`motion_compensation`, runtime/motion.py): the read
shift of a textured frame, no read on a flat one, and the tracker's box carried along only when asked."""

from __future__ import annotations

import numpy as np
import pytest
from test_runtime_plausible import ScriptedBackend

from dadiff.runtime import Tracker
from dadiff.runtime.errors import InputError
from dadiff.runtime.motion import PictureMotion


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


def test_the_tracker_moves_its_search_region_with_the_picture_only_when_asked() -> None:
    """The scripted network always answers the crop's centre (it never finds anything by itself): with
    compensation the box follows a picture moved 30 px, without it the box stays, and the released tracker
    (lost_score 0) ignores the setting."""
    ground = _ground()
    box = (200.0, 150.0, 40.0, 40.0)

    def centre_after(**overrides: object) -> tuple[float, float]:
        tracker = Tracker(ScriptedBackend([0.95], 20.0), overrides=overrides)
        tracker.init(_view(ground, 0, 0), box)
        x, y, w, h = tracker.update(_view(ground, 30, -12)).box
        return x + w / 2, y + h / 2

    still = centre_after()
    moved = centre_after(motion_compensation=0.2)
    assert moved == pytest.approx((still[0] + 30, still[1] - 12), abs=3.0)
    assert centre_after(motion_compensation=0.2, lost_score=0) == pytest.approx(still)


def test_motion_compensation_is_checked() -> None:
    with pytest.raises(InputError, match="motion_compensation"):
        Tracker(ScriptedBackend([0.9], 20.0), overrides={"motion_compensation": 2})
