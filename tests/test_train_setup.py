"""What only setting a run up can find (the `init` checkpoint, the `teacher` folder, `train_only` names, a day
source's folder) is one line naming the config file that sets the key and the key; a path says where it was
looked for, since relative paths are taken from the working folder, not the config's. And dadiff-export of a
stopped run's final.pt says the run has not finished instead of only "no such file"."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

pytest.importorskip("torch")

from dadiff.export import train  # noqa: E402


def _error(capsys) -> str:
    out, err = capsys.readouterr()
    lines = [line for line in (out + err).replace("\r", "\n").splitlines() if line.startswith("dadiff-")]
    assert len(lines) == 1 and err.count("\n") == 1, err
    return lines[0]


def _train(tmp_path: Path, capsys, body: str, name: str = "c.toml") -> tuple[Path, str]:
    config = tmp_path / name
    config.write_text(f'out = "{tmp_path / "run"}"\nstage = "baseline"\nsteps = 2\nbatch_size = 2\n{body}\n')
    assert train.main(["--config", str(config), "--max-steps", "1"]) == 2
    assert not (tmp_path / "run").exists()
    return config, _error(capsys)


@pytest.fixture
def elsewhere(tmp_path, monkeypatch) -> Path:
    """A working folder other than the config's (and the checkout's)."""
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    monkeypatch.chdir(folder)
    return folder


def test_a_missing_init_says_where_it_was_looked_for_and_that_its_run_stopped_early(tmp_path, capsys, elsewhere):
    (elsewhere / "runs" / "x").mkdir(parents=True)
    (elsewhere / "runs" / "x" / "last.pt").write_bytes(b"state")
    config, line = _train(tmp_path, capsys, 'init = "runs/x/final.pt"')
    assert line == (f"dadiff-train: error: {config}: 'init' is 'runs/x/final.pt': no such file "
                    f"({elsewhere}/runs/x/final.pt; a relative path is taken from the working folder, {elsewhere}); "
                    f"expected \"imagenet\" or a dadiff checkpoint; that run has not finished: start from its "
                    f"last.pt, or finish the run first")
    _, line = _train(tmp_path, capsys, 'init = "../gone.pt"')
    assert f"'init' is '../gone.pt': no such file ({tmp_path}/gone.pt; a relative path" in line
    assert "has not finished" not in line


def test_an_init_of_another_family_says_which_keys_are_missing_and_which_unexpected(tmp_path, capsys):
    from dadiff.export.checkpoint import save_checkpoint
    from dadiff.export.config import default_config
    from dadiff.export.network import build_model

    save_checkpoint(tmp_path / "lite.pt", build_model(default_config("dadiff-lite")))
    config, line = _train(tmp_path, capsys, f'family = "dadiff-mobile"\ninit = "{tmp_path / "lite.pt"}"')
    assert line.startswith(f"dadiff-train: error: {config}: 'init' is '{tmp_path / 'lite.pt'}': its dadiff-lite "
                           f"model does not fit the configured dadiff-mobile model (unexpected, not in the "
                           f"configured model: backbone.")
    assert line.endswith('more); set family = "dadiff-lite" or start from a dadiff-mobile checkpoint')
    _, line = _train(tmp_path, capsys, f'init = "{tmp_path}"')
    assert line.endswith(f"'init': {tmp_path}: is a folder, expected a checkpoint file (.pt/.pth)")


def test_a_teacher_folder_that_is_not_there_is_named_with_its_key_and_where_it_was_looked_for(
        tmp_path, capsys, elsewhere):
    pytest.importorskip("onnxruntime")
    config, line = _train(tmp_path, capsys, 'family = "dadiff-mobile"\nteacher = "../shared/weights/nanotrack/v3"')
    assert line == (f"dadiff-train: error: {config}: 'teacher' is '../shared/weights/nanotrack/v3': no such folder "
                    f"({tmp_path}/shared/weights/nanotrack/v3; a relative path is taken from the working folder, "
                    f"{elsewhere}); expected the NanoTrack v3 ONNX folder")
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "nanotrack_backbone.onnx").write_bytes(b"")
    _, line = _train(tmp_path, capsys, f'family = "dadiff-mobile"\nteacher = "{tmp_path / "half"}"')
    assert line.endswith(f"'teacher' is '{tmp_path / 'half'}': the folder ({tmp_path / 'half'}) lacks "
                         "nanotrack_head.onnx (NanoTrack v3 ONNX)")


def test_a_teacher_on_a_family_it_cannot_teach_names_the_file_that_sets_it(tmp_path, capsys):
    pytest.importorskip("onnxruntime")
    (tmp_path / "base.toml").write_text('teacher = "t"\n')
    leaf = tmp_path / "leaf.toml"
    leaf.write_text(f'extends = "base.toml"\nout = "{tmp_path / "run"}"\nstage = "baseline"\nbatch_size = 2\n')
    assert train.main(["--config", str(leaf), "--max-steps", "1"]) == 2
    assert _error(capsys) == (f"dadiff-train: error: {tmp_path / 'base.toml'}: 'teacher' is 't', but teacher "
                              "distillation needs a one-level stride-16 family (dadiff-mobile), not dadiff-lite; set "
                              "family = \"dadiff-mobile\" or drop 'teacher'")


def test_train_only_that_names_no_parameter_names_the_key_and_the_file(tmp_path, capsys):
    config, line = _train(tmp_path, capsys, 'train_only = ["head.", "nothing."]')
    assert line.startswith(f"dadiff-train: error: {config}: 'train_only' has 'nothing.', but no parameter of the "
                           "network starts with 'nothing.' (its parameter names start with ")
    assert "backbone., " in line and "head." in line


def test_a_day_folder_that_is_not_there_names_the_entry_and_where_it_was_looked_for(tmp_path, capsys, elsewhere):
    config, line = _train(tmp_path, capsys, 'day = [{ kind = "scenes" }, { kind = "images", root = "frames" }]')
    assert line == (f"dadiff-train: error: {config}: 'day' entry 2 (kind 'images'): 'root' is 'frames': no such "
                    f"folder ({elsewhere}/frames; a relative path is taken from the working folder, {elsewhere})")


def test_exporting_a_stopped_runs_final_pt_says_the_run_has_not_finished(tmp_path, capsys, monkeypatch):
    from dadiff.export.cli import main

    monkeypatch.chdir(tmp_path)
    os.makedirs("runs/x")
    Path("runs/x/last.pt").write_bytes(b"state")
    assert main(["runs/x/final.pt"]) == 2
    assert _error(capsys) == ("dadiff-export: error: runs/x/final.pt: no such file (the run has not finished: "
                              "export its last.pt, or resume it)")
    assert main(["runs/y/final.pt"]) == 2  # no run there: the line as before
    assert _error(capsys) == "dadiff-export: error: runs/y/final.pt: no such file"
