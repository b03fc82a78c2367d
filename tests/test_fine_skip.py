"""`fine_skip`: Lite0's stride-8 block 4 folded into dadiff-mobile's 16 px cells beside the neck (ours)."""

from __future__ import annotations

from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from dadiff.export.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from dadiff.export.cli import main  # noqa: E402
from dadiff.export.config import lite_config, mobile_config, validate_config, with_overrides  # noqa: E402
from dadiff.export.neck import FineSkip  # noqa: E402
from dadiff.export.network import build_model  # noqa: E402

GATED = {"align_residual": True}


def test_a_trained_tracker_gains_the_branch_as_its_identity():
    torch.manual_seed(0)
    plain = build_model(with_overrides(mobile_config(), GATED)).eval()
    skip = build_model(with_overrides(mobile_config(), GATED | {"fine_skip": True})).eval()
    missing, unexpected = skip.load_state_dict(plain.state_dict(), strict=False)
    assert unexpected == [] and missing == ["fine_skip.conv.weight"]
    z, x = torch.rand(1, 3, 127, 127) * 255, torch.rand(1, 3, 255, 255) * 255
    with torch.no_grad():
        for a, b in zip(plain(z, x), skip(z, x), strict=True):
            assert torch.equal(a, b)
        skip.fine_skip.conv.weight.normal_()
        assert not torch.allclose(plain(z, x)[1], skip(z, x)[1])


def test_the_branch_keeps_where_inside_a_cell_the_fine_map_is():
    """Space-to-depth: a fine pixel's position inside its 2 x 2 cell becomes its channel."""
    branch = FineSkip(1, 4, center_size=2)
    with torch.no_grad():
        branch.conv.weight.copy_(torch.eye(4).view(4, 4, 1, 1))
    fine = torch.zeros(1, 1, 4, 4)
    fine[0, 0, 0, 1] = 1.0  # top row, right column of cell (0, 0)
    out = branch(fine, template=False)
    assert out.shape == (1, 4, 2, 2) and out[0, :, 0, 0].tolist() == [0.0, 1.0, 0.0, 0.0]
    assert out[0, :, 1:, :].abs().sum() == 0 and out[0, :, :, 1:].abs().sum() == 0
    assert FineSkip(1, 4, center_size=2)(torch.zeros(1, 1, 8, 8), template=True).shape == (1, 4, 2, 2)


def test_the_option_is_checked():
    validate_config(with_overrides(mobile_config(), {"fine_skip": True}))
    with pytest.raises(ValueError, match="'fine_skip' needs the efficientnet-lite0-s16 trunk"):
        validate_config(with_overrides(lite_config(), {"fine_skip": True}))
    with pytest.raises(ValueError, match="'fine_skip' is 1; expected true or false"):
        validate_config(with_overrides(mobile_config(), {"fine_skip": 1}))


def test_a_model_with_the_branch_exports_with_parity(tmp_path, capsys):
    torch.manual_seed(3)
    net = build_model(with_overrides(mobile_config(), {"fine_skip": True}))
    with torch.no_grad():
        net.fine_skip.conv.weight.normal_(std=0.05)  # an open branch, as after training
    ckpt = tmp_path / "skip.pt"
    save_checkpoint(ckpt, net)
    assert load_checkpoint(ckpt).config.fine_skip
    code = main([str(ckpt), "-o", str(tmp_path / "m"), "--search-size", "223"])
    out = capsys.readouterr().out
    assert code == 0 and "OK" in out


def test_a_training_round_starts_the_branch_from_a_state_without_it(tmp_path):
    from dadiff.export.train import TrainConfig, build_network

    start = tmp_path / "start.pt"
    save_checkpoint(start, build_model(with_overrides(mobile_config(), GATED)))
    cfg = TrainConfig(out=str(tmp_path / "run"), stage="dadiff", family="dadiff-mobile", init=str(start),
                      model=GATED | {"fine_skip": True})
    net = build_network(cfg)
    assert net.cfg.fine_skip and torch.count_nonzero(net.fine_skip.conv.weight) == 0


SHIPPED = Path(__file__).resolve().parents[1] / "export" / "configs" / "mobile-dadiff-fineskip.toml"


def test_the_shipped_round_starts_from_the_default_state():
    from dadiff.export.train import TrainConfig, build_network

    net = build_network(TrainConfig.from_toml(SHIPPED))
    assert net.cfg.fine_skip and net.cfg.align_residual
