"""`head_upsample`: the BAN head answering on a grid finer than the features' stride (model option, ours)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from dadiff.export.checkpoint import CheckpointError, load_checkpoint, save_checkpoint  # noqa: E402
from dadiff.export.cli import main  # noqa: E402
from dadiff.export.config import ModelConfig, mobile_config, validate_config, with_head_upsample  # noqa: E402
from dadiff.export.network import build_model  # noqa: E402
from dadiff.export.search_size import with_search_size  # noqa: E402
from dadiff.export.teacher import refine_teacher_maps  # noqa: E402


def test_the_tracker_grid_moves_with_the_head():
    coarse = mobile_config()
    fine = with_head_upsample(coarse, 2)
    assert (fine.head_upsample, fine.tracker.stride, fine.tracker.score_size) == (2, 8, 25)
    assert fine.tracker.point_origin == coarse.tracker.point_origin == -96
    assert with_head_upsample(coarse, 1) == coarse
    assert ModelConfig.from_dict(fine.to_dict()) == fine  # stored in checkpoints
    validate_config(fine)
    with pytest.raises(ValueError, match="'head_upsample' is 3; expected an integer >= 1 that divides the stride 16"):
        with_head_upsample(coarse, 3)
    for not_an_integer in (True, 1.0, "2"):  # a TOML true or 1.0 is not silently the coarse grid
        with pytest.raises(ValueError, match="'head_upsample' is"):
            with_head_upsample(coarse, not_an_integer)
    with pytest.raises(ValueError, match="'head_upsample' is 0"):
        validate_config(replace(coarse, head_upsample=0))


def test_the_fine_head_keeps_the_coarse_answers_on_the_coarse_points():
    """A trained head starts a fine-grid round from itself: every second point is the coarse map's point."""
    torch.manual_seed(0)
    coarse = build_model(mobile_config()).eval()
    fine = build_model(with_head_upsample(mobile_config(), 2)).eval()
    fine.load_state_dict(coarse.state_dict())
    z, x = torch.rand(1, 3, 127, 127) * 255, torch.rand(1, 3, 255, 255) * 255
    with torch.no_grad():
        cls_c, loc_c = coarse(z, x)
        cls_f, loc_f = fine(z, x)
    assert cls_c.shape[-1] == 13 and cls_f.shape[-1] == 25
    assert torch.allclose(cls_f[..., ::2, ::2], cls_c, atol=1e-5)
    assert torch.allclose(loc_f[..., ::2, ::2], loc_c, rtol=1e-4)
    assert not torch.allclose(cls_f[..., 1::2, 1::2], cls_c[..., :-1, :-1], atol=1e-3)


def test_teacher_maps_on_the_fine_grid_measure_from_the_fine_points():
    """One box seen from every coarse point: on the fine grid each point's distances are to that box."""
    side, stride = 5, 16
    pos = torch.arange(side, dtype=torch.float32) * stride
    x1, y1, x2, y2 = 10.0, 20.0, 70.0, 50.0
    py, px = torch.meshgrid(pos, pos, indexing="ij")
    loc = torch.stack([px - x1, py - y1, x2 - px, y2 - py])[None]
    prob = torch.rand(1, side, side)
    prob_f, loc_f = refine_teacher_maps(prob, loc, 2)
    assert prob_f.shape == (1, 9, 9) and loc_f.shape == (1, 4, 9, 9)
    assert torch.equal(prob_f[:, ::2, ::2], prob)
    fpos = torch.arange(9, dtype=torch.float32) * 8
    fy, fx = torch.meshgrid(fpos, fpos, indexing="ij")
    expected = torch.stack([fx - x1, fy - y1, x2 - fx, y2 - fy]).clamp_min(1e-3)[None]
    assert torch.allclose(loc_f, expected, atol=1e-4)


@pytest.fixture(scope="module")
def fine_checkpoint(tmp_path_factory):
    torch.manual_seed(1)
    path = tmp_path_factory.mktemp("ckpt") / "fine.pt"
    save_checkpoint(path, build_model(with_head_upsample(mobile_config(), 2)))
    return path


def test_a_fine_head_shrinks_its_search_crop_by_whole_feature_cells(fine_checkpoint):
    small = with_search_size(load_checkpoint(fine_checkpoint), 223)
    tr = small.config.tracker
    assert (tr.instance_size, tr.stride, tr.score_size, tr.point_origin) == (223, 8, 21, -80)
    with pytest.raises(CheckpointError, match="must be one of 255, 223, 191, 159"):
        with_search_size(load_checkpoint(fine_checkpoint), 239)


def test_a_fine_head_exports_with_its_grid_in_the_metadata(tmp_path, capsys, fine_checkpoint):
    code = main([str(fine_checkpoint), "-o", str(tmp_path / "m"), "--search-size", "223"])
    out = capsys.readouterr().out
    assert code == 0 and "score map 21 x 21" in out and "OK" in out
    meta = ort.InferenceSession(str(tmp_path / "m" / "search.onnx")).get_modelmeta().custom_metadata_map
    assert (meta["stride"], meta["score_size"], meta["point_origin"]) == ("8", "21", "-80")


def test_a_training_config_sets_the_fine_grid_from_the_model_table(tmp_path):
    from dadiff.export.train import TrainConfig, model_config

    cfg = TrainConfig(out=str(tmp_path), stage="dadiff", family="dadiff-mobile",
                      model={"align_residual": True, "head_upsample": 2})
    mc = model_config(cfg)
    assert (mc.head_upsample, mc.tracker.stride, mc.tracker.score_size, mc.align_residual) == (2, 8, 25, True)


SHIPPED = Path(__file__).resolve().parents[1] / "export" / "configs" / "mobile-dadiff-fine.toml"


def test_the_fine_round_config_starts_from_the_shipped_state():
    from dadiff.export.train import TrainConfig, build_network

    cfg = TrainConfig.from_toml(SHIPPED)
    net = build_network(cfg)
    assert net.cfg.head_upsample == 2 and net.cfg.tracker.stride == 8

