"""`align_template`: the search side's tracking-oriented layer also attends to the template's features (ours)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from dadiff.export.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from dadiff.export.config import mobile_config, validate_config, with_overrides  # noqa: E402
from dadiff.export.network import build_model  # noqa: E402
from dadiff.export.onnx_export import export_model  # noqa: E402

GATED = {"align_residual": True}
READS = GATED | {"align_template": True}


def crops() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return torch.rand(1, 3, 127, 127, generator=g) * 255, torch.rand(1, 3, 255, 255, generator=g) * 255


def open_gate(net) -> None:
    """The block's gate as after training (the untrained one is 0, which hides the layer's output)."""
    with torch.no_grad():
        net.align_scale.fill_(0.5)


def test_a_trained_block_gains_the_attention_as_its_identity():
    torch.manual_seed(0)
    plain = build_model(with_overrides(mobile_config(), GATED)).eval()
    reads = build_model(with_overrides(mobile_config(), READS)).eval()
    open_gate(plain)
    missing, unexpected = reads.load_state_dict(plain.state_dict(), strict=False)
    assert unexpected == [] and missing and all(k.startswith(("align_track.template_", "align_track.norm_template."))
                                                for k in missing)
    z, x = crops()
    with torch.no_grad():
        for a, b in zip(plain(z, x), reads(z, x), strict=True):
            assert torch.equal(a, b)
        reads.align_track.template_scale.fill_(0.5)
        assert not torch.allclose(plain(z, x)[0], reads(z, x)[0])


def test_the_search_side_answers_to_the_template():
    """Same search crop, two templates: the layer's output differs only through what it read."""
    torch.manual_seed(1)
    net = build_model(with_overrides(mobile_config(), READS)).eval()
    open_gate(net)
    with torch.no_grad():
        net.align_track.template_scale.fill_(0.5)
        z, x = crops()
        zf_a, zf_b = net.template(z), net.template(torch.flip(z, dims=[-1]))
        a = net.search_branch(x, zf_a).aligned[0]
        b = net.search_branch(x, zf_b).aligned[0]
        assert not torch.allclose(a, b)
        assert torch.equal(net.search_branch(x, zf_a).neck[0], net.search_branch(x, zf_b).neck[0])
    with pytest.raises(ValueError, match="reads the template"):
        net.search_branch(x)


def test_the_option_is_checked():
    validate_config(with_overrides(mobile_config(), READS))
    with pytest.raises(ValueError, match="'align_template' needs align = \"paper\""):
        validate_config(with_overrides(mobile_config(), READS | {"align": "none"}))
    with pytest.raises(ValueError, match="'align_template' is 1; expected true or false"):
        validate_config(with_overrides(mobile_config(), {"align_template": 1}))
    with pytest.raises(ValueError, match="'align_template_gate' is 'open'; expected a number"):
        validate_config(with_overrides(mobile_config(), READS | {"align_template_gate": "open"}))
    opened = build_model(with_overrides(mobile_config(), READS | {"align_template_gate": 0.1}))
    assert torch.allclose(opened.align_track.template_scale.detach(), torch.tensor(0.1))


def test_the_export_feeds_the_template_features_to_the_search_graph(tmp_path):
    from dadiff.runtime.onnx_backend import OnnxBackend

    torch.manual_seed(2)
    net = build_model(with_overrides(mobile_config(), READS))
    open_gate(net)
    with torch.no_grad():
        net.align_track.template_scale.fill_(0.5)
    ckpt = tmp_path / "reads.pt"
    save_checkpoint(ckpt, net)
    loaded = load_checkpoint(ckpt)
    assert loaded.config.align_template
    report = export_model(loaded, tmp_path / "m", "reads")
    assert report.max_parity < 1e-4
    search = ort.InferenceSession(str(tmp_path / "m" / "search.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in search.get_inputs()] == ["x", "kcls0", "kloc0", "zf0"]
    backend = OnnxBackend(tmp_path / "m", provider="cpu", threads=1, cache=False)
    z, x = crops()
    e, i = backend.meta["exemplar_size"], backend.meta["instance_size"]
    z_np = z.numpy()[:, :, :int(e), :int(e)].copy()
    x_np = x.numpy()[:, :, :int(i), :int(i)].copy()
    feeds = backend.template(z_np)
    cls, _ = backend.search(x_np, feeds)
    other = dict(feeds, zf0=np.zeros_like(feeds["zf0"]))
    cls_other, _ = backend.search(x_np, other)
    assert np.abs(cls - cls_other).max() > 1e-4  # the graph reads zf0
