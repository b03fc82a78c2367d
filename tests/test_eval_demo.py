"""run_demo: one generated night sequence tracked into an annotated video."""

from __future__ import annotations

import cv2
import pytest

from dadiff.runtime.commands.demo import run_demo
from dadiff.runtime.errors import ModelError

pytest.importorskip("skimage")  # the scene photos


def test_demo_writes_video_and_reports(tmp_path, capsys):
    pytest.importorskip("onnx")
    from runtime_models import write_corr_model

    model = write_corr_model(tmp_path / "corr")
    result = run_demo(str(model), tmp_path / "out", seed=1, frames=8)
    assert set(result) >= {"video", "frames", "fps", "success", "precision", "norm_precision"}
    assert result["frames"] == 8 and 0 <= result["success"] <= 1
    capture = cv2.VideoCapture(str(result["video"]))
    count = 0
    while capture.read()[0]:
        count += 1
    assert count == 8
    assert "success" in capsys.readouterr().out


def test_demo_without_default_model_raises_a_clear_error(tmp_path, no_shipped_model):
    with pytest.raises(ModelError, match="no trained default model"):
        run_demo(None, tmp_path)
