"""The fixed-camera video benchmark: movers labelled by background subtraction, written as day and night."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main as eval_main
from dadiff.runtime.datamaking.datasets import load_dataset
from dadiff.runtime.datamaking.fixed_camera import LabelSettings, label_tracks, read_video

SIZE = (320, 240)  # width, height


def _backdrop(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.uniform(90, 170, (SIZE[1], SIZE[0], 3)).astype(np.float32), (0, 0), 3)
    return texture.astype(np.uint8)


def _video(movers: list[list[tuple[int, int, int, int]]], frames: int) -> list[np.ndarray]:
    """Frames of a fixed camera: a textured backdrop with dark boxes moving over it (movers[k][i] = box)."""
    back = _backdrop()
    out = []
    for i in range(frames):
        frame = back.copy()
        for path in movers:
            x, y, w, h = path[i]
            frame[y:y + h, x:x + w] = (20, 25, 30)
        out.append(frame)
    return out


def _walk(x0: int, y0: int, dx: int, frames: int, w: int = 14, h: int = 40) -> list[tuple[int, int, int, int]]:
    return [(x0 + dx * i, y0, w, h) for i in range(frames)]


def _write_folder(frames: list[np.ndarray], folder: Path) -> Path:
    folder.mkdir(parents=True)
    for i, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:04d}.png"), frame)
    return folder


def test_a_lone_mover_is_labelled_to_the_pixel():
    truth = _walk(30, 100, 3, 80)
    tracks = label_tracks(_video([truth], 80), LabelSettings(min_frames=40))
    assert len(tracks) == 1 and tracks[0].start == 0
    assert len(tracks[0].boxes) == 80
    np.testing.assert_allclose(tracks[0].boxes, np.array(truth, float), atol=1)


def test_tracks_end_before_two_movers_merge_and_start_again_once_they_part():
    left, right = _walk(20, 100, 3, 80), _walk(260, 100, -3, 80)  # they overlap in frames 38-42
    tracks = label_tracks(_video([left, right], 80), LabelSettings(min_frames=20))
    assert sorted((t.start, t.start + len(t.boxes)) for t in tracks) == [(0, 37), (0, 37), (44, 80), (44, 80)]
    for track in tracks:
        frames = range(track.start, track.start + len(track.boxes))
        truth = [np.array([path[i] for i in frames], float) for path in (left, right)]
        assert any(np.abs(track.boxes - boxes).max() <= 1 for boxes in truth)


def test_short_wide_and_border_movers_are_not_kept():
    wide = _walk(30, 60, 3, 80, w=40, h=20)
    assert len(label_tracks(_video([wide], 80), LabelSettings(min_frames=40))) == 1
    assert label_tracks(_video([wide], 80), LabelSettings(min_frames=40, min_aspect=1.8)) == []
    assert label_tracks(_video([wide], 80), LabelSettings(min_frames=81)) == []
    leaving = _walk(250, 100, 3, 80)  # reaches the right border after ~18 frames
    assert label_tracks(_video([leaving], 80), LabelSettings(min_frames=30)) == []


def test_video_command_writes_day_and_night_sequences(tmp_path: Path, capsys):
    truth = _walk(30, 100, 3, 80)
    video = tmp_path / "walk.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, SIZE)
    for frame in _video([truth], 80):
        writer.write(frame)
    writer.release()
    assert len(read_video(video)) == 80
    out = tmp_path / "bench"
    assert eval_main(["video", "--video", str(video), "--output", str(out), "--min-frames", "40"]) == 0
    assert "wrote 1 day + 1 night sequences" in capsys.readouterr().out
    dataset = load_dataset(out)
    day, night = (next(s for s in dataset.sequences if s.name == f"vid001_{k}") for k in ("day", "night"))
    assert len(day) == len(night) == 80
    np.testing.assert_allclose(day.boxes, night.boxes)
    np.testing.assert_allclose(day.boxes, np.array(truth, float), atol=1.5)  # MJPG blurs the edges a little
    day_luma = np.mean([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).mean() for p in day.frames[:5]])
    night_luma = np.mean([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).mean() for p in night.frames[:5]])
    assert night_luma < 40 < day_luma


def test_video_command_renders_the_night_with_the_camera_model(tmp_path: Path, capsys):
    video = _write_folder(_video([_walk(30, 100, 3, 50)], 50), tmp_path / "walk")
    out = tmp_path / "bench"
    args = ["video", "--video", str(video), "--output", str(out), "--min-frames", "40", "--night", "camera"]
    assert eval_main(args) == 0
    assert "wrote 1 day + 1 night sequences" in capsys.readouterr().out
    info = json.loads((out / "benchmark.json").read_text())
    assert info["night"] == "camera" and info["night_cameras"]["vid001_night"]["model"] == "camera"
    night = next(s for s in load_dataset(out).sequences if s.name == "vid001_night")
    assert len(night) == 50 and cv2.imread(str(night.frames[0]), cv2.IMREAD_GRAYSCALE).mean() < 60


def test_video_command_renders_the_night_with_the_sensor_model(tmp_path: Path):
    video = _write_folder(_video([_walk(30, 100, 3, 50)], 50), tmp_path / "walk")
    nights = {}
    for model in ("camera", "sensor"):
        out = tmp_path / model
        args = ["video", "--video", str(video), "--output", str(out), "--min-frames", "40", "--night", model]
        assert eval_main(args) == 0
        info = json.loads((out / "benchmark.json").read_text())
        assert info["night"] == model and info["night_cameras"]["vid001_night"]["model"] == model
        nights[model] = cv2.imread(str(out / "vid001_night" / "img" / "0001.jpg"))
    assert nights["sensor"].shape == nights["camera"].shape
    assert not np.array_equal(nights["sensor"], nights["camera"])  # a third look, not the second one renamed


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda tmp: tmp / "missing.avi", "no such video file or image folder"),
        (lambda tmp: _write_folder(_video([], 70), tmp / "still"), "no mover seen whole and alone"),
        (lambda tmp: _write_folder(_video([_walk(30, 100, 3, 30)], 30), tmp / "short"), "fewer than the 60"),
    ],
)
def test_video_command_bad_input_is_one_line_and_exit_2(tmp_path: Path, capsys, make, message):
    video = make(tmp_path)
    assert eval_main(["video", "--video", str(video), "--output", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err and err.startswith("dadiff-eval: error:")


@pytest.mark.parametrize(
    "args, message",
    [
        (["--min-frames", "80", "--max-frames", "50"], "--max-frames 50 is below --min-frames 80"),
        (["--min-aspect", "-1"], "--min-aspect -1.0 must be in [0, 100)"),
        (["--threshold", "300"], "--threshold 300 must be below 255"),
    ],
)
def test_video_command_bad_settings_are_one_line_and_exit_2(tmp_path: Path, capsys, args, message):
    video = _write_folder(_video([_walk(30, 100, 3, 80)], 80), tmp_path / "walk")
    assert eval_main(["video", "--video", str(video), "--output", str(tmp_path / "out"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err and err.startswith("dadiff-eval: error:")
