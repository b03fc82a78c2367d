"""The "sensor" night renderer: deterministic, fixed look per sequence, fresh noise per frame, real-night statistics."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.datamaking import sensor_night
from dadiff.runtime.datamaking.camera_night import night_statistics  # the note's statistics, one frame
from dadiff.runtime.datamaking.sensor_night import MODEL, render_night

# Medians and ranges of real night UAV footage (UAVDark135, DarkTrack2021) that rendered daylight photos must reach.
REAL = {"mean": (8.0, 30.0), "below_20": (0.5, 0.9), "noise": (0.8, 4.0)}


def _photos() -> list[np.ndarray]:
    """Daylight photos shipped with scikit-image, as 320x240 BGR frames (the test skips without it)."""
    data = pytest.importorskip("skimage.data")
    out = []
    for name in ("astronaut", "coffee", "chelsea", "rocket"):
        rgb = getattr(data, name)()
        out.append(cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), (320, 240), interpolation=cv2.INTER_AREA))
    return out


def _street(h: int = 120, w: int = 160, seed: int = 0) -> np.ndarray:
    """A synthetic daylight frame: sky, textured road and walls, so tests without scikit-image have something real."""
    rng = np.random.default_rng(seed)
    img = np.empty((h, w, 3), np.uint8)
    img[: h // 3] = (220, 190, 160)  # sky, BGR
    img[h // 3 :] = (110, 115, 120)
    noise = rng.normal(0, 18, (h, w, 1))
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def test_output_shape_dtype_and_model_name() -> None:
    day = [_street(seed=i) for i in range(3)]
    night, rec = render_night(day, [1])
    assert MODEL == "sensor" and rec["model"] == MODEL
    assert len(night) == 3
    for f in night:
        assert f.shape == day[0].shape and f.dtype == np.uint8
    assert rec["n_frames"] == 3 and rec["size"] == [160, 120]
    assert len(rec["gain_per_frame"]) == 3


def test_deterministic_for_a_seed_and_different_for_another() -> None:
    day = [_street(seed=i) for i in range(3)]
    a, rec_a = render_night(day, [5, 7])
    b, rec_b = render_night(day, [5, 7])
    assert rec_a == rec_b
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    c, rec_c = render_night(day, [5, 8])
    assert rec_c != rec_a
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))


def test_mismatched_frame_sizes_raise() -> None:
    day = [_street(120, 160), _street(120, 160), _street(100, 160)]
    with pytest.raises(ValueError, match=r"frame 2.*160x100.*160x120"):
        render_night(day, [0])
    with pytest.raises(ValueError, match="frame 0"):
        render_night([np.zeros((10, 10), np.uint8)], [0])


def _walk_floats(x: object) -> list[float]:
    if isinstance(x, float):
        return [x]
    if isinstance(x, dict):
        return [f for v in x.values() for f in _walk_floats(v)]
    if isinstance(x, list):
        return [f for v in x for f in _walk_floats(v)]
    return []


def test_record_is_json_and_rounded() -> None:
    _, rec = render_night([_street()] * 2, [3])
    assert json.loads(json.dumps(rec)) == rec
    floats = _walk_floats(rec)
    assert floats and all(f == round(f, 4) for f in floats)
    for key in ("lights", "illumination_fraction", "bayer", "adc_bits", "ae", "awb", "tone", "denoise", "jpeg_quality"):
        assert key in rec
    assert 1 / 300 <= rec["illumination_fraction"] <= 1 / 30
    assert 15 <= rec["jpeg_quality"] <= 55


def test_look_does_not_depend_on_length_or_frames() -> None:
    """Every drawn parameter is per sequence: a shorter or different sequence with the same seed has the same look."""
    per_frame = {"n_frames", "gain_per_frame", "size"}
    _, long_rec = render_night([_street(seed=i) for i in range(6)], [11])
    _, short_rec = render_night([_street(seed=9)] * 2, [11])
    assert {k: v for k, v in long_rec.items() if k not in per_frame} == {
        k: v for k, v in short_rec.items() if k not in per_frame
    }


def test_auto_exposure_converges_and_is_capped() -> None:
    night, rec = render_night([_street()] * 12, [4])
    gains = rec["gain_per_frame"]
    ae = rec["ae"]
    assert gains[0] == ae["start_gain"]
    assert all(1.0 <= g <= ae["max_gain"] for g in gains)
    # Converged: the last steps move far less than the first.
    assert abs(gains[-1] - gains[-2]) <= max(0.05 * gains[-1], abs(gains[1] - gains[0]))


def test_lights_stay_in_place_over_a_static_sequence() -> None:
    """The time-average brightness of two halves of a static sequence correlate; another seed's lights do not."""
    day = [np.full((90, 120, 3), 150, np.uint8)] * 16

    def halves(seed: int) -> tuple[np.ndarray, np.ndarray]:
        night, _ = render_night(day, [seed])
        luma = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY).astype(np.float32) for f in night]
        return np.mean(luma[4:10], axis=0), np.mean(luma[10:], axis=0)

    a1, a2 = halves(21)
    b1, _ = halves(22)
    same = np.corrcoef(a1.ravel(), a2.ravel())[0, 1]
    other = np.corrcoef(a1.ravel(), b1.ravel())[0, 1]
    assert same > 0.9
    assert same > other + 0.1


def test_noise_is_fresh_each_frame() -> None:
    night, rec = render_night([_street()] * 8, [6])
    # Frames 6 and 7 come from the same day frame at a settled gain, yet their noise differs.
    diff = np.abs(night[6].astype(np.int16) - night[7].astype(np.int16))
    assert diff.mean() > 0.05


def test_rendered_photos_match_real_night_footage() -> None:
    photos = _photos()
    stats = []
    for seed in range(12):
        night, _ = render_night([photos[seed % len(photos)]] * 4, [seed])
        stats += [night_statistics(f) for f in night[2:]]
    for key, (lo, hi) in REAL.items():
        med = float(np.median([s[key] for s in stats]))
        assert lo <= med <= hi, (key, med)
    assert float(np.median([s["above_245"] for s in stats])) <= 0.01


def _sodium_seeds(n: int) -> list[int]:
    """Seeds whose scene is lit by sodium lamps only (read from the record of a tiny render)."""
    found = []
    tiny = [np.full((8, 8, 3), 128, np.uint8)]
    for seed in range(200):
        if all("sodium" in lamp for lamp in render_night(tiny, [seed])[1]["lamps"]):
            found.append(seed)
            if len(found) == n:
                break
    return found


def test_sodium_scenes_are_orange() -> None:
    photos = _photos()
    ratios = []
    for i, seed in enumerate(_sodium_seeds(8)):
        night, _ = render_night([photos[i % len(photos)]] * 3, [seed])
        st = night_statistics(night[-1])
        ratios.append(st["red"] / max(st["blue"], 0.5))
    assert len(ratios) == 8
    assert float(np.median(ratios)) >= 2.0, ratios


def test_the_sensor_model_shares_no_code_with_the_other_night_models():
    """Independence: a model trained on the generator's and the camera model's nights is judged on this one."""
    tree = ast.parse(Path(sensor_night.__file__).read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert names <= {"__future__", "math", "dataclasses", "cv2", "numpy"}, names
    code = ("import sys, dadiff.runtime.datamaking.sensor_night; "
            "print(sorted(m for m in sys.modules if m.rsplit('.', 1)[-1] in ('night', 'camera_night', 'scenes')))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"
