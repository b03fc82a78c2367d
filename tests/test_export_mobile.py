"""dadiff-mobile: stride-16 geometry, the 0.5 GFLOP budget with the DaDiff block, export parity, the teacher."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest

torch = pytest.importorskip("torch")

from conftest import random_crops  # noqa: E402
from dadiff.export.checkpoint import detect_family, load_checkpoint, save_checkpoint  # noqa: E402
from dadiff.export.config import mobile_config  # noqa: E402
from dadiff.export.network import build_model  # noqa: E402
from dadiff.export.onnx_export import SearchGraph, count_gflop, export_model  # noqa: E402

BUDGET_GFLOP = 0.5
TEACHER = Path(__file__).resolve().parents[2] / "shared" / "weights" / "nanotrack" / "v3"


@pytest.fixture(scope="module")
def mobile():
    torch.manual_seed(0)
    return build_model(mobile_config(), pretrained_backbone=True).eval()


def test_search_frame_with_dadiff_within_budget(mobile):
    z, x = random_crops()
    with torch.no_grad():
        _, kcls, kloc = mobile.template_kernels(z)
    per_frame = count_gflop(SearchGraph(mobile), x, *kcls, *kloc)
    assert 0.3 < per_frame <= BUDGET_GFLOP, per_frame
    assert mobile.cfg.use_dadiff and mobile.cfg.align == "paper" and mobile.cfg.ddim_steps == 2


def test_geometry_is_stride_16_and_centred(mobile):
    z, x = random_crops()
    with torch.no_grad():
        zf, kcls, _ = mobile.template_kernels(z)
        cls, loc = mobile.track(x, *mobile.head.kernels(zf))
    tr = mobile.cfg.tracker
    assert zf[0].shape[-1] == 6 and kcls[0].shape[-1] == 4
    assert cls.shape == (1, 2, 13, 13) and loc.shape == (1, 4, 13, 13)
    assert tr.stride == 16 and tr.score_size == 13 and tr.point_origin == -96


def test_template_crop_is_the_centre():
    """The neck keeps the centre of the template map whatever its size (15 -> 4..11 as the release)."""
    from dadiff.export.neck import AdjustLayer

    layer = AdjustLayer(1, 1, 7).eval()
    torch.nn.init.ones_(layer.downsample[0].weight)
    x = torch.arange(15.0).view(1, 1, 1, 15).expand(1, 1, 15, 15)
    with torch.no_grad():
        out = layer(x, template=True)
        search = layer(x, template=False)
    assert out.shape[-1] == 7 and search.shape[-1] == 15
    assert torch.allclose(out[0, 0, 0] / out[0, 0, 0, 0], torch.arange(4.0, 11.0) / 4)


def test_export_parity_and_family_detection(tmp_path, mobile):
    path = tmp_path / "mobile.pt"
    save_checkpoint(path, mobile)
    loaded = load_checkpoint(path)
    assert loaded.config.family == "dadiff-mobile"
    assert detect_family(mobile.state_dict()) == "dadiff-mobile"
    report = export_model(loaded, tmp_path / "model", "test-mobile")
    assert report.max_parity < 1e-4
    assert report.gflop_search <= BUDGET_GFLOP
    stem = [n.op_type for n in onnx.load(tmp_path / "model" / "search.onnx").graph.node
            if n.name.startswith("/backbone/") and "_blocks" not in n.name]
    assert "Div" not in stem and "Slice" not in stem and stem.count("Sub") == 1  # normalisation folded
    from dadiff.runtime.tracker import Tracker

    tracker = Tracker.load(tmp_path / "model", threads=1)
    frame = np.full((360, 640, 3), 40, np.uint8)
    tracker.init(frame, (300, 160, 40, 30))
    result = tracker.update(frame)
    assert np.all(np.isfinite(result.box))


@pytest.mark.skipif(not TEACHER.is_dir(), reason="NanoTrack v3 teacher weights are not at ../shared/weights")
def test_teacher_finds_the_target_on_our_grid():
    """A textured patch centred in the template and moved by (+32, -48) px in the search crop: the teacher's
    peak must land on our cell for that offset, and its box distances must fit the patch."""
    from dadiff.export.teacher import NanoTrackTeacher

    rng = np.random.default_rng(0)
    patch = cv2_blur(rng.integers(0, 255, (64, 64, 3)).astype(np.float32))
    z = np.full((127, 127, 3), 110, np.float32)
    z[31:95, 31:95] = patch
    x = np.full((255, 255, 3), 110, np.float32)
    x[95 - 48:159 - 48, 95 + 32:159 + 32] = patch
    chw = [torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None] for a in (z, x)]
    feats, prob, loc = NanoTrackTeacher(TEACHER)(*chw, 13)
    assert feats.shape == (1, 96, 16, 16) and prob.shape == (1, 13, 13) and loc.shape == (1, 4, 13, 13)
    iy, ix = np.unravel_index(int(prob[0].argmax()), (13, 13))
    assert (ix, iy) == (6 + 2, 6 - 3)
    assert np.allclose(loc[0, :, iy, ix].numpy(), 32, atol=12)  # l, t, r, b of the 64 px patch


def cv2_blur(img: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(img, (0, 0), 2) * 3 - 200
