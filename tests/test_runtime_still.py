"""A box standing still on the ground around it (runtime/still.py): still after it stops on the ground, also
while a hovering camera sways; never while a followed target stays put in the picture over flowing ground,
nor for a target chosen while it stands; and the tracker reports such a frame 'uncertain'."""

from __future__ import annotations

import numpy as np
import pytest
from test_runtime_motion import _ground
from test_runtime_plausible import ScriptedBackend

from dadiff.runtime import Tracker
from dadiff.runtime.errors import InputError
from dadiff.runtime.still import StillCheck

SIZE = 24  # the object's side (px)


def _frame(ground: np.ndarray, camera: tuple[int, int], thing: tuple[int, int]) -> np.ndarray:
    """The 480 x 360 view of a camera at `camera` (ground px of its top-left corner) with a bright square on
    the ground at `thing` (ground px of its centre)."""
    world = ground.copy()
    x, y = thing
    world[y - SIZE // 2 : y + SIZE // 2, x - SIZE // 2 : x + SIZE // 2] = (60, 200, 250)
    cx, cy = camera
    return np.ascontiguousarray(world[cy : cy + 360, cx : cx + 480])


def _stills(cameras: list[tuple[int, int]], things: list[tuple[int, int]]) -> list[bool]:
    """What StillCheck says each frame for a box exactly on the object (frame 0 is the start)."""
    ground, check = _ground(), StillCheck(frames=30, travel=0.15)
    out = []
    for camera, thing in zip(cameras, things, strict=True):
        box = (thing[0] - camera[0], thing[1] - camera[1], SIZE, SIZE)
        out.append(check.observe(_frame(ground, camera, thing), box))
    return out


def test_a_box_that_stops_on_the_ground_is_still_after_the_window() -> None:
    things = [(200 + 3 * min(i, 20), 250) for i in range(70)]  # walks 20 frames, then stands
    said = _stills([(100, 100)] * 70, things)
    assert not any(said[:48])  # moving, then standing for fewer than 30 frames (3 px steps, 3.6 px allowed)
    assert all(said[52:])


def test_a_box_that_stops_is_still_while_a_hovering_camera_sways() -> None:
    """The picture sways by a pixel each way (a hovering drone's steadied gimbal): the ring's reads take the
    sway out. (Sways of 2-3 px a frame make reads of this 24 px box's ground miss by as much as the 3.6 px
    allowed, and the check then stays silent on some frames: it fails towards 'tracking'.)"""
    rng = np.random.default_rng(5)
    cameras = [(100 + int(x), 100 + int(y)) for x, y in rng.integers(-1, 2, size=(70, 2))]
    things = [(300 + 3 * min(i, 20), 250) for i in range(70)]
    said = _stills(cameras, things)
    assert not any(said[:48])
    assert all(said[52:])


def test_a_followed_target_over_flowing_ground_is_never_still() -> None:
    """The camera keeps the walking target at the same place in the picture: still in the picture, not
    on the ground."""
    things = [(300 + 3 * i, 250) for i in range(70)]
    cameras = [(100 + 3 * i, 100) for i in range(70)]
    assert not any(_stills(cameras, things))


def test_a_target_chosen_while_it_stands_is_not_still_until_it_has_moved() -> None:
    things = [(300, 250)] * 40 + [(300 + 3 * i, 250) for i in range(1, 16)] + [(345, 250)] * 40
    said = _stills([(100, 100)] * len(things), things)
    assert not any(said[:80])  # a parked car picked by the operator stays a lock
    assert all(said[87:])  # once it has moved and stood again for 30 frames


def test_the_tracker_reports_a_still_box_uncertain_unless_told_not_to(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(StillCheck, "observe", lambda self, image, box: True)
    frame = _frame(_ground(), (100, 100), (300, 250))
    states = {}
    for name, overrides in (("default", {}), ("off", {"still_frames": 0}), ("released", {"lost_score": 0})):
        tracker = Tracker(ScriptedBackend([0.97], 20.0), overrides=overrides)
        tracker.init(frame, (188.0, 138.0, 24.0, 24.0))
        states[name] = [tracker.update(frame).state for _ in range(3)]
    assert states == {"default": ["uncertain"] * 3, "off": ["tracking"] * 3, "released": ["tracking"] * 3}


@pytest.mark.parametrize(("key", "value"), [("still_frames", 2.5), ("still_frames", -1), ("still_travel", -0.1)])
def test_still_settings_are_checked(key: str, value: float) -> None:
    with pytest.raises(InputError, match=key):
        Tracker(ScriptedBackend([0.9], 20.0), overrides={key: value})
