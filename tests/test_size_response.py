"""`dadiff-eval box-read --sizes`: how far the network's box follows the size the crop was cut for, the
slope of that, and the size a tracker settles at."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from test_runtime_plausible import FRAME, ScriptedBackend

from dadiff.runtime import Tracker
from dadiff.runtime.commands.eval import main
from dadiff.runtime.datamaking.datasets import Dataset, Sequence
from dadiff.runtime.datamaking.scenes import write_benchmark
from dadiff.runtime.evaluation.size_response import (
    format_size_response,
    resting_size,
    scaled_box,
    size_response,
    summarise_sizes,
)

SIZES = (0.7, 0.85, 1.0, 1.18, 1.4)


def test_a_network_that_answers_in_crop_pixels_repeats_the_size_it_is_given(tmp_path) -> None:
    """The scripted network always proposes 40 crop px: its read scales with the crop, so with the size held,
    slope 1, and a 40 px target read as 40 crop px / (127 / 80) = 25.2 px at f = 1: smaller than any size
    given, so the tracker would shrink past the smallest factor."""
    frame = tmp_path / "frame.png"
    cv2.imwrite(str(frame), FRAME)
    sequence = Sequence("still", (frame,) * 3, np.array([[200, 150, 40, 40]] * 3, dtype=float))
    dataset = Dataset("one", tmp_path, "otb", (sequence,))
    response = size_response(Tracker(ScriptedBackend([0.9], 20.0)), dataset, SIZES)
    at_truth = math.log(40 / (127 / 80) / 40)
    assert response.frames == 2
    assert response.width == pytest.approx([at_truth + math.log(f) for f in SIZES], abs=1e-6)
    assert response.slope == pytest.approx((1.0, 1.0), abs=1e-6) and response.rest == (0.0, 0.0)
    assert "width 1.00, height 1.00" in format_size_response(dataset, response)
    assert "below the smallest f" in format_size_response(dataset, response)


def test_the_resting_size_is_where_the_read_meets_the_size_held() -> None:
    logs = np.log(SIZES)
    assert resting_size(logs, 0.05 + 0.8 * logs) == pytest.approx(math.exp(0.05 / 0.2), rel=1e-6)
    assert resting_size(logs, np.full(5, 0.1)) == pytest.approx(math.exp(0.1), rel=1e-6)  # a reader of the truth
    assert resting_size(logs, 0.3 + logs) == float("inf")  # grows past the largest factor
    assert math.isnan(resting_size(logs, 1.5 * logs))  # crosses upwards only: the size runs away either way


def test_summary_takes_the_median_per_factor_and_fits_the_slope() -> None:
    logs = np.log(SIZES)
    reads = np.stack([np.stack([0.02 + 0.5 * logs, -0.1 + 0.9 * logs], axis=1)] * 3)
    reads[0] += 5.0  # one wild frame: the median ignores it
    response = summarise_sizes(SIZES, reads)
    assert response.slope == pytest.approx((0.5, 0.9), abs=1e-9)
    # width: meets f at log f = 0.02 / 0.5; height: smaller than every size given (-0.1 - 0.1 log f < 0)
    assert response.rest[0] == pytest.approx(math.exp(0.04), rel=1e-6) and response.rest[1] == 0.0


def test_scaled_box_keeps_the_trackers_centre() -> None:
    x, y, w, h = scaled_box((10, 20, 41, 21), 2.0)
    assert (w, h) == (82, 42) and x + (w - 1) / 2 == 10 + 20 and y + (h - 1) / 2 == 20 + 10


def test_command_prints_the_reads_the_slope_and_the_resting_size(tmp_path, capsys) -> None:
    root = write_benchmark(tmp_path / "bench", sequences=1, frames=5, seed=4, size=(320, 180), workers=1)
    assert main(["box-read", "--dataset", str(root), "--sequences", "*_day", "--sizes", "0.8", "1", "1.25",
                 "--threads", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split() == ["f", "0.80", "1.00", "1.25"]
    assert [line.split()[0] for line in lines[2:4]] == ["width", "height"]
    assert all(math.isfinite(float(v)) for v in lines[2].split()[1:] + lines[3].split()[1:])
    assert lines[4].startswith("slope") and lines[5].startswith("resting size")


@pytest.mark.parametrize(("args", "message"), [(["--sizes", "0"], "--sizes: expected a number from 0.25 to 4"),
                                               (["--sizes", "1", "--shifts", "0"], "--sizes and --shifts: give one")])
def test_bad_sizes_are_one_line(tmp_path, capsys, args: list[str], message: str) -> None:
    try:
        status = main(["box-read", "--dataset", str(tmp_path), *args])
    except SystemExit as e:
        status = e.code
    assert status == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
