"""`extends` in a dadiff-train config: a recipe lists only what differs from another, each key replacing the
base's value whole, and a broken chain is one line naming the file that holds the problem."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("torch")

from dadiff.export import train  # noqa: E402
from dadiff.export.train_toml import config_chain  # noqa: E402

BASE = """[train]
out = "runs/base"
steps = 40
lr = 0.001
train_only = ["head."]
day = [{ kind = "scenes", split = "train" }, { kind = "scenes", split = "train", pairs = 2 }]
"""


def _write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_keys_given_replace_the_base_values_whole_and_the_rest_is_inherited(tmp_path) -> None:
    _write(tmp_path, "configs/base.toml", BASE)
    _write(tmp_path, "configs/middle.toml", 'extends = "base.toml"\n[train]\nsteps = 60\ntrain_only = []\n')
    leaf = _write(tmp_path, "mine/leaf.toml",
                  'extends = "../configs/middle.toml"\n[train]\nout = "runs/leaf"\n'
                  'day = [{ kind = "images", root = "f" }]\n')
    cfg = train.TrainConfig.from_toml(leaf)
    assert (cfg.out, cfg.steps, cfg.lr) == ("runs/leaf", 60, 0.001)  # leaf, middle, base
    assert cfg.train_only == []  # an emptied list stays empty: no merge with the base's
    assert cfg.day == [{"kind": "images", "root": "f"}]  # the whole list replaced, not the first entry
    assert [p.name for p, _ in config_chain(leaf)] == ["base.toml", "middle.toml", "leaf.toml"]


def test_a_config_without_extends_reads_as_before(tmp_path) -> None:
    path = _write(tmp_path, "base.toml", BASE)
    assert train.TrainConfig.from_toml(path).day == [{"kind": "scenes", "split": "train"},
                                                       {"kind": "scenes", "split": "train", "pairs": 2}]


@pytest.mark.parametrize(("files", "blamed", "message"), [
    ({"a.toml": 'extends = "b.toml"\n', "b.toml": 'extends = "a.toml"\n'}, "b.toml", "'extends' loops"),
    ({"a.toml": 'extends = "a.toml"\n'}, "a.toml", "'extends' loops"),
    ({"a.toml": 'extends = "gone.toml"\n'}, "a.toml", "'extends' names 'gone.toml', which is not a file"),
    ({"a.toml": "extends = 3\n"}, "a.toml", "'extends' is 3; expected the path of another config file"),
    ({"a.toml": 'extends = "b.toml"\n', "b.toml": "stepz = 3\n"}, "b.toml", "unknown config keys: stepz"),
    ({"a.toml": 'extends = "b.toml"\n', "b.toml": 'steps = "3"\n'}, "b.toml", "'steps' is '3'"),
    ({"a.toml": 'extends = "b.toml"\nlr = -1\n', "b.toml": BASE}, "a.toml", "'lr' is -1"),
    ({"a.toml": 'extends = "b.toml"\n', "b.toml": "steps = [\n"}, "b.toml", "invalid TOML"),
])
def test_a_broken_chain_is_one_line_naming_the_file(tmp_path, capsys, files, blamed: str, message: str) -> None:
    for name, text in files.items():
        _write(tmp_path, name, text)
    assert train.main(["--config", str(tmp_path / "a.toml"), "--output", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"dadiff-train: error: {tmp_path / blamed}: "), err
    assert message in err[0]
    assert not (tmp_path / "run").exists()


CONFIGS = sorted((Path(train.__file__).parent / "configs").glob("*.toml"))


def test_show_config_prints_the_resolved_config_in_a_file_that_reads_back_the_same(tmp_path, capsys) -> None:
    """`--show-config`: what a run of a chained recipe uses, in one standalone file (every shipped config)."""
    for path in CONFIGS:
        assert train.main(["--config", str(path), "--show-config"]) == 0
        shown = tmp_path / path.name
        shown.write_text(capsys.readouterr().out)
        assert "extends" not in shown.read_text()
        assert [s.cfg for s in train.load_recipe(shown)] == [s.cfg for s in train.load_recipe(path)], path.name
    assert any("extends" in p.read_text() for p in CONFIGS)  # the shipped chains are covered


def test_show_config_applies_the_command_line_overrides(tmp_path, capsys) -> None:
    path = _write(tmp_path, "base.toml", BASE)
    assert train.main(["--config", str(path), "--show-config", "--output", "elsewhere", "--seed", "5"]) == 0
    shown = capsys.readouterr().out
    assert 'out = "elsewhere"' in shown and "seed = 5" in shown and "# night: not set" in shown
    assert not (tmp_path / "elsewhere").exists()
