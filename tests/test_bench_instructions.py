"""`dadiff-bench --instructions`: instructions per update counted under valgrind (a CPU without AVX-512).

The counts themselves depend on the machine's libraries, never asserted; the arithmetic, the report, the
counted program and the errors are.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from dadiff.runtime.commands import bench as bench_cli
from dadiff.runtime.commands import bench_instructions as instructions
from dadiff.runtime.commands.bench_instructions import InstructionCountError, UpdateCount, callgrind_total, per_update
from dadiff.runtime.commands.bench_lanes import write_night_video
from dadiff.runtime.evaluation.evaluate import nano_available, nano_files
from runtime_models import write_corr_model

CALLGRIND_TEXT = "version: 1\ncreator: callgrind-3.19.0\nevents: Ir\nsummary: 2016277912\n\ntotals: 2016277912\n"


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_corr_model(tmp_path_factory.mktemp("instructions") / "corr-test")


def test_totals_and_instructions_per_update() -> None:
    assert callgrind_total(CALLGRIND_TEXT) == 2016277912
    with pytest.raises(InstructionCountError, match="summary"):
        callgrind_total("events: Ir\n")
    count = per_update("m", (1_000, 4_200), (4, 36))
    assert count.instructions == pytest.approx(100.0) and count.runs == (1_000, 4_200)
    with pytest.raises(InstructionCountError, match="no more instructions"):
        per_update("m", (5_000, 5_000), (4, 36))


def test_the_counted_program_tracks_the_clip(model_dir: Path, tmp_path: Path) -> None:
    """What valgrind runs: load the clip, init, N updates, exit 0 (here without valgrind, in seconds)."""
    video = write_night_video(tmp_path, 0, 8)
    clip = instructions.write_clip(video.path, tmp_path / "clip.npy")
    kinds = [("model", str(model_dir))]
    if nano_available():
        kinds.append(("nano", str(nano_files()[0].parent)))
    for kind, target in kinds:
        command = instructions._worker_command(kind, target, clip, video.first_box, 3)
        done = subprocess.run(command, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr


def test_the_clip_is_the_first_frames_as_one_array(tmp_path: Path) -> None:
    """The counted program loads frames, not a video: decoding is not counted and does not vary the totals."""
    video = write_night_video(tmp_path, 0, 60)
    clip = np.load(instructions.write_clip(video.path, tmp_path / "clip.npy"))
    assert clip.shape == (instructions.CLIP, 360, 640, 3) and clip.dtype == np.uint8
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"not a video")
    with pytest.raises(InstructionCountError, match="broken.mp4: fewer than 2 frames"):
        instructions.write_clip(broken, tmp_path / "broken.npy")


def test_report_sets_each_model_against_tracker_nano(model_dir: Path, monkeypatch, capsys) -> None:
    counted = []

    def fake_count(kind, target, clip, box, name, updates=instructions.UPDATES):
        counted.append(kind)
        return UpdateCount(name, 40e6 if kind == "model" else 20e6, (1, 2))

    monkeypatch.setattr(bench_cli, "count_updates", fake_count)
    monkeypatch.setattr(bench_cli, "valgrind_path", lambda: "/usr/bin/valgrind")
    monkeypatch.setattr(bench_cli, "_use_nano", lambda args: (True, None))
    monkeypatch.setattr(bench_cli, "nano_files", lambda folder: (Path("/weights/v2/backbone.onnx"), None))
    argv = ["--model", str(model_dir), "--instructions", "--clip", "5"]
    assert bench_cli.main(argv) == 0
    out = capsys.readouterr().out
    assert "without AVX-512" in out and counted == ["model", "nano"]
    row = next(line for line in out.splitlines() if line.startswith("corr-test"))
    assert row.split()[1:] == ["40.0", "M", "0.50x"]
    assert bench_cli.main([*argv, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["results"][0]["instructions"] == 40e6 and report["nano"]["instructions"] == 20e6


def test_without_valgrind_is_one_line(model_dir: Path, monkeypatch, capsys) -> None:
    monkeypatch.setattr(instructions.shutil, "which", lambda name: None)
    assert bench_cli.main(["--model", str(model_dir), "--instructions"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "needs valgrind" in err


@pytest.mark.valgrind
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind is not installed")
def test_a_real_count_under_valgrind(model_dir: Path, tmp_path: Path) -> None:
    """The whole path once, on the tiny test model: valgrind runs the program (it would stop with SIGILL at an
    AVX-512 instruction) and the longer run counts more. The same program's totals usually vary by under 1e7,
    but on a 2-core Xeon (2026-12-05) two of four runs had the 1-update run count 1.1e8 more than the 5-update
    one; forty-eight updates of the tiny model (6.4e6 each, 3e8 in all) stand clear of that."""
    video = write_night_video(tmp_path, 0, 6)
    clip = instructions.write_clip(video.path, tmp_path / "clip.npy")
    count = instructions.count_updates("model", str(model_dir), clip, video.first_box, "corr-test", (1, 49))
    assert count.instructions > 0 and count.runs[1] > count.runs[0]
