"""Pseudo-labels from a detector's boxes: linked into tracks over a moving camera, written as day and night."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main as eval_main
from dadiff.runtime.datamaking.datasets import load_dataset
from dadiff.runtime.datamaking.detection_tracks import LinkSettings, link, read_detections, scene_cuts
from dadiff.runtime.datamaking.detector import write_det_txt

SIZE = (320, 240)  # width, height


def _walk(x0: float, y0: float, dx: float, frames: int, w: float = 16, h: float = 40) -> np.ndarray:
    return np.array([(x0 + dx * i, y0, w, h) for i in range(frames)], float)


def _detections(paths: list[np.ndarray], rng: np.random.Generator, jitter: float = 0.5,
                missed: dict[int, range] | None = None) -> list[np.ndarray]:
    """Per frame, each path's box with a detector's jitter (x, y, w, h, score), minus the `missed` frames."""
    frames = len(paths[0])
    out = []
    for t in range(frames):
        rows = [np.r_[p[t] + rng.normal(0, jitter, 4), 0.9] for k, p in enumerate(paths)
                if not (missed and t in missed.get(k, ()))]
        out.append(np.array(rows).reshape(-1, 5))
    return out


def _matches(track_boxes: np.ndarray, truth: np.ndarray, tolerance: float) -> bool:
    return bool(np.abs(track_boxes - truth).max() <= tolerance)


def test_a_detected_walker_becomes_one_smooth_track_with_its_gap_filled():
    truth = _walk(30, 100, 1, 80, w=24, h=60)  # 7 px on after the gap: it still overlaps the last box
    dets = _detections([truth], np.random.default_rng(0), jitter=1.0, missed={0: range(30, 36)})
    tracks = link(dets, [False] * 80, LinkSettings())
    assert len(tracks) == 1 and tracks[0].start == 0 and len(tracks[0].boxes) == 80
    assert _matches(tracks[0].boxes, truth, 1.5)  # 1 px of jitter averaged over 5 frames; the gap interpolated
    raw = np.array([d[0, :4] for d in dets if len(d)])
    assert np.abs(np.diff(tracks[0].boxes[:, 0])).std() < np.abs(np.diff(raw[:, 0])).std() / 2


def test_two_walkers_that_cross_end_their_tracks_instead_of_swapping():
    left, right = _walk(20, 100, 3, 90), _walk(280, 104, -3, 90)  # they overlap around frame 43
    tracks = link(_detections([left, right], np.random.default_rng(1)), [False] * 90, LinkSettings(min_frames=20))
    assert len(tracks) >= 2
    for track in tracks:
        span = slice(track.start, track.start + len(track.boxes))
        assert _matches(track.boxes, left[span], 3) or _matches(track.boxes, right[span], 3)
    assert all(track.start + len(track.boxes) <= 45 or track.start >= 40 for track in tracks)


def test_a_scene_cut_ends_every_track_and_short_ones_are_dropped():
    truth = _walk(30, 100, 1, 80)
    dets = _detections([truth], np.random.default_rng(2))
    cuts = [t == 50 for t in range(80)]
    tracks = link(dets, cuts, LinkSettings(min_frames=25))
    assert [(t.start, len(t.boxes)) for t in tracks] == [(0, 50), (50, 30)]
    assert [(t.start, len(t.boxes)) for t in link(dets, cuts, LinkSettings(min_frames=40))] == [(0, 50)]


def _panning_video(paths: list[np.ndarray], frames: int, cut: int | None = None) -> list[np.ndarray]:
    """A camera panning over a textured backdrop (the background moves 2 px a frame), dark walkers drawn on it;
    from frame `cut` on, another backdrop."""
    rng = np.random.default_rng(5)
    wide = cv2.GaussianBlur(rng.uniform(80, 180, (SIZE[1], SIZE[0] + 2 * frames, 3)).astype(np.float32), (0, 0), 3)
    other = wide * 0.3  # a darker, different place
    out = []
    for t in range(frames):
        back = other if cut is not None and t >= cut else wide
        frame = back[:, 2 * t:2 * t + SIZE[0]].astype(np.uint8).copy()
        for path in paths:
            x, y, w, h = path[t].round().astype(int)
            frame[y:y + h, x:x + w] = (25, 20, 30)
        out.append(frame)
    return out


def test_scene_cuts_are_found_and_panning_is_not_one():
    truth = _walk(30, 100, 2, 60)
    cuts = scene_cuts(_panning_video([truth], 60, cut=40), LinkSettings().cut_threshold)
    assert [t for t, c in enumerate(cuts) if c] == [40]


def _write_det(path: Path, dets: list[np.ndarray], extra: str = "") -> Path:
    write_det_txt(path, dets)
    with path.open("a") as f:
        f.write(extra)
    return path


def _write_video(frames: list[np.ndarray], folder: Path) -> Path:
    folder.mkdir(parents=True)
    for i, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:04d}.png"), frame)
    return folder


@pytest.mark.parametrize("night", ["real", "camera"])
def test_command_writes_day_and_night_sequences_from_a_moving_camera(tmp_path: Path, capsys, night):
    truth = _walk(40, 90, 2, 60)
    video = _write_video(_panning_video([truth], 60), tmp_path / "pan")
    rng = np.random.default_rng(3)
    dets = _detections([truth], rng)
    dets = [np.r_[d, [[200, 20, 30, 10, 0.9], [150, 150, 15, 40, 0.2]]] for d in dets]  # too wide; too unsure
    det = _write_det(tmp_path / "det.txt", dets)
    out = tmp_path / "bench"
    assert eval_main(["pseudo-label", "--video", str(video), "--detections", str(det), "--output", str(out),
                      "--night", night]) == 0
    assert "wrote 1 day + 1 night sequences" in capsys.readouterr().out
    assert json.loads((out / "benchmark.json").read_text())["night"] == night
    dataset = load_dataset(out)
    day, night = (next(s for s in dataset.sequences if s.name == f"vid001_{k}") for k in ("day", "night"))
    assert len(day) == len(night) == 60
    np.testing.assert_allclose(day.boxes, truth, atol=1.5)
    night_luma = np.mean([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).mean() for p in night.frames[:5]])
    assert night_luma < 40


def test_the_day_half_of_a_written_benchmark_is_a_training_source(tmp_path: Path):
    pytest.importorskip("torch")
    from dadiff.export.train_data import make_day_source

    truth = _walk(40, 90, 2, 40)
    video = _write_video(_panning_video([truth], 40), tmp_path / "pan")
    det = _write_det(tmp_path / "det.txt", _detections([truth], np.random.default_rng(4)))
    assert eval_main(["pseudo-label", "--video", str(video), "--detections", str(det), "--output",
                      str(tmp_path / "bench")]) == 0
    source = make_day_source({"kind": "sequences", "root": str(tmp_path / "bench"), "match": "*_day"})
    assert [frames[0].parent.parent.name for frames, _, _ in source.sequences] == ["vid001_day"]
    with pytest.raises(ValueError, match="no sequence folders matching '\\*_dusk'"):
        make_day_source({"kind": "sequences", "root": str(tmp_path / "bench"), "match": "*_dusk"})


@pytest.mark.parametrize(
    "extra, message",
    [
        ("3,-1,10,10,abc,40,0.9\n", "det.txt:41: expected frame,id,x,y,w,h,score numbers, got '3,-1,10,10,abc,40,0.9'"),
        ("41,-1,10,10,16,40,0.9\n", "det.txt:41: frame 41 is outside the video's 1-40"),
        ("2,-1,10,10,0,40,0.9\n", "det.txt:41: box width and height must be positive, got 0 x 40"),
    ],
)
def test_a_bad_detection_line_is_named_with_its_number(tmp_path: Path, capsys, extra, message):
    truth = _walk(40, 90, 2, 40)
    video = _write_video(_panning_video([truth], 40), tmp_path / "pan")
    det = _write_det(tmp_path / "det.txt", _detections([truth], np.random.default_rng(6)), extra)
    assert eval_main(["pseudo-label", "--video", str(video), "--detections", str(det), "--output",
                      str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err and err.startswith("dadiff-eval: error:")


@pytest.mark.parametrize(
    "args, message",
    [
        (["--detections", "missing.txt"], "missing.txt: no such detections file"),
        (["--min-frames", "41"], "link into no track of 41 frames"),
        (["--aspect", "5-1"], "expected 0 < MIN < MAX, got '5-1'"),
        (["--min-score", "2"], "--min-score 2.0 must be in [0, 1]"),
        (["--min-frames", "60", "--max-frames", "50"], "--max-frames 50 is below --min-frames 60"),
    ],
)
def test_bad_settings_are_one_line_and_exit_2(tmp_path: Path, capsys, monkeypatch, args, message):
    truth = _walk(40, 90, 2, 40)
    video = _write_video(_panning_video([truth], 40), tmp_path / "pan")
    _write_det(tmp_path / "det.txt", _detections([truth], np.random.default_rng(7)))
    monkeypatch.chdir(tmp_path)
    try:
        status = eval_main(["pseudo-label", "--video", str(video), "--detections", "det.txt", "--output", "out", *args])
    except SystemExit as exc:  # a usage error, found by the argument parser
        status = exc.code
    assert status == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err and err.startswith("dadiff-eval: error:")


def test_read_detections_filters_and_merges_overlapping_boxes(tmp_path: Path):
    det = tmp_path / "det.txt"
    det.write_text("# a comment\n1,-1,10,10,16,40,0.9\n1,-1,11,10,16,40,0.8\n1,-1,100,10,16,40,0.3\n"
                   "1,-1,200,10,40,16,0.9\n2,-1,50,50,16,20,0.9\n")
    rows = read_detections(det, 2, LinkSettings())
    np.testing.assert_allclose(rows[0], [[10, 10, 16, 40, 0.9]])  # NMS kept the surer; low score; too wide
    assert rows[1].shape == (0, 5)  # 20 px tall: below min_height
