"""`dadiff-bench`: the report's structure, the torch comparison and step sweep, and one-line errors.

Structure only: no assertion here depends on how fast this machine is.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from dadiff.runtime.commands import bench as bench_cli
from dadiff.runtime.commands.bench_lanes import STAGES, BenchLane, run_lanes, write_night_video
from dadiff.runtime.evaluation.evaluate import nano_available, nano_problem, opencv_available
from runtime_models import write_corr_model


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_corr_model(tmp_path_factory.mktemp("bench") / "corr-test")


def _report(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict:
    assert bench_cli.main([*argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_report_has_every_stage_and_memory(model_dir: Path, capsys) -> None:
    report = _report(capsys, ["--model", str(model_dir), "--max-frames", "40", "--clip", "15", "--warmup", "3",
                              "--threads", "1"])
    (result,) = report["results"]
    assert result["frames"] == 40 and result["fps"] > 0
    for stage in (*STAGES, "template"):
        assert 0 < result[stage]["p50"] <= result[stage]["p95"], stage
    # the 15-frame clip is looped: the template branch ran at every restart, plus the timed inits
    assert len(result["rss_mb"]["samples"]) == 2 and result["rss_mb"]["peak"] >= result["rss_mb"]["last"] > 0
    assert 0 < result["outside_onnx_tracker"] < 1 and 0 < result["outside_onnx_frame"] < 1
    assert report["threads"] == 1 and report["machine"]["physical"] >= 1


def test_two_models_side_by_side_with_night_success(model_dir: Path, capsys) -> None:
    argv = ["--model", str(model_dir), "--model", str(model_dir), "--max-frames", "10", "--clip", "8", "--warmup", "1",
            "--success", "1", "--success-frames", "12"]
    assert bench_cli.main(argv) == 0
    out = capsys.readouterr().out
    for label in ("search graph (ONNX)", "MAVLink 275 encode", "FPS end to end", "night success", "peak RSS"):
        assert label in out
    assert "x)" in out.split("FPS end to end")[1].splitlines()[0]  # second model: ratio to the first


def test_torch_comparison_and_step_sweep(lite_checkpoint: Path, lite_model_dir: Path, capsys) -> None:
    argv = ["--model", str(lite_model_dir), "--checkpoint", str(lite_checkpoint), "--compare-torch", "--sweep-steps",
            "1",
            "--max-frames", "4", "--clip", "6", "--warmup", "1", "--threads", "1"]
    report = _report(capsys, argv)
    first, k1 = report["results"]
    assert first["torch"]["crops"] == 5 and first["torch"]["ratio"] > 0
    assert first["torch"]["torch_eager"]["p50"] > 0 and first["torch"]["ort"]["p50"] > 0
    assert (first["ddim_steps"], k1["ddim_steps"]) == (2, 1)
    assert first["gflop_search"] > k1["gflop_search"] > 0  # one denoiser call less


def test_nano_row_and_ratio(model_dir: Path, capsys) -> None:
    if not nano_available():
        pytest.skip(nano_problem())
    argv = ["--model", str(model_dir), "--max-frames", "6", "--clip", "5", "--warmup", "1", "--threads", "1", "--nano",
            "--success", "1", "--success-frames", "5"]
    assert bench_cli.main(argv) == 0
    out = capsys.readouterr().out
    header, columns = out.splitlines()[:2]
    assert "avx2 " in header and "avx512f " in header and "avx512_vnni " in header
    assert "TrackerNano (NanoTrack v2, OpenCV " in columns
    fps = next(line for line in out.splitlines() if line.startswith("FPS end to end"))
    assert len(fps.split()) == 7 and fps.endswith("x)")  # ours, then TrackerNano with its ratio
    assert "runs at" in out and "TrackerNano's frame rate" in out
    report = _report(capsys, [*argv, "--no-nano"])
    assert "nano" not in report and set(report["machine"]["flags"]) == {"avx2", "avx512f", "avx512_vnni"}
    report = _report(capsys, argv)
    nano = report["nano"]
    assert nano["fps"] > 0 and nano["tracker"]["p50"] > 0 and nano["night"]["sequences"] == 1
    assert nano["ratio"]["fps"] == pytest.approx(report["results"][0]["fps"] / nano["fps"])


def test_nano_without_weights_is_one_line(model_dir: Path, tmp_path: Path, capsys) -> None:
    assert bench_cli.main(["--model", str(model_dir), "--nano", "--nano-dir", str(tmp_path), "--max-frames", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nanotrack_backbone_sim.onnx" in err
    if opencv_available("nano"):  # named dadiff-eval's option, --tracker nano, which dadiff-bench does not have
        assert err.startswith("dadiff-bench: error: --nano needs NanoTrack v2's") and "--tracker" not in err
        assert err.endswith("give the folder that holds them with --nano-dir DIR or DADIFF_NANO_DIR=DIR")


def test_nano_left_out_by_default_says_why(model_dir: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    """Without its weights, TrackerNano used to vanish from the report without a word."""
    monkeypatch.setenv("DADIFF_NANO_DIR", str(tmp_path))
    argv = ["--model", str(model_dir), "--max-frames", "2", "--clip", "3", "--warmup", "0", "--threads", "1", "--json"]
    assert bench_cli.main(argv) == 0
    captured = capsys.readouterr()
    assert "nano" not in json.loads(captured.out)  # stdout stays one JSON document
    (note,) = captured.err.strip().splitlines()
    assert note.startswith("dadiff-bench: note: TrackerNano was not timed: ")
    assert note.endswith(" (--no-nano silences this note)")
    if opencv_available("nano"):
        assert (f"nanotrack_backbone_sim.onnx and nanotrack_head_sim.onnx were not found in {tmp_path} (from "
                "DADIFF_NANO_DIR); give --nano-dir DIR or DADIFF_NANO_DIR=DIR") in note
    assert bench_cli.main([*argv, "--no-nano"]) == 0
    assert capsys.readouterr().err == ""


def test_peak_is_measured(model_dir: Path, capsys) -> None:
    pytest.importorskip("torch")  # --peak builds its probe graph with the export side
    report = _report(capsys, ["--model", str(model_dir), "--max-frames", "3", "--clip", "5", "--warmup", "0", "--peak"])
    assert report["peak_gflops"] > 1


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--model", "/no/such/model"], "/no/such/model"),
        (["--model", "{model}", "--compare-torch", "--max-frames", "2"], "checkpoint.pt: checkpoint not found"
         if importlib.util.find_spec("torch") else "--compare-torch needs the export side"),  # companion install
        (["--model", "{model}", "--sweep-steps", "one", "--checkpoint", "{model}/search.onnx"], "--sweep-steps"),
        (["--model", "{model}", "--success", "-1"], "argument --success: expected an integer of at least 0"),
        (["--model", "{model}", "--interleave", "-5"], "argument --interleave: expected an integer from 0 to 1000000"),
        (["--model", "{model}", "--hp", "foo=1", "--max-frames", "2"], "unknown override 'foo'"),
        # checked at parsing, naming the option: a traceback, a temporary file's name, a numpy allocation error
        (["--model", "{model}", "--seed", "-1", "--max-frames", "2"],
         "argument --seed: expected an integer of at least 0"),
        (["--model", "{model}", "--clip", "1", "--max-frames", "2"],
         "argument --clip: expected an integer from 2 to 1000"),
        (["--model", "{model}", "--max-frames", "1000000000000"],
         "argument --max-frames: expected an integer from 1 to 1000000"),
        (["--model", "{model}", "--warmup", "-1"], "argument --warmup: expected an integer from 0"),
        # was silently ignored
        (["--model", "{model}", "--checkpoint", "nope.pt", "--max-frames", "2", "--clip", "3"],
         "--checkpoint applies to --compare-torch and --sweep-steps only"),
    ],
)
def test_bad_input_is_one_line(model_dir: Path, capsys, monkeypatch, tmp_path, argv: list[str], expected: str) -> None:
    monkeypatch.setenv("DADIFF_NANO_DIR", str(tmp_path))  # no weights, as on a clean clone: no note before the error
    argv = [a.replace("{model}", str(model_dir)) for a in argv]
    try:
        assert bench_cli.main(argv) == 2
    except SystemExit as exc:  # usage errors leave through argparse
        assert exc.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err and err.startswith("dadiff-bench: error:")


def test_bad_settings_are_refused_before_the_clip_is_rendered(model_dir: Path, capsys, monkeypatch) -> None:
    """Rendering the night clip takes 15-20 s on two cores: a mistyped --hp must not wait for it."""

    def rendered(*args: object, **kwargs: object) -> None:
        raise AssertionError("the clip was rendered before the settings were checked")

    monkeypatch.setattr(bench_cli, "write_night_video", rendered)
    assert bench_cli.main(["--model", str(model_dir), "--hp", "swap_distance=2", "--max-frames", "2"]) == 2
    assert "swap_distance" in capsys.readouterr().err


class _LoggingTracker:
    """A baseline-style tracker that records which lane ran when (a test double for the turn order)."""

    def __init__(self, name: str, log: list[str]) -> None:
        self.name, self.log = name, log

    def init(self, frame, box) -> None:
        pass

    def update(self, frame):
        self.log.append(self.name)
        return (0.0, 0.0, 1.0, 1.0)


@pytest.mark.parametrize(("block", "expected"), [
    (3, "aa bb aaa bbb aaa bbb a b"),
    (0, "aa aaaaaaa bb bbbbbbb"),
])
def test_lanes_take_turns(tmp_path: Path, block: int, expected: str) -> None:
    video = write_night_video(tmp_path, frames=5)
    log: list[str] = []
    lanes = [BenchLane(_LoggingTracker(n, log), video, frames=7, template_runs=2) for n in "ab"]
    runs = run_lanes(lanes, warmup=2, block=block)
    assert "".join(log) == expected.replace(" ", "")
    for run in runs:  # each lane's own time only, every frame timed once
        assert run.frames == 7 and run.seconds > 0 and not np.isnan(run.stages["frame"]).any()
