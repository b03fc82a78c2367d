"""The independent night model (camera_night) and `dadiff-eval night`: real-footage statistics, determinism,
the datasets it writes, and its independence from the generator's night renderer.

Targets from ../shared/notes/real-night-footage.md (median [10th-90th percentile] over frames): mean luma 11.5
(UAVDark135 person11) and 23.5 [11.7-45.9] (DarkTrack2021); share < 20 0.79 and 0.60 [0.14-0.84]; share > 245
2e-6 and 0.0014 [1e-4-0.011]; dark-area noise 1.71 and 2.19 [1.33-3.63]; under sodium light red ~2.7x blue.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main as eval_main
from dadiff.runtime.datamaking import camera_night, night_sets
from dadiff.runtime.datamaking.camera_night import NightCamera, night_statistics, render_night
from dadiff.runtime.datamaking.datasets import load_dataset

SIZE = (320, 240)
CAMERAS = range(16)


def day_frame(seed: int = 0) -> np.ndarray:
    """A daylight frame: coarse patches of every brightness (walls, ground, cars) with fine texture."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(40, 220, (SIZE[1] // 16, SIZE[0] // 16, 3)).astype(np.float32)
    base = cv2.resize(coarse, SIZE, interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.normal(0, 25, (SIZE[1], SIZE[0], 3)).astype(np.float32), (0, 0), 1.2)
    return np.clip(base + fine, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def nights() -> list[tuple[dict, dict]]:
    """The third night frame's statistics and the camera's record, for 16 cameras over one day frame."""
    day = [day_frame()] * 3
    out = []
    for k in CAMERAS:
        frames, record = render_night(day, [k])
        out.append((night_statistics(frames[-1]), record))
    return out


def test_statistics_land_in_the_real_footage_ranges(nights):
    rows = [stats for stats, _ in nights]
    median = {key: float(np.median([r[key] for r in rows])) for key in rows[0]}
    assert 6 <= median["mean"] <= 46
    assert 0.55 <= median["below_20"] <= 0.92
    assert 0 < median["above_245"] <= 0.011  # lamps in view saturate, little else
    assert 0.5 <= median["noise"] <= 3.7  # denoised: far below the classic night's 5.49
    assert all(r["mean"] < 60 for r in rows)  # no camera sees daylight
    assert np.mean([r["below_20"] > 0.3 for r in rows]) >= 0.8  # most of a frame near black


def test_sodium_light_makes_red_well_above_blue(nights):
    ratios = [stats["red"] / max(stats["blue"], 1e-3) for stats, record in nights if record["lamp"] == "sodium"]
    assert ratios, "no sodium camera among the draws"
    assert 1.8 <= np.median(ratios) <= 6
    cool = [stats["red"] / max(stats["blue"], 1e-3) for stats, record in nights if record["lamp"] == "led_cool"]
    assert not cool or np.median(cool) < 1.3


def test_same_seed_same_night_other_seed_other_night():
    day = [day_frame(1), day_frame(2)]
    first, record = render_night(day, [3, 4])
    again, record_again = render_night(day, [3, 4])
    other, record_other = render_night(day, [3, 5])
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True)) and record == record_again
    assert not np.array_equal(first[0], other[0]) and record != record_other
    json.dumps(record)  # the record is what benchmark.json keeps


def test_shot_noise_grows_as_the_light_falls():
    """Poisson statistics plus read noise: the raw frame's spread over its mean goes as sqrt(e + r^2) / e, with
    e the electrons above the camera's black point."""
    camera = NightCamera.draw(np.random.default_rng(0))
    gain = camera.full_well / 1000  # 1000 electrons fill full scale: far from clipping, fine ADC steps
    spread, expected = [], []
    for electrons in (400.0, 25.0):
        raw = camera.sensor(np.full((200, 200, 3), electrons, np.float32), gain, np.random.default_rng(1))
        spread.append(raw.std() / raw.mean())
        above_black = electrons - camera.black_crush * camera.read_noise
        expected.append(np.sqrt(electrons + camera.read_noise**2) / above_black)
    assert spread[1] / spread[0] == pytest.approx(expected[1] / expected[0], rel=0.1)
    assert spread[1] > 3 * spread[0]


def test_gain_is_locked_on_the_first_frame():
    """The auto-exposure does not follow the scene within a sequence: a brighter second frame comes out brighter
    than the same frame metered on its own (a camera whose gain has room to move)."""
    camera = replace(NightCamera.draw(np.random.default_rng(7)), max_gain=1e5)
    dark, bright = day_frame(5) // 3, day_frame(5)
    frames, locked = camera.render([dark, bright], [1])
    alone, locked_alone = camera.render([bright], [1])
    assert locked["gain"] > 1.5 * locked_alone["gain"]
    assert frames[1].mean() > alone[0].mean() + 2


def test_no_code_of_the_generators_night_is_imported():
    """Independence: the new modules import nothing of night.py / scene.py / library_scenes.py, directly or not."""
    for module in (camera_night, night_sets):
        tree = ast.parse(Path(module.__file__).read_text())
        names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert not names & {"night", "scene", "scenes", "library_scenes", "fixed_camera"}, module.__name__
    code = ("import sys, dadiff.runtime.datamaking.camera_night, dadiff.runtime.datamaking.night_sets; "
            "print(sorted(m for m in sys.modules if m.rsplit('.', 1)[-1] in "
            "('night', 'scene', 'scenes', 'library_scenes', 'fixed_camera')))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"


def _day_dataset(root: Path, sequences: int = 2, frames: int = 4) -> Path:
    for k in range(sequences):
        folder = root / f"seq{k:03d}_day" / "img"
        folder.mkdir(parents=True)
        for i in range(frames):
            cv2.imwrite(str(folder / f"{i + 1:04d}.jpg"), day_frame(10 * k + i))
        boxes = np.array([[40 + 3 * i, 50, 30, 60] for i in range(frames)], float)
        np.savetxt(folder.parent / "groundtruth_rect.txt", boxes, fmt="%.1f", delimiter=",")
        night = root / f"seq{k:03d}_night" / "img"  # the source's own night is left alone
        night.mkdir(parents=True)
        cv2.imwrite(str(night / "0001.jpg"), day_frame() // 4)
        np.savetxt(night.parent / "groundtruth_rect.txt", boxes[:1], fmt="%.1f", delimiter=",")
    (root / "attributes.json").write_text(json.dumps({"seq000_day": ["SV"], "seq001_day": []}))
    return root


def test_night_command_writes_a_day_and_night_dataset(tmp_path: Path, capsys):
    source = _day_dataset(tmp_path / "days")
    out = tmp_path / "camera"
    assert eval_main(["night", "--dataset", str(source), "--output", str(out), "--seed", "3"]) == 0
    printed = capsys.readouterr().out
    assert "wrote 2 day + 2 night sequences (camera night, seed 3)" in printed and "mean luma" in printed
    dataset = load_dataset(out)
    names = sorted(s.name for s in dataset.sequences)
    assert names == ["seq000_day", "seq000_night", "seq001_day", "seq001_night"]
    truth = load_dataset(source)
    for sequence in dataset.sequences:
        base = sequence.name.rsplit("_", 1)[0]
        np.testing.assert_allclose(sequence.boxes, next(s for s in truth.sequences if s.name == f"{base}_day").boxes)
        assert len(sequence) == 4
    night = next(s for s in dataset.sequences if s.name == "seq000_night")
    day = next(s for s in dataset.sequences if s.name == "seq000_day")
    assert night.attributes == ("SV", "LAI") and day.attributes == ("SV",)
    assert cv2.imread(str(night.frames[0])).mean() < cv2.imread(str(day.frames[0])).mean() / 2
    info = json.loads((out / "benchmark.json").read_text())
    assert info["night"] == "camera" and info["seed"] == 3 and sorted(info["night_cameras"]) == [
        "seq000_night", "seq001_night"]
    assert info["night_cameras"]["seq000_night"]["lamp"] in camera_night.LAMPS


def test_night_command_is_deterministic_per_sequence_name(tmp_path: Path, capsys):
    source = _day_dataset(tmp_path / "days")
    for name, pattern in (("all", []), ("one", ["--sequences", "seq001_day"])):
        assert eval_main(["night", "--dataset", str(source), "--output", str(tmp_path / name), *pattern]) == 0
    capsys.readouterr()
    frames = [sorted((tmp_path / name / "seq001_night" / "img").iterdir()) for name in ("all", "one")]
    assert [p.read_bytes() for p in frames[0]] == [p.read_bytes() for p in frames[1]]


def _with_a_file(folder: Path) -> Path:
    folder.mkdir()
    (folder / "x.txt").write_text("x")
    return folder


@pytest.mark.parametrize(
    "make_out, message",
    [
        (lambda tmp: tmp / "days" / "inside", "lies inside the input folder"),
        (lambda tmp: _with_a_file(tmp / "full"), "exists and is not an empty folder"),
    ],
)
def test_night_command_bad_output_is_one_line_and_exit_2(tmp_path: Path, capsys, make_out, message):
    source = _day_dataset(tmp_path / "days", sequences=1, frames=2)
    assert eval_main(["night", "--dataset", str(source), "--output", str(make_out(tmp_path))]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err and err.startswith("dadiff-eval: error:")


def test_night_command_unreadable_frame_is_one_line_and_exit_2(tmp_path: Path, capsys):
    source = _day_dataset(tmp_path / "days", sequences=1, frames=2)
    (source / "seq000_day" / "img" / "0002.jpg").write_bytes(b"not a jpeg")
    assert eval_main(["night", "--dataset", str(source), "--output", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "0002.jpg: cannot be read as an image" in err
