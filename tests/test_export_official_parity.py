"""Official parity: the released DaDiff-BAN path against the official implementation's fixture (spec 13)."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import fixture_dir  # noqa: E402
from dadiff.export.config import ban_r50_config  # noqa: E402
from dadiff.export.network import build_model  # noqa: E402
from dadiff.export.procedural import fixture_inputs, procedural_state_dict  # noqa: E402

TOL = 1e-4
LEVELS = (2, 3, 4)


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    return dict(np.load(fixture_dir() / "dadiff_ban_procedural_ref.npz"))


@pytest.fixture(scope="module")
def ban_model(ban_shapes):
    model = build_model(ban_r50_config())
    model.load_state_dict(procedural_state_dict(ban_shapes), strict=True)
    return model.eval()


@pytest.fixture(scope="module")
def inputs(reference) -> tuple[np.ndarray, np.ndarray]:
    z, x = fixture_inputs()
    assert np.array_equal(z, reference["z"])
    assert zlib.crc32(np.ascontiguousarray(x).tobytes()) == int(reference["x_crc32"][0]) == 3631511829
    return z, x


def test_state_dict_keys_and_shapes_equal_the_release(ban_shapes):
    sd = build_model(ban_r50_config()).state_dict()
    assert len(sd) == len(ban_shapes) == 589
    assert set(sd) == set(ban_shapes)
    assert {k: list(v.shape) for k, v in sd.items()} == ban_shapes


def test_torch_matches_official_outputs(ban_model, inputs, reference):
    z, x = inputs
    with torch.no_grad():
        zb = ban_model.template_branch(torch.from_numpy(z))
        xb = ban_model.search_branch(torch.from_numpy(x))
        cls, loc = ban_model.head(xb.aligned, *ban_model.head.kernels(zb.aligned))
    for i, level in enumerate(LEVELS):
        ref_neck = reference[f"zf_neck{level}"]
        assert np.abs(zb.neck[i].numpy() - ref_neck).max() <= TOL * np.abs(ref_neck).max()
        assert np.abs(zb.aligned[i].numpy() - reference[f"zf_aligned{level}"]).max() <= TOL
        f = xb.neck[i].double().numpy()
        stats = reference[f"xf_neck{level}_stats"]
        ours = np.array([f.mean(), f.std(ddof=1), np.abs(f).max()])
        assert np.all(np.abs(ours - stats) <= TOL * stats[2])
    assert np.abs(cls.numpy() - reference["cls"]).max() <= TOL
    assert np.abs(loc.numpy() - reference["loc"]).max() <= TOL


def test_onnx_matches_official_outputs(ban_model, inputs, reference, ban_shapes, tmp_path_factory):
    import onnxruntime as ort

    from dadiff.export.checkpoint import load_checkpoint
    from dadiff.export.onnx_export import export_model
    from dadiff.export.procedural import write_released_checkpoint

    folder = tmp_path_factory.mktemp("ban")
    ckpt = folder / "checkpoint_e40.pth"
    write_released_checkpoint(str(ckpt), ban_shapes)
    report = export_model(load_checkpoint(ckpt), folder / "model", "ban-procedural")
    ckpt.unlink()
    assert report.max_parity <= TOL
    assert 240 < report.gflop_search < 255  # spec 14: about 247 GFLOP without the dead encoder
    z, x = inputs
    opts = ort.SessionOptions()
    template = ort.InferenceSession(str(folder / "model" / "template.onnx"), opts, providers=["CPUExecutionProvider"])
    outs = dict(zip([o.name for o in template.get_outputs()], template.run(None, {"z": z}), strict=True))
    for i, level in enumerate(LEVELS):
        assert np.abs(outs[f"zf{i}"] - reference[f"zf_aligned{level}"]).max() <= TOL
    search = ort.InferenceSession(str(folder / "model" / "search.onnx"), opts, providers=["CPUExecutionProvider"])
    feeds = {"x": x} | {i.name: outs[i.name] for i in search.get_inputs()[1:]}
    cls, loc = search.run(["cls", "loc"], feeds)
    assert np.abs(cls - reference["cls"]).max() <= TOL
    assert np.abs(loc - reference["loc"]).max() <= TOL
    meta = search.get_modelmeta().custom_metadata_map
    assert meta["family"] == "dadiff-ban-r50" and meta["ddim_timesteps"] == "[10, 0]" and meta["ddim_start_t"] == "1"
