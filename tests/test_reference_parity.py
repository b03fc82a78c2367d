"""The onboard tracker (onnxruntime) against the PyTorch reference tracker on one generated sequence."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dadiff.export.checkpoint import load_checkpoint  # noqa: E402
from dadiff.export.reference import TorchBackend  # noqa: E402
from dadiff.runtime import Tracker  # noqa: E402
from runtime_scenes import iou, moving_sequence  # noqa: E402


def test_onnx_tracker_follows_the_torch_reference(lite_checkpoint, lite_model_dir):
    frames, boxes = moving_sequence(60)
    onboard = Tracker.load(str(lite_model_dir), threads=1)
    reference = Tracker(TorchBackend(load_checkpoint(lite_checkpoint)))
    onboard.init(frames[0], boxes[0])
    reference.init(frames[0], boxes[0])
    ious, dscores = [], []
    for frame in frames[1:]:
        a, b = onboard.update(frame), reference.update(frame)
        ious.append(iou(a.box, b.box))
        dscores.append(abs(a.score - b.score))
        assert a.state == b.state
    assert len(ious) >= 50
    assert min(ious) >= 0.99, f"min per-frame IoU {min(ious):.4f}"
    assert max(dscores) <= 1e-3, f"max |dscore| {max(dscores):.2e}"
    print(f"\nparity over {len(ious)} frames: min IoU {min(ious):.6f}, max |dscore| {max(dscores):.2e}, "
          f"mean IoU {np.mean(ious):.6f}")
