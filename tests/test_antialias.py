"""`antialias_blocks`: Lite0's strided blocks blurring before they subsample (model option, ours)."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from dadiff.export.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from dadiff.export.cli import main  # noqa: E402
from dadiff.export.config import (  # noqa: E402
    ModelConfig,
    lite_config,
    mobile_config,
    validate_config,
    with_overrides,
)
from dadiff.export.efficientnet_lite import (  # noqa: E402
    BLOCK_SPECS,
    BlurDownsample,
    EfficientNetLite0,
    subsampling_blocks,
)
from dadiff.export.network import build_model  # noqa: E402


def test_the_blocks_that_subsample():
    assert subsampling_blocks(15, None) == tuple(i for i, spec in enumerate(BLOCK_SPECS) if spec[1] == 2)
    assert subsampling_blocks(15, None) == (1, 3, 5, 11)
    assert subsampling_blocks(10, 5) == (1, 3)  # dadiff-lite: atrous from block 5


def test_blur_downsample_halves_the_map_and_keeps_a_flat_one_flat():
    flat = torch.full((1, 4, 16, 16), 3.0)
    out = BlurDownsample(4)(flat)
    assert out.shape == (1, 4, 8, 8)
    assert torch.allclose(out[..., 1:, 1:], flat[..., :7, :7])  # the zero padding only touches the first row/column
    step = torch.zeros(1, 1, 8, 8)
    step[..., 4:] = 1.0  # an edge between columns 3 and 4: plain subsampling keeps it hard, the blur softens it
    assert torch.allclose(BlurDownsample(1)(step)[0, 0, 3], torch.tensor([0.0, 0.0, 0.75, 1.0]))  # not 1.0


def test_an_antialiased_trunk_loads_the_same_weights_and_keeps_its_map_size():
    torch.manual_seed(0)
    plain = EfficientNetLite0(last_block=6, out_blocks=(6,)).eval()
    blurred = EfficientNetLite0(last_block=6, out_blocks=(6,), antialias_blocks=(3, 5)).eval()
    assert plain.state_dict().keys() == blurred.state_dict().keys()
    blurred.load_state_dict(plain.state_dict())
    x = torch.rand(1, 3, 255, 255) * 255
    with torch.no_grad():
        a, b = plain(x)[0], blurred(x)[0]
    assert a.shape == b.shape == (1, 80, 16, 16)
    assert (a - b).abs().max() > 0.05 * a.abs().max()  # the blur changes what the block passes on
    with pytest.raises(ValueError, match=r"antialias_blocks \[6\]: not a stride-2 block"):
        EfficientNetLite0(last_block=6, out_blocks=(6,), antialias_blocks=(6,))


def test_the_option_goes_through_the_config_and_its_checks():
    cfg = with_overrides(mobile_config(), {"antialias_blocks": [5]})  # a TOML list
    assert cfg.antialias_blocks == (5,)
    validate_config(cfg)
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg  # stored in checkpoints
    old = mobile_config().to_dict()
    del old["antialias_blocks"]  # a checkpoint from before the option
    assert ModelConfig.from_dict(old).antialias_blocks == ()
    with pytest.raises(ValueError, match=r"'antialias_blocks' is \[6\]; efficientnet-lite0-s16 subsamples in "
                                         r"blocks \[1, 3, 5\]"):
        validate_config(with_overrides(mobile_config(), {"antialias_blocks": [6]}))
    with pytest.raises(ValueError, match=r"subsamples in blocks \[1, 3\]"):  # atrous from block 5
        validate_config(with_overrides(lite_config(), {"antialias_blocks": [5]}))
    with pytest.raises(ValueError, match="'antialias_blocks' is 5; expected a list"):
        validate_config(with_overrides(mobile_config(), {"antialias_blocks": 5}))


def test_an_antialiased_model_exports_with_parity(tmp_path, capsys):
    torch.manual_seed(2)
    ckpt = tmp_path / "aa.pt"
    save_checkpoint(ckpt, build_model(with_overrides(mobile_config(), {"antialias_blocks": [5]})))
    assert load_checkpoint(ckpt).config.antialias_blocks == (5,)
    code = main([str(ckpt), "-o", str(tmp_path / "m"), "--search-size", "223"])
    out = capsys.readouterr().out
    assert code == 0 and "OK" in out

