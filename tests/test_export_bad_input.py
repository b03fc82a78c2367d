"""dadiff-export and dadiff-train refuse more bad input up front, in one line (exit 2): non-finite weights, a
start noise level past the schedule, a missing tracker table, an unknown format, a stride the network does not
have, unknown preset keys, huge crop settings; and training configs with no or unknown day data, or a bad seed."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from test_reliability_export import _checkpoint, _one_error, one_torch_thread  # noqa: E402, F401

from dadiff.export import cli as export_cli  # noqa: E402
from dadiff.export import train  # noqa: E402
from dadiff.export.config import (  # noqa: E402
    BACKBONE_STRIDES,
    LITE0_TRUNKS,
    default_config,
    lite0_subsampling_blocks,
    validate_config,
)


def _export(path, out, capsys) -> str:
    assert export_cli.main([str(path), "-o", str(out)]) == 2
    line = _one_error(capsys, "dadiff-export")
    assert not out.exists()
    return line


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_weights_are_refused_naming_the_tensor(tmp_path, capsys, mobile_checkpoint, value) -> None:
    obj = torch.load(mobile_checkpoint, weights_only=True)
    key = list(obj["state_dict"])[5]
    obj["state_dict"][key].view(-1)[0] = value
    torch.save(obj, tmp_path / "bad.pt")
    line = _export(tmp_path / "bad.pt", tmp_path / "out", capsys)  # was: "parity ... nan (tolerance 0.0001) OK"
    assert f"tensor '{key}' holds 1 NaN or inf value(s)" in line and str(tmp_path / "bad.pt") in line


@pytest.mark.usefixtures("one_torch_thread")
def test_parity_gate_fails_on_non_finite_outputs(tmp_path, mobile_checkpoint) -> None:
    from dadiff.export.checkpoint import load_checkpoint
    from dadiff.export.onnx_export import ExportError, export_model, parity_error

    assert parity_error(np.array([np.nan]), np.zeros(1)) == (math.inf, math.inf)  # nan > tol is False
    assert parity_error(np.zeros(1), np.array([np.inf])) == (math.inf, math.inf)
    loaded = load_checkpoint(mobile_checkpoint)
    with torch.no_grad():  # after loading: the load-time check would refuse the file first
        next(loaded.model.head.parameters()).fill_(math.nan)
    with pytest.raises(ExportError, match="parity check failed: output .* holds NaN or inf"):
        export_model(loaded, tmp_path / "out", "m")
    assert not (tmp_path / "out").exists()


BAD_STORED = [
    ({"ddim_start_t": 20}, None, "'ddim_start_t' is 20; expected an integer in 0..19"),  # was: IndexError
    ({"ddim_start_t": 1000}, None, "'ddim_start_t' is 1000; expected an integer in 0..19"),
    (None, {"stride": 16}, "'tracker.stride' is 16; the network (efficientnet-lite0) has stride 8"),
    ({"fine_skip": True}, None, "'fine_skip' is True: a retired experiment this version cannot build"),
    ({"head_upsample": 2}, None, "'head_upsample' is 2: a retired experiment"),
    ({"antialias_blocks": [4]}, None, "'antialias_blocks' is [4]: a retired experiment"),
    ({"align_template": True}, None, "'align_template' is True: a retired experiment"),
    (None, {"hp_presets": {"NAT": {"lr": 0.4, "penalty_k": 0.1, "window_influence": 0.3, "foo": 1}}},
     "'tracker.hp_presets.NAT' has unknown key 'foo'"),
    (None, {"context_amount": 1e308}, "'tracker.context_amount' is 1e+308; expected at most 10"),
    (None, {"min_size": 1e308}, "'tracker.min_size' is 1e+308; expected at most 1000"),
]


@pytest.mark.parametrize(("model", "tracker", "message"), BAD_STORED)
def test_export_refuses_more_bad_stored_configs(tmp_path, capsys, model, tracker, message) -> None:
    if tracker and "hp_presets" in tracker:
        tracker["default_preset"] = "NAT"
    path = _checkpoint(tmp_path / "bad.pt", model, tracker)
    line = _export(path, tmp_path / "out", capsys)
    assert "invalid model config" in line and message in line and str(path) in line


def test_states_saved_with_the_retired_keys_at_their_values_still_load() -> None:
    """The committed training states store head_upsample = 1, antialias_blocks = [], fine_skip = false."""
    from dadiff.export.config import RETIRED_KEYS, ModelConfig

    cfg = default_config("dadiff-mobile")
    assert ModelConfig.from_dict(cfg.to_dict() | RETIRED_KEYS) == cfg


@pytest.mark.parametrize(("change", "message"), [
    (lambda obj: obj["config"].pop("tracker"), "'tracker' is missing"),  # was: a tensor-size traceback
    (lambda obj: obj.update(dadiff_format=2), "'dadiff_format' is 2; this exporter reads format 1"),
    (lambda obj: obj.pop("dadiff_format"), "'dadiff_format' is None; this exporter reads format 1"),
])
def test_export_refuses_a_missing_tracker_or_unknown_format(tmp_path, capsys, change, message) -> None:
    path = _checkpoint(tmp_path / "bad.pt")
    obj = torch.load(path, weights_only=True)
    change(obj)
    torch.save(obj, path)
    assert message in _export(path, tmp_path / "out", capsys)


@pytest.mark.usefixtures("one_torch_thread")
def test_crop_sizes_the_network_cannot_run_are_one_line(tmp_path, capsys) -> None:
    import dataclasses

    from dadiff.export.checkpoint import save_checkpoint
    from dadiff.export.network import build_model

    base = default_config("dadiff-mobile")  # its start noise is for a 255 px crop (16 x 16 map)
    cfg = dataclasses.replace(base, tracker=dataclasses.replace(base.tracker, instance_size=223, score_size=11))
    save_checkpoint(tmp_path / "m.pt", build_model(cfg))
    line = _export(tmp_path / "m.pt", tmp_path / "out", capsys)  # was: a RuntimeError traceback
    assert "does not run on its stored crop sizes (tracker.exemplar_size 127, tracker.instance_size 223" in line


def test_backbone_strides_match_the_trunks_and_the_defaults() -> None:
    for backbone in LITE0_TRUNKS:  # the stem subsamples once, then each stride-2 block
        assert BACKBONE_STRIDES[backbone] == 2 ** (1 + len(lite0_subsampling_blocks(backbone)))
    for family in ("dadiff-ban-r50", "dadiff-gat-googlenet", "dadiff-lite", "dadiff-mobile"):
        validate_config(default_config(family))


BAD_TRAIN = [
    ("day = []", "'day' is []; expected at least one day source"),  # was: "high <= 0" once training ran
    ('day = [{kind = "nope"}]', "'day' entry 1 has kind 'nope'; expected one of scenes"),  # was: no file named
    ('day = [{kind = "images"}]', "'day' entry 1 (kind 'images') has no 'root'"),  # was: KeyError traceback
    ("seed = -1", "'seed' is -1; expected >= 0"),  # was: "expected non-negative integer" once training ran
    ("seed = 4294967296", "'seed' is 4294967296; expected <= 4294967295"),
]


@pytest.mark.parametrize(("text", "message"), BAD_TRAIN)
def test_train_refuses_bad_day_data_and_seeds_up_front(tmp_path, capsys, text: str, message: str) -> None:
    config = tmp_path / "c.toml"
    config.write_text(text + "\n")
    assert train.main(["--config", str(config), "--output", str(tmp_path / "run"), "--show-config"]) == 2
    line = _one_error(capsys, "dadiff-train")
    assert message in line and str(config) in line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("seed", ["-1", "4294967296"])
def test_train_seed_option_is_bounded(tmp_path, capsys, seed: str) -> None:
    config = tmp_path / "c.toml"
    config.write_text("steps = 1\n")
    with pytest.raises(SystemExit) as info:
        train.main(["--config", str(config), "--seed", seed, "--show-config"])
    assert info.value.code == 2
    assert "argument --seed: expected an integer from 0 to 4294967295" in _one_error(capsys, "dadiff-train")
