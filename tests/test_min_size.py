"""`dadiff-export --min-size`: the smallest box the runtime keeps, and what it does for a tiny target."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from dadiff.export.cli import main  # noqa: E402
from dadiff.runtime.tracker import Tracker  # noqa: E402
from runtime_models import write_corr_model  # noqa: E402


def _graph_and_meta(path) -> tuple[bytes, dict[str, str]]:
    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    model.ClearField("metadata_props")
    return model.SerializeToString(), meta


def test_export_writes_the_min_size_and_keeps_the_graphs(tmp_path, capsys, mobile_checkpoint):
    assert main([str(mobile_checkpoint), "-o", str(tmp_path / "ten"), "--name", "m"]) == 0
    assert main([str(mobile_checkpoint), "-o", str(tmp_path / "six"), "--name", "m", "--min-size", "6"]) == 0
    capsys.readouterr()
    for graph in ("template", "search"):
        ten, ten_meta = _graph_and_meta(tmp_path / "ten" / f"{graph}.onnx")
        six, six_meta = _graph_and_meta(tmp_path / "six" / f"{graph}.onnx")
        assert ten == six
        assert (ten_meta.pop("min_size"), six_meta.pop("min_size")) == ("10.0", "6.0")
        assert ten_meta == six_meta
    tracker = Tracker.load(tmp_path / "six", threads=1)
    assert tracker.geometry.min_size == 6.0


@pytest.mark.parametrize("value", ["0", "0.5", "-3", "nan", "inf", "small", "1e308", "1001"])  # 1e308 overflowed a crop
def test_a_bad_min_size_is_one_line_and_exit_2(tmp_path, capsys, mobile_checkpoint, value):
    with pytest.raises(SystemExit) as exc:
        main([str(mobile_checkpoint), "-o", str(tmp_path / "m"), f"--min-size={value}"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "--min-size" in err and value in err
    assert not (tmp_path / "m").exists()


def test_min_size_is_refused_for_a_model_folder(tmp_path, capsys):
    folder = write_corr_model(tmp_path / "corr")
    code = main([str(folder), "--quantize", "int8", "--min-size", "6", "-o", str(tmp_path / "q")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--min-size applies to checkpoints" in err


def _tiny_target_box(min_size: str, tmp_path) -> tuple[float, float]:
    """Track a 6 x 6 px bright square drifting over a dark frame; the box's mean side over the last frames."""
    tracker = Tracker.load(write_corr_model(tmp_path / f"corr-{min_size}", meta={"min_size": min_size}), threads=1)
    rng = np.random.default_rng(3)
    background = rng.integers(0, 30, (240, 320, 3)).astype(np.uint8)
    sides = []
    for k in range(25):
        frame = background.copy()
        x, y = 150 + k, 110 + k // 2
        frame[y:y + 6, x:x + 6] = 230
        if k == 0:
            tracker.init(frame, (x, y, 6, 6))
        else:
            box = tracker.update(frame).box
            sides.append((box[2], box[3]))
    return tuple(np.mean(sides[-10:], axis=0))


def test_below_the_released_floor_the_box_fits_a_tiny_target(tmp_path):
    assert _tiny_target_box("10", tmp_path) == pytest.approx((10.0, 10.0))  # held at the released floor
    w, h = _tiny_target_box("4", tmp_path)
    assert w < 9 and h < 9
