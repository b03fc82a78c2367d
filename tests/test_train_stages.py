"""dadiff-train on a config in stages: the list parses, bad stage keys are one line, and the stages run in
order, each continuing from the previous one's final state, resumable."""

from __future__ import annotations

from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

from dadiff.export.checkpoint import read_checkpoint_file  # noqa: E402
from dadiff.export.train import load_recipe, main  # noqa: E402

SHARED = """
[train]
out = "{out}"
family = "dadiff-lite"
batch_size = 2
optimizer = "adamw"
lr = 0.001
warmup_steps = 1
checkpoint_every = 1
day = [{{ kind = "images", root = "{images}" }}]
night = "{images}"
"""
STAGES = """
[[stages]]
name = "day"
stage = "baseline"
steps = 3
stop_at = 2

[[stages]]
name = "day-more"
stage = "baseline"
resume = true
steps = 3

[[stages]]
name = "night"
stage = "dadiff"
steps = 2
seed = 5
train_only = ["head.box0.loc."]
"""


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    data = pytest.importorskip("skimage.data")
    root = tmp_path_factory.mktemp("imgs")
    for name in ("chelsea", "coffee", "astronaut"):
        cv2.imwrite(str(root / f"{name}.jpg"), getattr(data, name)()[:, :, ::-1])
    return root


def _recipe(tmp_path: Path, images: Path, stages: str = STAGES) -> Path:
    path = tmp_path / "recipe.toml"
    path.write_text(SHARED.format(out=tmp_path / "runs", images=images) + stages)
    return path


def test_a_stage_list_parses_into_chained_stages(tmp_path, images, capsys) -> None:
    path = _recipe(tmp_path, images)
    recipe = load_recipe(path)
    assert [s.plan.name for s in recipe] == ["day", "day-more", "night"]
    assert [s.cfg.out for s in recipe] == [str(tmp_path / "runs" / f) for f in ("01-day", "02-day-more", "03-night")]
    assert recipe[0].cfg.init == "imagenet" and recipe[0].plan.stop_at == 2
    assert recipe[1].plan.resume and recipe[2].cfg.stage == "dadiff"  # a stage's keys replace the shared ones
    assert recipe[2].cfg.init == str(tmp_path / "runs" / "02-day-more" / "final.pt") and recipe[2].cfg.seed == 5
    assert all(s.cfg.batch_size == 2 for s in recipe)  # the shared keys reach every stage
    assert main(["--config", str(path), "--show-config"]) == 0
    shown = tmp_path / "shown.toml"
    shown.write_text(capsys.readouterr().out)
    def stages(r):
        return [(s.plan.name, s.plan.resume, s.plan.stop_at, s.cfg) for s in r]

    assert stages(load_recipe(shown)) == stages(recipe)
    moved = load_recipe(path, out=str(tmp_path / "elsewhere"))
    assert moved[1].cfg.out == str(tmp_path / "elsewhere" / "02-day-more")


@pytest.mark.parametrize(("stages", "message"), [
    ('stages = "all"', "'stages' must be a list of tables"),
    ("[[stages]]\nsteps = 2", "stage 1: 'name' is None"),
    ('[[stages]]\nname = "A b"', "stage 1: 'name' is 'A b'"),
    ('[[stages]]\nname = "a"\n[[stages]]\nname = "a"', "stage 2: 'name' 'a' is used by an earlier stage"),
    ('[[stages]]\nname = "a"\nsteps_to = 2', "stage 1 'a': unknown keys: steps_to"),
    ('[[stages]]\nname = "a"\nout = "x"', "stage 1 'a': 'out' is set by the recipe"),
    ('[[stages]]\nname = "a"\n[[stages]]\nname = "b"\ninit = "x.pt"', "stage 2 'b': 'init' is set by the previous"),
    ('[[stages]]\nname = "a"\nresume = true', "stage 1 'a': 'resume' needs a previous stage"),
    ('[[stages]]\nname = "a"\nresume = 1\n', "stage 1 'a': 'resume' is 1"),
    ('[[stages]]\nname = "a"\nsteps = 3\nstop_at = 4\n[[stages]]\nname = "b"', "stage 1 'a': 'stop_at' is 4"),
    ('[[stages]]\nname = "a"\nstop_at = 0', "stage 1 'a': 'stop_at' is 0"),
    ('[[stages]]\nname = "a"\nstop_at = 1', "stage 1 'a': 'stop_at' on the last stage"),
    ('[[stages]]\nname = "a"\n[[stages]]\nname = "b"\nlr = "fast"', "stage 2 'b': 'lr' is 'fast'"),
])
def test_a_bad_stage_is_one_line_and_exit_2(tmp_path, images, capsys, stages: str, message: str) -> None:
    if stages.startswith("stages ="):  # a top-level key: before the [train] table
        path = tmp_path / "recipe.toml"
        path.write_text(stages + "\n" + SHARED.format(out=tmp_path / "runs", images=images))
    else:
        path = _recipe(tmp_path, images, stages)
    assert main(["--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"dadiff-train: error: {path}: "), err
    assert message in err[0]
    assert not (tmp_path / "runs").exists()  # checked before any work


def test_stages_continue_from_each_other_and_resume(tmp_path, images, capsys) -> None:
    path = _recipe(tmp_path, images)
    runs = tmp_path / "runs"
    assert main(["--config", str(path), "--max-steps", "3"]) == 0  # 2 steps of 'day', 1 of 'day-more'
    assert "stopped before stage 3/3 'night'; resume with the same command" in capsys.readouterr().out
    day = read_checkpoint_file(runs / "01-day" / "final.pt")
    more = read_checkpoint_file(runs / "02-day-more" / "final.pt")
    assert day["step"] == 2 and day["train_config"]["steps"] == 3  # stopped inside its 3-step schedule
    assert more["step"] == 3  # 'resume': the same run went on from step 2, its optimiser carried
    assert (runs / "02-day-more" / "log.csv").read_text().splitlines()[1].startswith("3,")
    assert not (runs / "03-night").exists()
    day_written = (runs / "01-day" / "final.pt").stat().st_mtime_ns

    assert main(["--config", str(path)]) == 0  # the same command: finished stages are skipped
    assert f"all 3 stages done: export {runs / '03-night' / 'final.pt'}" in capsys.readouterr().out
    assert (runs / "01-day" / "final.pt").stat().st_mtime_ns == day_written
    night = read_checkpoint_file(runs / "03-night" / "final.pt")
    assert night["step"] == 2 and night["train_config"]["init"] == str(runs / "02-day-more" / "final.pt")
    start, end = more["state_dict"], night["state_dict"]  # 'night' trains the box branch alone: the rest is
    moved = {k for k in start if not torch.equal(start[k], end[k])}  # 'day-more''s final state, handed on
    assert moved and all(k.startswith("head.box0.loc.") for k in moved)


def test_seed_and_torchrun_are_refused_on_a_staged_config(tmp_path, images, capsys, monkeypatch) -> None:
    """Each stage sets its own seed; the stages run in one process."""
    path = _recipe(tmp_path, images)
    assert main(["--config", str(path), "--seed", "3"]) == 2
    assert "--seed applies to a config without stages" in capsys.readouterr().err
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert main(["--config", str(path)]) == 2
    assert "runs in one process" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()
