"""Uncut clips: whole-video sequences whose truth marks frames unknown or absent, and their wrong-lock score."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main as eval_main
from dadiff.runtime.datamaking.datasets import load_dataset
from dadiff.runtime.evaluation.evaluate import write_result, write_states
from dadiff.runtime.evaluation.uncut import read_truth, uncut_scores

REPO = Path(__file__).resolve().parents[1]
VTEST_TRUTH = REPO / "docs" / "vtest-uncut"
VTEST = Path(os.environ.get("DADIFF_VTEST", "/usr/share/doc/opencv-doc/examples/data/vtest.avi"))  # opencv-doc
FRAMES = 12
NAN = [np.nan] * 4


def _video(folder: Path) -> Path:
    """A 12-frame 'video' (a folder of PNGs): frame i is grey level 10 * i, so a frame can be told by its grey."""
    folder.mkdir()
    for i in range(FRAMES):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.full((48, 64, 3), 10 * i, np.uint8))
    return folder


def _truth(folder: Path, clips: dict[str, tuple[int, list, list[int]]]) -> Path:
    folder.mkdir()
    (folder / "clips.json").write_text(json.dumps({n: {"first_frame": f} for n, (f, _, _) in clips.items()}))
    for name, (_, boxes, absent) in clips.items():
        (folder / name).mkdir()
        (folder / name / "groundtruth_rect.txt").write_text("".join(",".join(map(str, b)) + "\n" for b in boxes))
        (folder / name / "absence.label").write_text("".join(f"{a}\n" for a in absent))
    return folder


BOX = [10, 10, 8, 20]
PERFECT = 20 / 21  # success of IoU 1 in every frame: not above the last threshold (1.0, strict >)


def _walker_clip() -> tuple[int, list, list[int]]:
    """From video frame 4: in view 4 frames, 1 unknown (a crossing), 3 absent (gone out of view)."""
    boxes = [BOX] * 4 + [NAN] + [NAN] * 3
    return 4, boxes, [0] * 5 + [1] * 3


def test_clips_run_from_their_first_frame_to_the_video_end(tmp_path):
    truth = _truth(tmp_path / "truth", {"w": _walker_clip(), "z": (0, [BOX] * FRAMES, [0] * FRAMES)})
    assert eval_main(["uncut", "--video", str(_video(tmp_path / "v")), "--truth", str(truth),
                      "--output", str(tmp_path / "out")]) == 0
    dataset = load_dataset(tmp_path / "out")
    clips = {s.name: s for s in dataset.sequences}
    assert sorted(clips) == ["w", "z"] and len(clips["w"]) == 8 and len(clips["z"]) == FRAMES
    first = cv2.imread(str(clips["w"].frames[0]))
    assert abs(int(first.mean()) - 40) <= 1  # video frame 4, not frame 0
    assert np.isnan(clips["w"].boxes[4:]).all()


def test_truth_of_the_wrong_length_or_a_box_on_an_absent_frame_is_refused(tmp_path, capsys):
    video = _video(tmp_path / "v")
    short = _truth(tmp_path / "short", {"w": (4, [BOX] * 5, [0] * 5)})
    assert eval_main(["uncut", "--video", str(video), "--truth", str(short), "--output", str(tmp_path / "o1")]) == 2
    assert "5 rows from frame 4, but" in capsys.readouterr().err
    boxed = _truth(tmp_path / "boxed", {"w": (4, [BOX] * 8, [0] * 7 + [1])})
    assert eval_main(["uncut", "--video", str(video), "--truth", str(boxed), "--output", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a box on a frame marked absent" in err
    outside = _truth(tmp_path / "outside", {"w": _walker_clip()})
    (outside / "clips.json").write_text(json.dumps({"../w": {"first_frame": 4}}))
    assert eval_main(["uncut", "--video", str(video), "--truth", str(outside), "--output", str(tmp_path / "o3")]) == 2
    assert "not a plain folder name" in capsys.readouterr().err


def _results(folder: Path, name: str, boxes: list, states: list[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    write_result(folder / f"{name}.txt", boxes)
    write_states(folder / f"{name}.states", [(1.0, s) for s in states])


def test_tracking_on_an_absent_frame_counts_as_off_and_unknown_frames_do_not_count(tmp_path, capsys):
    truth = _truth(tmp_path / "truth", {"w": _walker_clip()})
    video = _video(tmp_path / "v")
    eval_main(["uncut", "--video", str(video), "--truth", str(truth), "--output", str(tmp_path / "d")])
    dataset = load_dataset(tmp_path / "d")
    both = _truth(tmp_path / "truth2", {"w": _walker_clip(), "z": (0, [BOX] * FRAMES, [0] * FRAMES)})
    eval_main(["uncut", "--video", str(video), "--truth", str(both), "--output", str(tmp_path / "d2")])
    post = [60, 20, 8, 20]  # a static look-alike far from the person
    # on the person in view; on the post at the crossing (unknown: not counted) and after the person left
    _results(tmp_path / "r" / "honest", "w", [BOX] * 4 + [post] * 4, ["init"] + ["tracking"] * 3 + ["lost"] * 4)
    _results(tmp_path / "r" / "chaser", "w", [BOX] * 4 + [post] * 4, ["init"] + ["tracking"] * 7)
    _results(tmp_path / "r" / "early", "w", [BOX, BOX, post, post] + [post] * 4,
             ["init"] + ["tracking"] * 3 + ["uncertain"] * 4)
    _results(tmp_path / "r" / "shy", "w", [BOX] * 4 + [post] * 4, ["init", "tracking"] + ["uncertain"] * 6)
    rows = {r.clip: r for r in uncut_scores(dataset, tmp_path / "r" / "honest")}
    assert rows["w"].tracking_on == 1.0  # every frame on the person reported 'tracking'
    assert uncut_scores(dataset, tmp_path / "r" / "shy")[0].tracking_on == pytest.approx(1 / 3)
    assert (rows["w"].in_view, rows["w"].absent) == (3, 3)  # frames after the first; the unknown one left out
    assert rows["w"].success == pytest.approx(PERFECT) and rows["w"].tracking_off == 0
    chaser = uncut_scores(dataset, tmp_path / "r" / "chaser")[0]
    assert chaser.tracking_off == pytest.approx(3 / 6) and chaser.tracking_absent == pytest.approx(3 / 6)
    early = uncut_scores(dataset, tmp_path / "r" / "early")[0]
    assert early.tracking_off == pytest.approx(2 / 6) and early.tracking_absent == 0
    assert early.success == pytest.approx(PERFECT / 3) and early.precision == pytest.approx(1 / 3)
    _results(tmp_path / "r2" / "chaser", "w", [BOX] * 4 + [post] * 4, ["init"] + ["tracking"] * 7)
    _results(tmp_path / "r2" / "chaser", "z", [BOX] * FRAMES, ["init"] + ["tracking"] * (FRAMES - 1))
    two = load_dataset(tmp_path / "d2")
    rows = {r.clip: r for r in uncut_scores(two, tmp_path / "r2" / "chaser")}
    assert rows["all"].tracking_off == pytest.approx(3 / (6 + FRAMES - 1))  # pooled over frames
    assert rows["mean"].tracking_off == pytest.approx((3 / 6 + 0) / 2)  # each clip counts once
    assert eval_main(["uncut-score", "--dataset", str(tmp_path / "d"), str(tmp_path / "r")]) == 0
    table = capsys.readouterr().out
    assert "chaser" in table and "50.0%" in table and "all" in table and "mean" in table


def test_night_clips_are_the_video_rendered_at_night_once_per_seed(tmp_path):
    truth = _truth(tmp_path / "truth", {"w": _walker_clip()})
    video = _video(tmp_path / "v")
    for out, night in (("day", []), ("n3", ["--night-seed", "3"]), ("n3b", ["--night-seed", "3"]),
                       ("n4", ["--night-seed", "4"])):
        assert eval_main(["uncut", "--video", str(video), "--truth", str(truth), "--output", str(tmp_path / out),
                          *night]) == 0
    clips = {out: load_dataset(tmp_path / out).sequences[0] for out in ("day", "n3", "n3b", "n4")}
    assert {len(c) for c in clips.values()} == {8}
    np.testing.assert_array_equal(clips["day"].boxes, clips["n3"].boxes)
    frames = {out: np.stack([cv2.imread(str(f)) for f in c.frames]).astype(int) for out, c in clips.items()}
    assert np.abs(frames["n3"] - frames["day"]).mean() > 5  # rendered, not copied
    np.testing.assert_array_equal(frames["n3"], frames["n3b"])  # one seed, one night
    assert np.abs(frames["n3"] - frames["n4"]).mean() > 1


def test_results_without_states_are_refused_in_one_line(tmp_path, capsys):
    truth = _truth(tmp_path / "truth", {"w": _walker_clip()})
    eval_main(["uncut", "--video", str(_video(tmp_path / "v")), "--truth", str(truth), "--output", str(tmp_path / "d")])
    (tmp_path / "r" / "old").mkdir(parents=True)
    write_result(tmp_path / "r" / "old" / "w.txt", [BOX] * 8)
    assert eval_main(["uncut-score", "--dataset", str(tmp_path / "d"), str(tmp_path / "r" / "old")]) == 2
    assert "no .states files" in capsys.readouterr().err


def test_the_shipped_vtest_truth_reads_and_fits_the_video():
    clips = read_truth(VTEST_TRUTH)
    assert len(clips) >= 4
    for first, boxes, absent in clips.values():
        assert first + len(boxes) == 795  # vtest.avi's frames
        assert np.isfinite(boxes[0]).all() and not absent[0]
    if not VTEST.is_file():
        pytest.skip(f"{VTEST} not here (Debian's opencv-doc; or set DADIFF_VTEST)")
    cap = cv2.VideoCapture(str(VTEST))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 795
