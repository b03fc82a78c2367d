"""The "real" night style against the statistics of real night drone video.

The numbers and their definitions come from /work/shared/notes/real-night-footage.md (UAVDark135 "person11"
and the first frames of DarkTrack2021's 110 sequences; median [10th-90th percentile] over frames):

| | mean luma | B / G / R means | share < 20 | share > 245 | noise in dark areas |
| UAVDark135 person11 | 11.5 [9.1-12.5] | 5.9 / 10.4 / 15.9 | 0.79 [0.75-0.92] | 2e-6 | 1.71 [1.61-1.84] |
| DarkTrack2021 | 23.5 [11.7-45.9] | 21.5 / 23.0 / 24.0 | 0.60 [0.14-0.84] | 0.0014 [1e-4-0.011] | 2.19 [1.33-3.63] |
| our classic night | 57.7 [40.9-71.8] | 47.9 / 56.9 / 59.1 | 0.036 | 3e-4 | 5.49 |

The bounds below hold the median over rendered frames inside the span of the two real sets' 10th-90th
percentiles: mean luma [9, 46] (9.1 .. 45.9), share < 20 [0.55, 0.92] (DarkTrack's median 0.60 less a margin
.. UAVDark's 0.92: the lower DarkTrack percentile, 0.14, is as bright as our classic night), share > 245 in
(0, 0.011] (non-zero but small), noise [1.2, 3.7] (1.33 .. 3.63). Sodium light: red / blue ~2.7 (person11).
The frames are rendered from scikit-image photos (no library needed).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dadiff.runtime.datamaking.camera_night import night_statistics  # the note's statistics, one frame
from dadiff.runtime.datamaking.night import NightLights, RealNight, render_night
from dadiff.runtime.datamaking.photos import load_photos
from dadiff.runtime.datamaking.scene import Scene
from dadiff.runtime.datamaking.scenes import make_sequence

pytest.importorskip("skimage")  # the scene photos

SIZE = (640, 360)
SCENES = range(300, 310)  # 10 scenes x 3 frames
FRAMES = 3


def _medians(frames: list[np.ndarray]) -> dict[str, float]:
    rows = [night_statistics(f) for f in frames]
    medians = {key: float(np.nanmedian([r[key] for r in rows])) for key in rows[0]}
    medians["red_blue"] = float(np.median([r["red"] / max(r["blue"], 1e-3) for r in rows]))
    return medians


@pytest.fixture(scope="module")
def real_frames() -> list[np.ndarray]:
    return [f for seed in SCENES for f in make_sequence(seed, frames=FRAMES, size=SIZE, night="real").night]


def test_real_night_matches_real_night_video(real_frames):
    m = _medians(real_frames)
    assert 9 <= m["mean"] <= 46, m
    assert 0.55 <= m["below_20"] <= 0.92, m
    assert 0 < m["above_245"] <= 0.011, m
    assert 1.2 <= m["noise"] <= 3.7, m
    assert m["red_blue"] > 1.2, m  # sodium light dominates, as in most real night streets
    means = [night_statistics(f)["mean"] for f in real_frames]
    assert max(means) < 57.7  # no frame as bright as the classic night's median


def test_single_frame_render_night_matches_too():
    photos = load_photos("test")
    frames = []
    for seed in range(12):
        day, _ = Scene.random(np.random.default_rng(seed), photos, size=SIZE, frames=1).render(0)
        frames.append(day)
    m = _medians([render_night(f, np.random.default_rng(50 + k)) for k, f in enumerate(frames)])
    assert 9 <= m["mean"] <= 46 and 0.55 <= m["below_20"] <= 0.92 and 1.2 <= m["noise"] <= 3.7, m


@pytest.mark.parametrize(("kind", "low", "high"), [("sodium", 2.0, 3.6), ("led", 0.75, 1.35)])
def test_light_colour(kind, low, high):
    photos = load_photos("test")
    ratios = []
    for seed in range(6):
        day, _ = Scene.random(np.random.default_rng(seed), photos, size=SIZE, frames=1).render(0)
        rng = np.random.default_rng(seed)
        camera = RealNight.random(rng, kind=kind)
        lights = NightLights.random(rng, kind, *SIZE).at(None, 0, *SIZE)
        s = night_statistics(camera.apply(day, rng, lights))
        ratios.append(s["red"] / s["blue"])
    assert low <= float(np.median(ratios)) <= high, ratios


def test_the_classic_night_is_what_the_note_measured():
    frames = make_sequence(301, frames=2, size=SIZE).night  # classic: the seeded benchmark's style
    m = _medians(frames)
    assert m["mean"] > 30 and m["below_20"] < 0.3, m  # too bright: why the "real" style exists


def test_night_statistics_definition() -> None:
    frame = np.zeros((64, 64, 3), np.uint8)
    frame[:, :32] = (5, 10, 15)  # luma 11: dark
    frame[:32, 32:] = 250  # bright; the remaining quarter stays black
    st = night_statistics(frame)
    assert set(st) == {"mean", "blue", "green", "red", "below_20", "above_245", "noise"}
    assert st["blue"] == pytest.approx(5 / 2 + 250 / 4)
    assert st["red"] == pytest.approx(15 / 2 + 250 / 4)
    assert st["mean"] == pytest.approx(11 / 2 + 250 / 4)
    assert st["below_20"] == pytest.approx(0.75)
    assert st["above_245"] == pytest.approx(0.25)
    flat = night_statistics(np.full((32, 32, 3), 10, np.uint8))
    assert flat["noise"] == pytest.approx(0.0, abs=1e-4)
    grain = np.random.default_rng(0).normal(15, 3, (64, 64, 1)).clip(0, 255).astype(np.uint8).repeat(3, axis=2)
    assert 1.5 < night_statistics(grain)["noise"] < 3.0  # white noise of std 3, minus its sigma-2 blur
    assert math.isnan(night_statistics(np.full((32, 32, 3), 200, np.uint8))["noise"])
