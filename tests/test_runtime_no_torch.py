"""dadiff.runtime must work where torch, onnx and dadiff.export are not installed (the drone)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import cv2

from runtime_models import write_corr_model
from runtime_scenes import moving_sequence
from torchless import PRELUDE

CHILD = PRELUDE + textwrap.dedent(
    """
    from pathlib import Path
    import cv2

    from dadiff import models
    from dadiff.runtime import Tracker
    from dadiff.runtime.commands import run as cli

    model, seq = sys.argv[1], sys.argv[2]
    images = sorted(Path(seq, "img").iterdir())
    box = tuple(float(v) for v in open(f"{seq}/groundtruth_rect.txt").readline().split(","))
    tracker = Tracker.load(model, threads=1)
    tracker.init(cv2.imread(str(images[0])), box)
    states = [tracker.update(cv2.imread(str(p))).state for p in images[1:6]]
    assert states == ["tracking"] * 5, states
    assert models.DEFAULT_MODEL in models.list_models()  # the shipped default resolves without torch
    argv = ["--video", seq, "--model", model, "--max-frames", "4", "--output", f"{seq}/out.csv"]
    assert cli.main(argv) == 0
    from dadiff.runtime.commands import bench as bench_cli

    assert bench_cli.main(["--model", model, "--max-frames", "5", "--clip", "6", "--warmup", "1", "--json"]) == 0
    # one line: needs dadiff[export]
    assert bench_cli.main(["--model", model, "--max-frames", "5", "--compare-torch"]) == 2
    loaded = [m for m in sys.modules if any(m == b or m.startswith(b + ".") for b in BLOCKED)]
    assert not loaded, loaded
    print("runtime ok without torch/onnx/export")
    """
)


def test_runtime_without_torch_onnx_or_export(tmp_path: Path) -> None:
    model = write_corr_model(tmp_path / "model")
    seq = tmp_path / "seq"
    (seq / "img").mkdir(parents=True)
    frames, boxes = moving_sequence(60)
    frames, boxes = frames[:8], boxes[:8]
    for k, frame in enumerate(frames):
        cv2.imwrite(str(seq / "img" / f"{k:04d}.png"), frame)
    (seq / "groundtruth_rect.txt").write_text("".join(",".join(map(str, b)) + "\n" for b in boxes))
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(model), str(seq)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert "runtime ok without torch/onnx/export" in proc.stdout
    assert len((seq / "out.csv").read_text().splitlines()) == 1 + 4
