"""`dadiff-export`: the model folder, its metadata, parity, determinism and the errors users see."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from dadiff.export.cli import main  # noqa: E402

REQUIRED_META = ["family", "exemplar_size", "instance_size", "stride", "score_size", "point_origin", "context_amount",
                 "penalty_k", "window_influence", "lr", "hp_presets", "pixel_mean", "pixel_std", "ddim_steps",
                 "ddim_timesteps", "opset", "source_sha256", "dadiff_version", "channel_order", "min_size"]


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_export_lite_prints_parity_and_writes_metadata(tmp_path, capsys, lite_checkpoint):
    code, out, err = _run(capsys, str(lite_checkpoint), "-o", str(tmp_path / "m"), "--name", "lite-test")
    assert code == 0, err
    assert "parity torch vs onnxruntime" in out and "OK" in out
    parity = float(out.split("relative where |output| > 1): ")[1].split()[0])
    assert parity <= 1e-4
    for graph in ("template", "search"):
        meta = ort.InferenceSession(str(tmp_path / "m" / f"{graph}.onnx")).get_modelmeta().custom_metadata_map
        assert all(k in meta for k in REQUIRED_META)
        assert meta["graph"] == graph and meta["name"] == "lite-test" and meta["family"] == "dadiff-lite"
        assert json.loads(meta["hp_presets"])["UAVDark70"]["penalty_k"] == 0.088
        assert meta["pixel_mean"] == "[127.0, 127.0, 127.0]"


def test_graphs_have_no_random_ops_and_search_takes_kernels(lite_model_dir):
    for graph in ("template.onnx", "search.onnx"):
        model = onnx.load(str(lite_model_dir / graph))
        assert not [n.op_type for n in model.graph.node if n.op_type.startswith("Random")]
    search = onnx.load(str(lite_model_dir / "search.onnx"))
    assert [i.name for i in search.graph.input] == ["x", "kcls0", "kloc0"]
    assert not any(n.op_type == "Sin" or n.op_type == "Cos" for n in search.graph.node)  # time embedding folded


def test_exports_and_runs_are_bit_identical(tmp_path, lite_checkpoint, lite_model_dir):
    from dadiff.export.checkpoint import load_checkpoint
    from dadiff.export.onnx_export import export_model

    export_model(load_checkpoint(lite_checkpoint), tmp_path / "again", "test-lite")
    for f in ("template.onnx", "search.onnx"):
        assert (tmp_path / "again" / f).read_bytes() == (lite_model_dir / f).read_bytes()
    sess = ort.InferenceSession(str(lite_model_dir / "template.onnx"))
    z = np.random.default_rng(3).integers(0, 256, (1, 3, 127, 127)).astype(np.float32)
    a, b = sess.run(None, {"z": z}), sess.run(None, {"z": z})
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_step_count_is_a_config_value(tmp_path, capsys, lite_checkpoint):
    code, out, err = _run(capsys, str(lite_checkpoint), "-o", str(tmp_path / "k4"), "--steps", "4")
    assert code == 0, err
    meta = ort.InferenceSession(str(tmp_path / "k4" / "search.onnx")).get_modelmeta().custom_metadata_map
    assert meta["ddim_steps"] == "4" and json.loads(meta["ddim_timesteps"]) == [15, 10, 5, 0]


def test_a_network_without_the_block_says_so(tmp_path, capsys):
    from dataclasses import replace

    from dadiff.export.checkpoint import save_checkpoint
    from dadiff.export.config import lite_config
    from dadiff.export.network import build_model

    torch.manual_seed(0)
    path = tmp_path / "baseline.pt"
    save_checkpoint(path, build_model(replace(lite_config(), use_dadiff=False), pretrained_backbone=False))
    code, out, err = _run(capsys, str(path), "-o", str(tmp_path / "m"))
    assert code == 0, err
    assert "no DaDiff block" in out and "DDIM" not in out


def test_parity_failure_exits_nonzero_and_leaves_no_files(tmp_path, capsys, lite_checkpoint):
    code, out, err = _run(capsys, str(lite_checkpoint), "-o", str(tmp_path / "m"), "--tolerance", "0")
    assert code == 1
    assert err.count("\n") == 1 and "parity check failed" in err
    assert not (tmp_path / "m").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".dadiff-export-")]


@pytest.mark.parametrize("argv, expected", [
    (["--opset", "9"], "unsupported opset 9"),
    (["--steps", "0"], "--steps must be in 1..20"),
])
def test_bad_options(tmp_path, capsys, lite_checkpoint, argv, expected):
    with pytest.raises(SystemExit) as info:
        main([str(lite_checkpoint), "-o", str(tmp_path / "m"), *argv])
    assert info.value.code == 2
    assert expected in capsys.readouterr().err


def test_user_errors_are_one_line(tmp_path, capsys, lite_checkpoint):
    code, _, err = _run(capsys, str(tmp_path / "missing.pth"))
    assert code == 2 and err.startswith("dadiff-export: error: ") and err.count("\n") == 1 and "no such file" in err
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    code, _, err = _run(capsys, str(lite_checkpoint), "-o", str(blocker / "m"))
    assert code == 2 and "cannot write" in err and err.count("\n") == 1
    if os.geteuid() != 0:  # root ignores permission bits
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        code, _, err = _run(capsys, str(lite_checkpoint), "-o", str(ro / "m"))
        assert code == 2 and "cannot write" in err and err.count("\n") == 1


def test_output_path_that_is_a_file(tmp_path, capsys, lite_checkpoint):
    target = tmp_path / "file.txt"
    target.write_text("x")
    code, _, err = _run(capsys, str(lite_checkpoint), "-o", str(target))
    assert code == 2 and "exists and is not a folder" in err


def test_preset_sets_the_runtime_default(tmp_path, capsys, lite_checkpoint):
    code, _, err = _run(capsys, str(lite_checkpoint), "-o", str(tmp_path / "nat"), "--preset", "NAT")
    assert code == 0, err
    meta = ort.InferenceSession(str(tmp_path / "nat" / "search.onnx")).get_modelmeta().custom_metadata_map
    assert meta["default_preset"] == "NAT" and meta["lr"] == "0.45" and meta["penalty_k"] == "0.14"


def test_unknown_preset_is_one_line(tmp_path, capsys, lite_checkpoint):
    code, _, err = _run(capsys, str(lite_checkpoint), "-o", str(tmp_path / "x"), "--preset", "GEN_NIGHT")
    assert code == 2 and "unknown preset 'GEN_NIGHT'; known: NAT, NAT_L, NUT_L, UAVDark70" in err
    assert len(err.strip().splitlines()) == 1


def test_model_is_named_after_its_folder_and_not_replaced_without_force(tmp_path, capsys, lite_checkpoint):
    """Issue 55: `-o FOLDER` holding a model was replaced without a word, and exporting a model's checkpoint.pt
    into its own folder renamed the model `checkpoint`."""
    checkpoint = tmp_path / "checkpoint.pt"
    checkpoint.write_bytes(lite_checkpoint.read_bytes())
    folder = tmp_path / "my-lite"

    def name() -> str:
        return {p.key: p.value for p in onnx.load(str(folder / "search.onnx")).metadata_props}["name"]

    code, _, err = _run(capsys, str(checkpoint), "-o", str(folder))
    assert code == 0, err
    assert name() == "my-lite"
    (folder / "checkpoint.pt").write_bytes(checkpoint.read_bytes())  # as the shipped folders hold theirs
    before = (folder / "search.onnx").read_bytes()
    code, out, err = _run(capsys, str(folder / "checkpoint.pt"), "-o", str(folder))
    assert code == 2 and err.count("\n") == 1 and "holds a model already" in err and "--force" in err
    assert (folder / "search.onnx").read_bytes() == before and not out
    code, _, err = _run(capsys, str(folder / "checkpoint.pt"), "-o", str(folder), "--force")
    assert code == 0, err
    assert name() == "my-lite"
