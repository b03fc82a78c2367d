"""Official parity of DaDiff-GAT: the network against the official implementation's fixture (its README)."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import gat_fixture_dir  # noqa: E402
from dadiff.export.config import gat_googlenet_config  # noqa: E402
from dadiff.export.inception import roi_mask  # noqa: E402
from dadiff.export.network import build_model  # noqa: E402
from dadiff.export.onnx_export import parity_inputs  # noqa: E402

TOL = 1e-4


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    return dict(np.load(gat_fixture_dir() / "dadiff_gat_procedural_ref.npz"))


@pytest.fixture(scope="module")
def inputs(reference) -> tuple[np.ndarray, np.ndarray]:
    """The fixture's z and x are the exporter's own parity inputs (default_rng(0), z then x)."""
    z, x = (t.numpy() for t in parity_inputs(gat_googlenet_config()))
    assert np.array_equal(z, reference["z"])
    assert zlib.crc32(np.ascontiguousarray(x).tobytes()) == int(reference["x_crc32"][0]) == 933319677
    return z, x


@pytest.fixture(scope="module")
def outputs(gat_loaded, inputs, reference) -> dict[str, np.ndarray]:
    """Every reference array's counterpart, computed once through the loaded released-format checkpoint."""
    net = gat_loaded.model
    z, x = inputs
    with torch.no_grad():
        zb = net.template_branch(torch.from_numpy(z), torch.from_numpy(reference["roi"]))
        xb = net.search_branch(torch.from_numpy(x))
        gat = net.attention(zb.aligned[0], xb.aligned[0])
        cls, loc, cen = net.car_head(gat)
    values = {"zf_backbone": zb.neck[0], "zf_diff": zb.states[0][-1], "zf_aligned": zb.aligned[0],
              "xf_backbone": xb.neck[0], "xf_diff": xb.states[0][-1], "xf_aligned": xb.aligned[0],
              "gat_features": gat, "cls": cls, "loc": loc, "cen": cen}
    return {k: v.numpy() for k, v in values.items()}


def test_state_dict_keys_and_shapes_equal_the_release(gat_shapes):
    sd = build_model(gat_googlenet_config()).state_dict()
    assert len(sd) == len(gat_shapes) == 613
    assert {k: list(v.shape) for k, v in sd.items()} == gat_shapes
    assert sum(v.numel() for v in sd.values()) == 31_569_074


def test_released_checkpoint_is_detected_and_loaded_strictly(gat_loaded):
    assert gat_loaded.config.family == "dadiff-gat-googlenet" and gat_loaded.source == "released"
    assert gat_loaded.config.tracker.default_preset == "NUT_L" and gat_loaded.config.tracker.instance_size == 287


def test_template_mask_is_the_release_s(reference):
    mask = roi_mask(torch.from_numpy(reference["roi"]), 13)[0, 0].numpy()
    assert np.array_equal(mask, reference["template_mask"]) and mask.sum() == 63
    # truncation toward zero, and the upper bound 12 exclusive: a box filling the crop never reaches row 12
    full = roi_mask(torch.tensor([[-30.0, -30.0, 200.0, 200.0]]), 13)[0, 0].numpy()
    assert full[:12, :12].all() and not full[12].any() and not full[:, 12].any()


@pytest.mark.parametrize("name", ["zf_backbone", "zf_diff", "zf_aligned", "xf_backbone", "xf_aligned",
                                  "gat_features", "cls", "loc", "cen"])
def test_torch_matches_official_outputs(outputs, reference, name):
    assert np.abs(outputs[name] - reference[name]).max() <= TOL


@pytest.mark.parametrize("name", ["xf_backbone", "xf_diff", "xf_aligned", "gat_features"])
def test_feature_statistics_match(outputs, reference, name):
    f = outputs[name].astype(np.float64)
    stats = reference[f"{name}_stats"]
    ours = np.array([f.mean(), f.std(ddof=1), np.abs(f).max()])
    assert np.all(np.abs(ours - stats) <= TOL * stats[2])


@pytest.mark.parametrize("problem", ["missing", "extra", "shape"])
def test_broken_released_checkpoint_is_refused_naming_the_key(tmp_path, gat_shapes, problem):
    from dadiff.export.checkpoint import CheckpointError, load_checkpoint
    from dadiff.export.procedural import procedural_state_dict

    sd = procedural_state_dict(gat_shapes)
    key = "attention.fi.0.weight"
    if problem == "missing":
        del sd[key]
    elif problem == "extra":
        key = "attention.extra.weight"
        sd[key] = torch.zeros(1)
    else:
        sd[key] = torch.zeros(3, 3)
    path = tmp_path / "checkpoint_e45.pth"
    torch.save({"epoch": 45, "state_dict": {f"module.{k}": v for k, v in sd.items()}, "optimizer": None}, path)
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path)
    message = str(err.value)
    assert "\n" not in message and key in message and str(path) in message


def test_export_passes_its_parity_gate(gat_model_dir):
    _, report = gat_model_dir
    assert set(report.parity) == {"zf0", "cls", "loc", "cen"} and report.max_parity <= TOL
    assert 66 < report.gflop_search < 67 and 12.5 < report.gflop_template < 13.5  # README 6: 66.45 / 13.05


def test_onnx_matches_official_outputs(gat_model_dir, inputs, reference):
    import onnxruntime as ort

    folder, _ = gat_model_dir
    z, x = inputs
    template = ort.InferenceSession(str(folder / "template.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in template.get_inputs()] == ["z", "roi"]
    (zf,) = template.run(None, {"z": z, "roi": reference["roi"]})
    assert np.abs(zf - reference["zf_aligned"]).max() <= TOL
    search = ort.InferenceSession(str(folder / "search.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in search.get_inputs()] == ["x", "zf0"]
    for name, ours in zip(("cls", "loc", "cen"), search.run(["cls", "loc", "cen"], {"x": x, "zf0": zf}), strict=True):
        assert np.abs(ours - reference[name]).max() <= TOL, name
    meta = search.get_modelmeta().custom_metadata_map
    assert meta["family"] == "dadiff-gat-googlenet" and meta["decoder"] == "siamgat"
    assert meta["default_preset"] == "NUT_L" and meta["point_origin"] == "-98" and meta["instance_size"] == "287"
    assert meta["template_inputs"] == '["z", "roi"]' and meta["search_outputs"] == '["cls", "loc", "cen"]'


def test_runtime_tracks_the_fixture_sequence_as_the_official_tracker(gat_model_dir, gat_frames):
    """The exported model in the onnxruntime Tracker, released settings: the official real-model boxes."""
    from dadiff.runtime import Tracker

    folder, _ = gat_model_dir
    ref = dict(np.load(gat_fixture_dir() / "dadiff_gat_tracker_ref.npz"))
    frames, _ = gat_frames
    tracker = Tracker.load(folder, threads=1, overrides={"lost_score": 0})
    tracker.init(frames[0], ref["nutl_init_box"])
    frames_checked = 4  # a search frame is 66 GFLOP: a few seconds each on a shared CPU
    boxes = np.array([tracker.update(f).box for f in frames[1:1 + frames_checked]])
    expected = ref["nutl_bbox"][:frames_checked]
    assert np.all(np.abs(boxes - expected) <= 1e-5 * np.abs(expected))
