"""Issue 13 on the torch side: dadiff-export validates a model's config up front (the runtime's checks) and
cannot be talked out of its parity gate; dadiff-train checks its config's types and ranges before work."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from dadiff.export import cli as export_cli  # noqa: E402
from dadiff.export import train  # noqa: E402
from dadiff.export.config import lite_config  # noqa: E402
from dadiff.export.train_cli import CONFIG_KEYS, finish_line  # noqa: E402


def _one_error(capsys: pytest.CaptureFixture, prog: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"{prog}: error: "), err
    return err[0]


def _checkpoint(path: Path, model: dict | None = None, tracker: dict | None = None) -> Path:
    """Our format with a stored config changed by `model` / `tracker`; the weights never get read."""
    config = lite_config().to_dict()
    config.update(model or {})
    config["tracker"].update(tracker or {})
    torch.save({"dadiff_format": 1, "config": config, "state_dict": {"w": torch.zeros(1)}}, path)
    return path


BAD_CONFIGS = [
    ({"backbone": "resnet18"}, None, "'backbone' is 'resnet18'"),
    ({"channels": -1}, None, "'channels' is -1"),
    ({"ddim_steps": 0}, None, "'ddim_steps' is 0"),
    ({"denoiser_groups": 7}, None, "'denoiser_groups' 7 does not divide"),
    ({"align": "fancy"}, None, "'align' is 'fancy'"),
    (None, {"exemplar_size": "127"}, "'tracker.exemplar_size' is '127'"),
    (None, {"default_preset": "NOPE"}, "'tracker.default_preset' is 'NOPE'"),
    (None, {"score_size": 0}, "'score_size' must be positive"),  # was: "parity OK", then refused by the runtime
    (None, {"context_amount": -1.0}, "'context_amount' must not be negative"),
]


@pytest.mark.parametrize(("model", "tracker", "message"), BAD_CONFIGS)
def test_export_refuses_a_bad_stored_config_up_front(tmp_path, capsys, model, tracker, message) -> None:
    path = _checkpoint(tmp_path / "bad.pt", model, tracker)
    assert export_cli.main([str(path), "-o", str(tmp_path / "out")]) == 2  # was: a traceback (exit 1)
    line = _one_error(capsys, "dadiff-export")
    assert "invalid model config" in line and message in line and str(path) in line
    assert not (tmp_path / "out").exists()


@pytest.fixture
def one_torch_thread():
    """Torch's thread pool fights other jobs for 2 cores (10 s instead of 2.5 s for this export)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_export_never_ships_a_model_the_runtime_refuses(tmp_path, capsys, one_torch_thread) -> None:
    from dadiff.export.checkpoint import save_checkpoint
    from dadiff.export.config import mobile_config
    from dadiff.export.network import build_model

    base = mobile_config()  # the smallest family: a fast export
    wrong = dataclasses.replace(base, tracker=dataclasses.replace(base.tracker, score_size=12))
    save_checkpoint(tmp_path / "wrong.pt", build_model(wrong))  # the graph gives 13x13: parity holds, runtime refuses
    assert export_cli.main([str(tmp_path / "wrong.pt"), "-o", str(tmp_path / "out")]) == 2
    assert "the runtime refuses the exported model" in _one_error(capsys, "dadiff-export")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", ["nan", "-1", "inf", "x"])
def test_tolerance_is_checked_before_any_work(value: str, capsys) -> None:
    with pytest.raises(SystemExit) as info:  # was: nan disabled the gate, -1 ran the whole export first
        export_cli.main(["never-read.pt", "--tolerance", value])
    assert info.value.code == 2
    assert "argument --tolerance: expected a number of at least 0" in _one_error(capsys, "dadiff-export")


def test_a_folder_of_checkpoints_is_not_called_a_model_folder(tmp_path, capsys) -> None:
    for name in ("last.pt", "final.pt"):
        (tmp_path / name).write_bytes(b"x")
    assert export_cli.main([str(tmp_path)]) == 2
    line = _one_error(capsys, "dadiff-export")
    assert "folder of checkpoints" in line and str(tmp_path / "final.pt") in line and "model folder" not in line


def test_quantize_uses_reduce_range_where_int8_saturates(monkeypatch) -> None:
    from dadiff.export import quantize

    monkeypatch.setattr(quantize, "int8_saturates", lambda: True)
    assert quantize.QuantizeSettings().use_reduce_range
    assert not quantize.QuantizeSettings(reduce_range=False).use_reduce_range
    monkeypatch.setattr(quantize, "int8_saturates", lambda: False)
    assert not quantize.QuantizeSettings().use_reduce_range


BAD_TRAIN = [
    ('steps = "3"', "'steps' is '3'; expected an integer"),
    ('batch_size = "2"', "'batch_size' is '2'; expected an integer"),
    ('lr = "fast"', "'lr' is 'fast'; expected a number"),
    ('warmup_steps = "x"', "'warmup_steps' is 'x'; expected an integer"),
    ('day = "scenes"', "'day' is 'scenes'; expected a list of tables"),
    ("model = {foo = 1}", "'model' has unknown keys foo"),
    ("model = {channels = -1}", "'model': 'channels' is -1"),
    ("model = {align_residual = 1}", "'model': 'align_residual' is 1; expected true or false"),
    ("checkpoint_every = 0", "'checkpoint_every' is 0; expected >= 1"),
    ("steps = 0", "'steps' is 0; expected >= 1"),  # was: an untrained final.pt
    ("steps = -3", "'steps' is -3; expected >= 1"),
    ("[train]\nlr = 0", "'lr' is 0; expected > 0"),
    ('family = "big"', "'family' is 'big'"),
    ("adversarial = 1", "'adversarial' is 1; expected true or false"),
    ("negative_pairs = 1.2", "'negative_pairs' is 1.2; expected <= 1"),
    ("negative_pairs = -0.1", "'negative_pairs' is -0.1; expected >= 0"),
]


@pytest.mark.parametrize(("text", "message"), BAD_TRAIN)
def test_train_config_is_checked_before_any_work(tmp_path, capsys, text: str, message: str) -> None:
    config = tmp_path / "c.toml"
    config.write_text(text + "\n")
    assert train.main(["--config", str(config), "--output", str(tmp_path / "run")]) == 2  # was: a traceback
    line = _one_error(capsys, "dadiff-train")
    assert message in line and str(config) in line
    assert not (tmp_path / "run").exists()


def test_train_config_not_utf8(tmp_path, capsys) -> None:
    config = tmp_path / "c.toml"
    config.write_bytes(b"\xff\xfe")
    assert train.main(["--config", str(config)]) == 2
    assert "not a text file" in _one_error(capsys, "dadiff-train")


def test_shipped_train_configs_pass_the_checks() -> None:
    for path in sorted((Path(train.__file__).parent / "configs").glob("*.toml")):
        train.load_recipe(path)


def test_every_train_config_key_is_documented_in_help() -> None:
    fields = {f.name: f for f in dataclasses.fields(train.TrainConfig)}
    assert sorted(k for k, _, _ in CONFIG_KEYS) == sorted(fields)  # `dadiff-train --help` lists them all
    defaults = train.TrainConfig()
    for key, shown, _ in CONFIG_KEYS:
        value = getattr(defaults, key)
        if isinstance(value, bool):
            assert shown == str(value).lower(), key
        elif isinstance(value, int | float) or (isinstance(value, str) and key != "night"):
            assert shown.strip('"') == str(value) or float(shown) == value, key


def test_the_finished_run_names_final_pt(tmp_path) -> None:
    assert "export " + str(tmp_path / "final.pt") in finish_line(5, 5, tmp_path)  # was: named last.pt
    assert "resume" in finish_line(2, 5, tmp_path) and "final.pt" not in finish_line(2, 5, tmp_path)
    assert str(tmp_path / "final-ema.pt") in finish_line(5, 5, tmp_path, averaged=True)
    assert "final-ema.pt" not in finish_line(5, 5, tmp_path)
