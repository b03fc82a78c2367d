"""dadiff-run, dadiff-eval and dadiff-bench take a DaDiff-GAT model folder like any other (the export is shared
with tests/test_export_gat_parity.py: built once per test run)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

pytest.importorskip("torch")

from dadiff.runtime import Tracker
from dadiff.runtime.commands import run as cli  # noqa: E402
from dadiff.runtime.commands.bench_lanes import time_search  # noqa: E402
from dadiff.runtime.commands.eval import main as eval_main  # noqa: E402

FRAMES = 3  # 66 GFLOP per search frame: a few frames say the commands work


@pytest.fixture(scope="module")
def sequence(tmp_path_factory, gat_frames):
    """The tracker fixture's first frames as an OTB-style folder (dataset/Night1/img + groundtruth_rect.txt)."""
    frames, boxes = gat_frames
    root = tmp_path_factory.mktemp("gatseq") / "dataset"
    (root / "Night1" / "img").mkdir(parents=True)
    for i, frame in enumerate(frames[:FRAMES]):
        cv2.imwrite(str(root / "Night1" / "img" / f"{i + 1:04d}.png"), frame)
    lines = "".join(f"{x},{y},{w},{h}\n" for x, y, w, h in boxes[:FRAMES])
    (root / "Night1" / "groundtruth_rect.txt").write_text(lines)
    return root


def test_dadiff_run_tracks_with_a_gat_model(gat_model_dir, sequence, tmp_path):
    folder, _ = gat_model_dir
    out = tmp_path / "run.jsonl"
    assert cli.main(["--video", str(sequence / "Night1"), "--model", str(folder), "--threads", "1", "--output",
                     str(out), "--preset", "UAVDark70"]) == 0
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(rows) == FRAMES and rows[0]["state"] == "init" and rows[-1]["state"] in ("tracking", "uncertain")


def test_dadiff_eval_runs_a_gat_model(gat_model_dir, sequence, tmp_path):
    folder, _ = gat_model_dir
    args = ["run", "--dataset", str(sequence), "--output", str(tmp_path / "results"), "--model", str(folder),
            "--threads", "1", "--no-plots", "--no-progress"]
    assert eval_main(args) == 0
    assert any((tmp_path / "results").rglob("Night1.txt"))


def test_bench_times_the_search_graph_with_the_template_roi(gat_model_dir, sequence):
    """dadiff-bench --compare-torch's ONNX side: the recorded template inputs include the target's ROI."""
    from dadiff.runtime.backend import RecordingBackend

    folder, _ = gat_model_dir
    tracker = Tracker.load(folder, threads=1)
    recorder = RecordingBackend(tracker.backend, 1)
    frame = cv2.imread(str(sequence / "Night1" / "img" / "0001.png"))
    Tracker(recorder).init(frame, (200, 150, 40, 30))
    assert recorder.rois[0].shape == (1, 4)
    x = np.zeros((1, 3, 287, 287), np.float32)
    times = time_search(tracker, {"z": recorder.templates[0], "roi": recorder.rois[0]}, x, repeats=1)
    assert len(times) == 1 and times[0] > 0


def test_int8_quantisation_refuses_a_gat_model_in_one_line(gat_model_dir):
    from dadiff.export.quantize import QuantizeError, check_source

    folder, _ = gat_model_dir
    with pytest.raises(QuantizeError, match="dadiff-gat-googlenet model stays fp32"):
        check_source(folder)


def test_template_without_the_roi_is_refused_in_one_line(gat_model_dir):
    from dadiff.runtime import InputError, OnnxBackend

    folder, _ = gat_model_dir
    backend = OnnxBackend(folder, threads=1)
    with pytest.raises(InputError, match="takes the target's ROI"):
        backend.template(np.zeros((1, 3, 127, 127), np.float32))
