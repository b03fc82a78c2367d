"""`Tracker.look` and `dadiff-eval box-read`: the network's own box around a known box, before the tracker's
smoothing, and the state untouched; the summary by width thirds; the command on a small generated set."""

from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from test_runtime_plausible import FRAME, ScriptedBackend

from dadiff.runtime import InputError, Tracker
from dadiff.runtime.commands.eval import main
from dadiff.runtime.datamaking.datasets import Dataset, Sequence
from dadiff.runtime.datamaking.scenes import write_benchmark
from dadiff.runtime.evaluation.box_read import box_read, format_box_read, read_ratios, summarise
from dadiff.runtime.evaluation.evaluate import EvalError


def test_look_reads_the_networks_box_where_the_crop_was_cut_and_leaves_the_state() -> None:
    """The scripted network proposes 20 crop px either side of the centre cell: `look` returns that box in
    frame pixels around the shifted crop centre, and the next update is the one a tracker that never
    looked gives."""
    looking, plain = Tracker(ScriptedBackend([0.9], 20.0)), Tracker(ScriptedBackend([0.9], 20.0))
    for tracker in (looking, plain):
        tracker.init(FRAME, (100, 100, 40, 40))
    x, y, w, h = looking.look(FRAME, (200, 150, 40, 40), (8.0, 0.0))
    scale = 127 / 80  # crop px per frame px: context side sqrt((40 + 40) * (40 + 40))
    assert w == pytest.approx(40 / scale) and h == pytest.approx(40 / scale)
    assert x + w / 2 == pytest.approx(219.5 + 8 / scale) and y + h / 2 == pytest.approx(169.5)
    looking.backend.calls = 0  # the scripted scores restart for both
    assert looking.update(FRAME).box == plain.update(FRAME).box


def test_box_read_finds_the_lag_of_a_network_that_stays_at_the_crop_centre(tmp_path) -> None:
    """The scripted network always answers the crop's centre cell: moved 8 crop px it misses the true centre
    by 8 crop px (5 frame px, 0.13 of the 40 px width), still inside the box; moved 40 crop px (25 frame px)
    its centre is outside the box on every read."""
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), FRAME)
    sequence = Sequence("still", (frame,) * 3, np.array([[200, 150, 40, 40]] * 3, dtype=float))
    tracker = Tracker(ScriptedBackend([0.9], 20.0))
    near, far = read_ratios(tracker, Dataset("one", tmp_path, "otb", (sequence,)), [8.0, 40.0])
    scale = 127 / 80
    assert near[:, 3] == pytest.approx(8 / scale / 40) and not near[:, 4].any()
    assert far[:, 3] == pytest.approx(40 / scale / 40) and far[:, 4].all()


def test_look_before_init_and_a_bad_box_are_refused() -> None:
    tracker = Tracker(ScriptedBackend([0.9], 20.0))
    with pytest.raises(InputError, match="before init"):
        tracker.look(FRAME, (1, 1, 10, 10))
    tracker.init(FRAME, (100, 100, 40, 40))
    with pytest.raises(ValueError, match="zero or negative size"):
        tracker.look(FRAME, (1, 1, 0, 10))


def test_summary_is_the_median_log_ratio_overall_and_by_thirds_of_the_true_width() -> None:
    widths = np.arange(10.0, 100.0, 1.0)  # 90 frames: thirds 10-39, 40-69, 70-99 px
    log_w = np.where(widths < 40, 0.2, np.where(widths < 70, 0.1, -0.1))
    centre = np.where(widths < 40, 0.6, 0.1)  # 30 of 90 reads with the centre outside the true box
    rows = np.stack([widths, log_w, -log_w, centre, (centre > 0.5).astype(float)], axis=1)
    read = summarise(8.0, rows)
    assert read.centre == pytest.approx(0.1) and read.off == pytest.approx(1 / 3)
    assert (read.shift, read.frames, read.width, read.height) == (8.0, 90, 0.1, -0.1)
    assert [round(t[2], 3) for t in read.thirds] == [0.2, 0.1, -0.1]
    assert [round(t[3], 3) for t in read.thirds] == [-0.2, -0.1, 0.1]
    assert math.isclose(read.thirds[0][0], 10) and math.isclose(read.thirds[2][1], 99)


def test_a_width_third_without_frames_prints_a_dash_not_nan() -> None:
    rows = np.array([[20.0, 0.1, 0.0, 0.0, 0.0]] * 3)  # one width only: the first two thirds hold no frame
    reads = [summarise(0.0, rows), summarise(8.0, rows)]
    one_sequence = SimpleNamespace(frames=[0] * 4, boxes=[0] * 4)  # 3 frames after the first
    table = format_box_read(SimpleNamespace(name="one", sequences=[one_sequence]), reads)
    assert "nan" not in table and table.count(" -") >= 6
    assert "+0.100 / +0.000" in table


def test_box_read_command_prints_one_row_per_shift_and_their_mean(tmp_path, capsys) -> None:
    root = write_benchmark(tmp_path / "bench", sequences=1, frames=5, seed=4, size=(320, 180), workers=1)
    assert main(["box-read", "--dataset", str(root), "--sequences", "*_day", "--shifts", "0", "8",
                 "--threads", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line.split()[1:3] for line in lines[2:]}
    assert list(rows) == ["0", "8", "mean"] and "(4 frames)" in lines[0]
    assert all(math.isfinite(float(v)) for v in rows["mean"])
    assert float(rows["mean"][0]) == pytest.approx((float(rows["0"][0]) + float(rows["8"][0])) / 2, abs=1e-3)


@pytest.mark.parametrize(("args", "message"), [(["--shifts", "nan"], "expected a number from -255 to 255, got 'nan'"),
                                               (["--shifts", "1e308"], "--shifts: expected a number from -255 to 255"),
                                               (["--shifts", "250"], "--shifts 250: at most 223 crop px"),
                                               (["--dataset", "/no/such/set"], "/no/such/set")])
def test_box_read_bad_input_is_one_line(tmp_path, capsys, args: list[str], message: str) -> None:
    argv = ["box-read", "--dataset", str(tmp_path), *args] if args[0] != "--dataset" else ["box-read", *args]
    try:
        status = main(argv)
    except SystemExit as e:  # usage errors leave through argparse
        status = e.code
    assert status == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dadiff-eval: error") and message in err[0], err


def test_true_boxes_outside_the_frame_are_skipped_and_counted(tmp_path) -> None:
    """One later box outside the frame (or many frames wide) used to stop the whole run with the tracker's
    'init box ... lies outside the frame', naming neither sequence nor frame."""
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), FRAME)  # 480x360
    boxes = [[200, 150, 40, 40], [1000, 150, 40, 40], [200, -500, 40, 40], [200, 150, 4000, 40],
             [float("nan")] * 4, [200, 150, 40, 40]]
    sequence = Sequence("still", (frame,) * len(boxes), np.array(boxes, dtype=float))
    dataset = Dataset("one", tmp_path, "otb", (sequence,))
    reads = box_read(Tracker(ScriptedBackend([0.9], 20.0)), dataset, [0.0])
    assert reads[0].frames == 1
    assert "(1 frames, 4 skipped: no true box inside the frame)" in format_box_read(dataset, reads).splitlines()[0]


def test_no_frame_after_the_first_is_refused_not_a_table_of_nan(tmp_path) -> None:
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), FRAME)
    tracker = Tracker(ScriptedBackend([0.9], 20.0))
    one = Sequence("one", (frame,), np.array([[200, 150, 40, 40]], dtype=float))
    with pytest.raises(EvalError, match="no frames after the first"):
        read_ratios(tracker, Dataset("one", tmp_path, "otb", (one,)), [0.0])
    gone = Sequence("gone", (frame,) * 2, np.array([[200, 150, 40, 40], [1000, 150, 40, 40]], dtype=float))
    with pytest.raises(EvalError, match="all 1 frames after the first were skipped"):
        read_ratios(tracker, Dataset("gone", tmp_path, "otb", (gone,)), [0.0])
