"""dadiff-train: each loss goes down, gradients reach the denoiser, resume, DDP replicas, export round trip."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

from dadiff.export.train import TrainConfig, Trainer, data_loader, run  # noqa: E402


@pytest.fixture(scope="module")
def image_folder(tmp_path_factory) -> Path:
    data = pytest.importorskip("skimage.data")
    root = tmp_path_factory.mktemp("imgs")
    for name in ("chelsea", "coffee", "astronaut"):
        cv2.imwrite(str(root / f"{name}.jpg"), getattr(data, name)()[:, :, ::-1])
    return root


def config(tmp_path: Path, image_folder: Path, **kw) -> TrainConfig:
    base = TrainConfig(out=str(tmp_path / "run"), stage="dadiff", steps=4, batch_size=2, optimizer="adamw", lr=1e-3,
                       warmup_steps=1, day=[{"kind": "images", "root": str(image_folder)}], night=str(image_folder),
                       checkpoint_every=2, seed=0)
    return replace(base, **kw)


def without_dropout(trainer: Trainer) -> None:
    """A fixed function of the weights, so that "the loss went down" is well defined."""
    for m in trainer.net.modules():
        if isinstance(m, torch.nn.Dropout):
            m.p = 0.0


def losses_on(trainer: Trainer, batch) -> dict[str, float]:
    trainer.train_mode()
    with torch.no_grad():
        out = trainer.model(batch["z"], batch["x"], batch["label"], batch["loc"], False, batch["z_night"],
                            batch["x_night"])
        night = out["night_states"]
        adv = trainer.disc(night, trainer.state_timesteps(len(night)))
    return {"cls": out["cls"].item(), "loc": out["loc"].item(), "adv": ((adv - 0.0) ** 2).sum(1).mean().item()}


def test_steps_decrease_each_loss_and_reach_the_denoiser(tmp_path, image_folder):
    cfg = config(tmp_path, image_folder, disc_lr=0.0)  # D held fixed, so its judgement is a fixed yardstick
    trainer = Trainer(cfg)
    without_dropout(trainer)
    batch = next(iter(data_loader(cfg, trainer.net, 0)))
    before = losses_on(trainer, batch)
    denoiser_w = trainer.net.diffusion.conv_in.weight.detach().clone()
    align_before = trainer.step_on(batch)["align"]
    for _ in range(4):
        logs = trainer.step_on(batch)
    after = losses_on(trainer, batch)
    assert after["cls"] < before["cls"] and after["loc"] < before["loc"]
    assert logs["align"] < align_before
    assert not torch.equal(denoiser_w, trainer.net.diffusion.conv_in.weight)  # gradients reached eps_theta
    # and the discriminator's own steps lower its day/night loss on the same states
    for g in trainer.disc_opt.param_groups:
        g["lr"] = 1e-3
    with torch.no_grad():
        out = trainer.model(batch["z"], batch["x"], batch["label"], batch["loc"], False, batch["z_night"],
                            batch["x_night"])
        day, night = out["day_states"], out["night_states"]
    ts = trainer.state_timesteps(len(day))
    d_first = trainer.discriminator_step(day, night, ts)
    for _ in range(4):
        d_last = trainer.discriminator_step(day, night, ts)
    assert d_last < d_first


def test_generator_steps_fool_a_fixed_discriminator(tmp_path, image_folder):
    cfg = config(tmp_path, image_folder, disc_lr=0.0, lambda_trc=0.0, align_loss=False, lambda_adv=1.0)
    trainer = Trainer(cfg)
    batch = next(iter(data_loader(cfg, trainer.net, 0)))
    before = losses_on(trainer, batch)["adv"]
    for _ in range(3):
        trainer.step_on(batch)
    assert losses_on(trainer, batch)["adv"] < before


def test_resume_restores_step_and_optimiser(tmp_path, image_folder):
    cfg = config(tmp_path, image_folder, steps=4)
    first = run(cfg, max_steps=2, progress=False)
    assert first.step == 2
    again = Trainer(cfg)
    assert again.resume() and again.step == 2
    state = again.opt.state_dict()["state"]
    assert state and all("exp_avg" in s for s in state.values())
    saved = first.opt.state_dict()["state"]
    key = next(iter(saved))
    assert torch.equal(saved[key]["exp_avg"], state[key]["exp_avg"])
    done = run(cfg, progress=False)
    assert done.step == 4 and (Path(cfg.out) / "final.pt").exists()
    rows = (Path(cfg.out) / "log.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 4  # header + one row per step across both runs


def test_keep_checkpoints_leaves_one_state_per_checkpoint_step(tmp_path, image_folder):
    from dadiff.export.checkpoint import read_checkpoint_file

    cfg = config(tmp_path, image_folder, steps=4, checkpoint_every=2, keep_checkpoints=True)
    run(cfg, progress=False)
    kept = sorted(p.name for p in Path(cfg.out).glob("step-*.pt"))
    assert kept == ["step-000002.pt", "step-000004.pt"]
    assert read_checkpoint_file(Path(cfg.out) / "step-000002.pt")["step"] == 2
    plain = config(tmp_path / "plain", image_folder, steps=2, checkpoint_every=1)
    run(plain, progress=False)
    assert not list(Path(plain.out).glob("step-*.pt"))


def test_weight_average_follows_the_weights_by_its_decay_and_copies_step_counters():
    from dadiff.export.weight_average import WeightAverage

    net = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2))
    start = {k: v.clone() for k, v in net.state_dict().items()}
    average = WeightAverage(net, 0.75)
    with torch.no_grad():
        net[0].weight.add_(4.0)
        net[1].num_batches_tracked.fill_(3)
    average.update(net)
    assert torch.allclose(average.state["0.weight"], start["0.weight"] + 1.0)  # 0.75 * w + 0.25 * (w + 4)
    assert torch.equal(average.state["0.bias"], start["0.bias"])
    assert int(average.state["1.num_batches_tracked"]) == 3
    twin = average.averaged(net)
    assert torch.equal(twin[0].weight, average.state["0.weight"]) and twin is not net
    assert not torch.equal(net[0].weight, twin[0].weight)  # the network keeps its own weights
    with pytest.raises(ValueError, match="does not match"):
        average.load({"0.weight": start["0.weight"]})
    with pytest.raises(ValueError, match="between 0 and 1"):
        WeightAverage(net, 1.0)


def test_ema_run_saves_the_average_beside_the_last_state_and_resumes_it(tmp_path, image_folder):
    from dadiff.export.checkpoint import load_checkpoint, read_checkpoint_file

    cfg = config(tmp_path, image_folder, steps=4, checkpoint_every=2, ema_decay=0.5, keep_checkpoints=True,
                 train_only=["head."])
    first = run(cfg, max_steps=2, progress=False)
    saved = read_checkpoint_file(Path(cfg.out) / "last.pt")["ema_state_dict"]
    again = Trainer(cfg)
    assert again.resume()
    assert all(torch.equal(again.ema.state[k], saved[k]) for k in saved)
    assert all(torch.equal(first.ema.state[k], saved[k]) for k in saved)
    done = run(cfg, progress=False)
    out = Path(cfg.out)
    assert sorted(p.name for p in out.glob("*ema.pt")) == ["final-ema.pt", "step-000002-ema.pt", "step-000004-ema.pt"]
    last, average = load_checkpoint(out / "final.pt").model.state_dict(), \
        load_checkpoint(out / "final-ema.pt").model.state_dict()
    moved = [k for k in last if k.startswith("head.") and last[k].is_floating_point() and
             not torch.equal(last[k], average[k])]
    assert moved  # the average lags the trained head
    assert all(torch.equal(last[k], average[k]) for k in last if k.startswith("backbone."))  # frozen: equal
    assert all(torch.equal(done.ema.state[k], average[k]) for k in average)
    plain = config(tmp_path / "plain", image_folder, steps=2, checkpoint_every=2)
    run(plain, progress=False)
    assert not (Path(plain.out) / "final-ema.pt").exists()
    assert "ema_state_dict" not in read_checkpoint_file(Path(plain.out) / "last.pt")


@pytest.mark.parametrize("value, message", [("1.0", "'ema_decay' is 1.0; expected < 1"),
                                            ("-0.5", "'ema_decay' is -0.5; expected >= 0")])
def test_ema_decay_out_of_range_is_one_line(tmp_path, capsys, value, message):
    from dadiff.export.train import main

    bad = tmp_path / "ema.toml"
    bad.write_text(f"[train]\nema_decay = {value}\n")
    assert main(["--config", str(bad)]) == 2
    assert message in capsys.readouterr().err


def test_train_only_moves_the_named_parameters_alone(tmp_path, image_folder):
    """train_only: the box branch trains; the backbone, its BN statistics and the classification branch stay."""
    cfg = config(tmp_path, image_folder, stage="baseline", train_only=["head.box0.loc."], steps=2,
                 checkpoint_every=2)
    trainer = Trainer(cfg)
    before = {k: v.detach().clone() for k, v in trainer.net.state_dict().items()}
    trainer.step_on(next(iter(data_loader(cfg, trainer.net, 0))))
    after = trainer.net.state_dict()
    moved = {k for k in before if not torch.equal(before[k], after[k])}
    assert moved and all(k.startswith("head.box0.loc.") for k in moved)
    assert any(k.endswith("running_mean") for k in moved)  # the branch's own BN statistics do follow
    with pytest.raises(ValueError, match="no parameter of the network starts with 'head.nothing'"):
        Trainer(replace(cfg, train_only=["head.nothing"]))


def test_checkpoint_exports_with_parity(tmp_path, image_folder):
    from dadiff.export.checkpoint import load_checkpoint
    from dadiff.export.onnx_export import export_model

    cfg = config(tmp_path, image_folder, steps=1)
    run(cfg, progress=False)
    report = export_model(load_checkpoint(Path(cfg.out) / "final.pt"), tmp_path / "model", "trained")
    assert report.max_parity <= 1e-4


def test_baseline_stage_bypasses_the_dadiff_block(tmp_path, image_folder):
    cfg = config(tmp_path, image_folder, stage="baseline", steps=1)
    trainer = run(cfg, progress=False)
    assert not trainer.net.cfg.use_dadiff and trainer.disc is None


def test_adversary_without_the_block_judges_the_neck_features_and_moves_the_backbone(tmp_path, image_folder):
    """`block = false`: the dadiff stage's adversary alone, on the neck features (Table IV's question whether
    the diffusion or the adversary gains): no block in the network, no L_align, and generator steps against a
    fixed discriminator make the night neck look more like day."""
    cfg = config(tmp_path, image_folder, block=False, disc_lr=0.0, lambda_trc=0.0, lambda_adv=1.0)
    trainer = Trainer(cfg)
    assert not trainer.net.cfg.use_dadiff and trainer.disc is not None
    batch = next(iter(data_loader(cfg, trainer.net, 0)))
    before = losses_on(trainer, batch)["adv"]
    neck_w = next(p for n, p in trainer.net.named_parameters() if n.startswith("neck.")).detach().clone()
    for _ in range(3):
        logs = trainer.step_on(batch)
    assert logs["align"] == 0 and "adv" in logs
    assert losses_on(trainer, batch)["adv"] < before
    assert not torch.equal(neck_w, next(p for n, p in trainer.net.named_parameters() if n.startswith("neck.")))
    assert trainer.state_timesteps(2) == [-1, -1]


@pytest.mark.parametrize("body", ["stage = 'baseline'\nblock = false\n", "adversarial = false\nblock = false\n"])
def test_block_off_needs_the_dadiff_stage_and_its_adversary(tmp_path, capsys, body):
    from dadiff.export.train import main

    bad = tmp_path / "noblock.toml"
    bad.write_text("[train]\n" + body)
    assert main(["--config", str(bad)]) == 2
    assert "block = false is the dadiff stage's adversary alone" in capsys.readouterr().err


TEACHER = Path(__file__).resolve().parents[2] / "shared" / "weights" / "nanotrack" / "v3"


@pytest.mark.skipif(not TEACHER.is_dir(), reason="NanoTrack v3 teacher weights are not at ../shared/weights")
def test_teacher_distillation_trains_the_mobile_family_and_stays_out_of_the_model(tmp_path, image_folder):
    cfg = config(tmp_path, image_folder, stage="baseline", family="dadiff-mobile", init="imagenet", steps=3,
                 teacher=str(TEACHER), freeze_backbone_blocks=2, ema_decay=0.5)
    trainer = Trainer(cfg)
    batch = next(iter(data_loader(cfg, trainer.net, 0)))
    adapter = trainer.adapter.weight.detach().clone()
    first = trainer.step_on(batch)
    for _ in range(3):
        logs = trainer.step_on(batch)
    assert logs["distill"] < first["distill"] and logs["feature"] < first["feature"]
    assert not torch.equal(adapter, trainer.adapter.weight)  # the adapter is trained with the network
    trainer.save(tmp_path / "final.pt")
    from dadiff.export.checkpoint import load_checkpoint

    model_keys = set(load_checkpoint(tmp_path / "final.pt").model.state_dict())
    assert model_keys == set(trainer.net.state_dict()) and not any("adapter" in k for k in model_keys)
    # the weight average keeps the adapter too, so a run that starts from it (`init`) continues the distillation
    trainer.save_average(tmp_path / "final-ema.pt")
    assert set(load_checkpoint(tmp_path / "final-ema.pt").model.state_dict()) == model_keys
    follower = Trainer(replace(cfg, init=str(tmp_path / "final-ema.pt"), out=str(tmp_path / "next")))
    assert torch.equal(follower.adapter.weight, trainer.adapter.weight)


def test_night_tracking_loss_on_rendered_night_pairs(tmp_path, image_folder):
    """With lambda_night_trc the rendered night pairs (whose boxes are the day boxes) are tracked too, in the
    baseline stage as well, and their loss goes down; without it they stay out of the total."""
    cfg = config(tmp_path, image_folder, stage="baseline", night=None, lambda_night_trc=1.0)
    trainer = Trainer(cfg)
    without_dropout(trainer)
    batch = next(iter(data_loader(cfg, trainer.net, 0)))
    assert bool(batch["paired"].all()) and batch["x_night"].shape == batch["x"].shape
    first = trainer.step_on(batch)
    for _ in range(4):
        logs = trainer.step_on(batch)
    assert logs["night_cls"] < first["night_cls"] and logs["night_loc"] < first["night_loc"]
    plain = Trainer(replace(cfg, lambda_night_trc=0.0))
    assert "night_cls" not in plain.step_on(batch)


def test_box_loss_weight_applies_by_day_and_at_night(tmp_path, image_folder):
    """lambda_loc weighs the IoU loss against the classification loss in both halves of L_trc."""
    cfg = config(tmp_path, image_folder, stage="baseline", night=None, lambda_night_trc=1.0, lambda_loc=3.0)
    trainer = Trainer(cfg)
    logs = trainer.step_on(next(iter(data_loader(cfg, trainer.net, 0))))
    expected = logs["cls"] + 3.0 * logs["loc"] + logs["night_cls"] + 3.0 * logs["night_loc"]
    assert logs["total"] == pytest.approx(expected, rel=1e-5)


def test_search_scale_sets_how_far_the_crop_strays_from_the_target_size(tmp_path, image_folder):
    """At 0 the target always fills the search crop as the tracker expects (its context square is the
    exemplar side); a wide jitter spreads its size, so the crop no longer tells the network the answer."""
    from dadiff.export.train_data import CropConfig, context_side

    def target_sides(search_scale: float) -> np.ndarray:
        cfg = config(tmp_path, image_folder, stage="baseline", night=None, batch_size=8, search_scale=search_scale)
        batch = next(iter(data_loader(cfg, Trainer(cfg).net, 0)))
        sides = []
        for label, loc in zip(batch["label"], batch["loc"], strict=True):
            i, j = (label == 1).nonzero()[0]
            left, top, right, bottom = loc[:, i, j].tolist()
            sides.append(context_side(left + right, top + bottom, CropConfig.context))
        return np.array(sides)

    exemplar = CropConfig.exemplar
    assert np.allclose(target_sides(0.0), exemplar, rtol=0.01)
    wide = target_sides(0.5)
    assert wide.max() / wide.min() > 1.1 and np.all(np.abs(np.log(wide / exemplar)) <= 0.5 + 0.01)


def test_search_shift_sets_how_far_the_target_strays_from_the_crop_centre(tmp_path, image_folder):
    """The positive points of each search crop's label lie where the target was moved to: at 0 on the
    centre cell, with a wide shift spread up to that many crop px off it (never farther)."""

    def offsets(search_shift: float) -> tuple[np.ndarray, int]:  # crop px from the centre to the positives
        cfg = config(tmp_path, image_folder, stage="baseline", night=None, batch_size=8, search_shift=search_shift,
                     search_scale=0.0)
        net = Trainer(cfg).net
        batch = next(iter(data_loader(cfg, net, 0)))
        centre = (batch["label"].shape[-1] - 1) / 2
        cells = [np.abs(np.argwhere(label.numpy() == 1).mean(0) - centre).max() for label in batch["label"]]
        return np.array(cells) * net.cfg.tracker.stride, net.cfg.tracker.stride

    still, stride = offsets(0.0)
    assert still.max() <= stride / 2
    wide, _ = offsets(96.0)
    assert wide.max() > 40 and wide.max() <= 96 + stride


def test_teacher_needs_a_stride_16_family(tmp_path, image_folder):
    cfg = config(tmp_path, image_folder, stage="baseline", teacher=str(tmp_path))
    with pytest.raises(ValueError, match="stride-16"):
        Trainer(cfg)


def test_bad_config_is_one_line(tmp_path, capsys):
    from dadiff.export.train import main

    bad = tmp_path / "bad.toml"
    bad.write_text("[train]\nstage = 'dadiff'\nsteps = 3\nbogus = 1\n")
    assert main(["--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown config keys: bogus" in err


@pytest.mark.parametrize(("table", "expected"), [
    ("ddim_steps = 30", ("'ddim_steps' is 30",)),  # more steps than the diffusion has
    ("head_upsample = 2", ("'model' has unknown keys head_upsample",)),  # a retired experiment's flag
])
def test_a_bad_model_table_is_one_line_naming_the_file(tmp_path, capsys, table, expected):
    """The run and the config check apply `model = {...}` through one function (`with_overrides`)."""
    from dadiff.export.train import main

    bad = tmp_path / "bad.toml"
    bad.write_text(f'[train]\nstage = "dadiff"\nfamily = "dadiff-mobile"\nsteps = 1\nmodel = {{ {table} }}\n')
    assert main(["--config", str(bad), "--output", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bad) in err and all(part in err for part in expected)


def test_seed_and_out_on_the_command_line_override_the_config(tmp_path, image_folder, capsys):
    """A second run of one recipe: the same TOML, another seed and folder; the state records the seed used."""
    from dadiff.export.checkpoint import read_checkpoint_file
    from dadiff.export.train import main

    toml = tmp_path / "recipe.toml"
    toml.write_text(f"[train]\nout = '{tmp_path / 'first'}'\nstage = 'baseline'\nsteps = 1\nbatch_size = 2\n"
                    f"seed = 3\nday = [{{ kind = 'images', root = '{image_folder}' }}]\n")
    assert main(["--config", str(toml), "--seed", "11", "--output", str(tmp_path / "second")]) == 0
    assert not (tmp_path / "first").exists()
    assert read_checkpoint_file(tmp_path / "second" / "final.pt")["train_config"]["seed"] == 11
    capsys.readouterr()  # the run's progress bar
    with pytest.raises(SystemExit) as stop:
        main(["--config", str(toml), "--seed", "-1"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--seed" in err and "'-1'" in err


def test_a_checkpoint_set_to_a_smaller_search_crop_is_refused_as_a_start(tmp_path, capsys):
    """The shipped default's checkpoint holds 14 x 14 search start noise (223 px); training crops 255 px."""
    from dadiff.export.train import main
    from dadiff.models import resolve

    cfg = tmp_path / "from-default.toml"
    cfg.write_text(f"[train]\nout = '{tmp_path / 'run'}'\nstage = 'dadiff'\nfamily = 'dadiff-mobile'\nsteps = 1\n"
                   f"model = {{ align_residual = true }}\ninit = '{resolve('dadiff-mobile') / 'checkpoint.pt'}'\n")
    assert main(["--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "e_xf [1, 48, 14, 14] vs model [1, 48, 16, 16]" in err


def test_ddp_two_processes_keep_weights_in_sync(tmp_path, image_folder):
    toml = tmp_path / "ddp.toml"
    toml.write_text(f"""[train]
out = "{tmp_path / 'ddp'}"
stage = "dadiff"
steps = 2
batch_size = 2
optimizer = "adamw"
warmup_steps = 1
day = [{{ kind = "images", root = "{image_folder}" }}]
night = "{image_folder}"
""")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "dadiff.export.train", "--config", str(toml)]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    line = next(ln for ln in result.stdout.splitlines() if "replicas" in ln)
    assert "2 replicas" in line and float(line.rsplit(" ", 1)[1]) == 0.0
    assert np.isfinite(float(line.rsplit(" ", 1)[1]))


def test_night_styles_are_checked_before_training(tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text('[train]\nnight_styles = ["real", "dusk"]\n')
    from dadiff.export.train import main

    assert main(["--config", str(config)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("'night_styles' has 'dusk'; expected items from classic, real, camera")


def test_chain_alignment_pulls_night_outputs_towards_the_paired_day_outputs(tmp_path, image_folder):
    """align_target = "chain": the loss is the sampler's night output against its detached day output, it goes
    down with training, and the day branch gets no gradient from it (the day output is the target)."""
    from dadiff.export.losses import chain_align_loss

    cfg = config(tmp_path, image_folder, night=None, adversarial=False, lambda_trc=0.0, align_target="chain")
    trainer = Trainer(cfg)
    without_dropout(trainer)
    batch = next(iter(data_loader(cfg, trainer.net, 0)))
    trainer.train_mode()
    out = trainer.model(batch["z"], batch["x"], batch["label"], batch["loc"], True, batch["z_night"],
                        batch["x_night"])
    day_out = out["day_states"][-1]  # the search branch's chain output
    assert out["align"].item() > 0.0
    assert chain_align_loss(day_out, day_out).item() == 0.0
    night_leaf, day_leaf = torch.randn(2, 4, 3, 3, requires_grad=True), torch.randn(2, 4, 3, 3, requires_grad=True)
    g_night, g_day = torch.autograd.grad(chain_align_loss(night_leaf, day_leaf), [night_leaf, day_leaf],
                                         allow_unused=True)
    assert g_day is None and g_night.abs().sum() > 0
    first = trainer.step_on(batch)["align"]
    for _ in range(5):
        last = trainer.step_on(batch)["align"]
    assert last < first


def test_chain_alignment_needs_paired_night(tmp_path, capsys):
    from dadiff.export.train import main

    bad = tmp_path / "chain.toml"
    bad.write_text(f'[train]\nalign_target = "chain"\nnight = "{tmp_path}"\n')
    assert main(["--config", str(bad)]) == 2
    assert "align_target 'chain' needs night rendered from the day frames" in capsys.readouterr().err
    bad.write_text('[train]\nalign_target = "x0"\n')
    assert main(["--config", str(bad)]) == 2
    assert "'align_target' is 'x0'; expected one of eps, chain, restore" in capsys.readouterr().err


def test_restore_alignment_trains_the_block_to_give_day_features_at_night(tmp_path, image_folder):
    """align_target = "restore": zero exactly when the aligned night and day features are the day neck's; with
    only the block training it goes down and the rest of the network does not move."""
    from dadiff.export.losses import restore_loss

    day = torch.randn(2, 4, 3, 3)
    assert restore_loss(day.clone(), day.clone(), day).item() == 0.0
    assert restore_loss(day + 1.0, day.clone(), day).item() > 0.0
    assert restore_loss(day.clone(), day + 1.0, day).item() > 0.0  # by day the block should change nothing

    cfg = config(tmp_path, image_folder, night=None, adversarial=False, lambda_trc=0.0, align_target="restore",
                 model={"align_residual": True}, train_only=["diffusion.", "align_track.", "align_scale"])
    trainer = Trainer(cfg)
    without_dropout(trainer)
    batch = next(iter(data_loader(cfg, trainer.net, 0)))
    head_w = trainer.net.head.box0.loc.head[3].weight.detach().clone()
    first = trainer.step_on(batch)["align"]
    for _ in range(5):
        last = trainer.step_on(batch)["align"]
    assert last < first
    assert trainer.net.align_scale.abs().sum() > 0  # the gate opened from 0
    assert torch.equal(trainer.net.head.box0.loc.head[3].weight, head_w)


@pytest.mark.skipif(not TEACHER.is_dir(), reason="NanoTrack v3 teacher weights are not at ../shared/weights")
def test_night_distillation_uses_the_teachers_day_responses_on_the_night_pairs(tmp_path, image_folder):
    """lambda_night_distill: the teacher's responses on the day crops are targets for the night crops' maps."""
    cfg = config(tmp_path, image_folder, stage="baseline", family="dadiff-mobile", night=None, teacher=str(TEACHER),
                 freeze_backbone_blocks=2, lambda_night_trc=1.0, lambda_night_distill=1.0)
    trainer = Trainer(cfg)
    batch = next(iter(data_loader(cfg, trainer.net, 0)))
    first = trainer.step_on(batch)
    for _ in range(4):
        last = trainer.step_on(batch)
    assert last["night_distill"] < first["night_distill"]
    assert "night_distill" not in Trainer(replace(cfg, lambda_night_distill=0.0)).step_on(batch)


def test_night_distillation_needs_a_teacher(tmp_path, capsys):
    from dadiff.export.train import main

    bad = tmp_path / "kd.toml"
    bad.write_text("[train]\nlambda_night_distill = 1.0\n")
    assert main(["--config", str(bad)]) == 2
    assert "lambda_night_distill needs a teacher" in capsys.readouterr().err


def test_residual_dadiff_block_joins_a_trained_tracker_as_its_identity_and_then_trains(tmp_path, image_folder):
    from dadiff.export.checkpoint import load_checkpoint
    from dadiff.export.onnx_export import export_model

    base_cfg = config(tmp_path / "base", image_folder, stage="baseline", steps=1)
    run(base_cfg, progress=False)
    start = Path(base_cfg.out) / "final.pt"
    cfg = config(tmp_path, image_folder, init=str(start), model={"align_residual": True}, steps=2, adversarial=False)
    joined = Trainer(cfg).net.eval()
    base = load_checkpoint(start).model.eval().to(memory_format=torch.channels_last)  # as the trainer lays it out
    gen = torch.Generator().manual_seed(0)
    z, x = torch.rand(2, 3, 127, 127, generator=gen) * 255, torch.rand(2, 3, 255, 255, generator=gen) * 255
    with torch.no_grad():
        for ours, theirs in zip(joined(z, x), base(z, x), strict=True):
            assert torch.equal(ours, theirs)  # the gate starts at 0: exactly the tracker it joins
    trained = run(cfg, progress=False).net
    assert trained.align_scale.abs().max().item() > 0  # the tracking losses open the gate
    report = export_model(load_checkpoint(Path(cfg.out) / "final.pt"), tmp_path / "model", "residual")
    assert report.max_parity <= 1e-4


def test_dadiff_lr_mult_gives_the_block_its_own_rate_and_keeps_two_groups_at_one(tmp_path, image_folder):
    from dadiff.export.train import DADIFF_BLOCK, param_groups

    plain = Trainer(config(tmp_path, image_folder, adversarial=False))
    assert len(plain.opt.param_groups) == 2  # the layout of earlier runs' optimiser states, so they resume
    fast = Trainer(config(tmp_path, image_folder, adversarial=False, dadiff_lr_mult=5.0))
    fast.set_lr()
    backbone, rest, block = fast.opt.param_groups
    names = {id(p): n for n, p in fast.net.named_parameters()}
    assert block["params"] and all(names[id(p)].startswith(DADIFF_BLOCK) for p in block["params"])
    assert not any(names[id(p)].startswith(DADIFF_BLOCK) for p in rest["params"])
    assert block["lr"] == pytest.approx(5.0 * rest["lr"])
    every = [p for g in param_groups(fast.net, fast.cfg) for p in g["params"]]
    assert len(every) == len({id(p) for p in every}) == sum(p.requires_grad for p in fast.net.parameters())


def test_loc_region_box_regresses_every_point_inside_the_target_box(tmp_path, capsys):
    """loc_region "box" trains the box at every point inside it as well as at BAN's positive ellipse."""
    import torch

    from dadiff.export.losses import ban_iou_loss, regression_points
    from dadiff.export.train import main
    from dadiff.export.train_data import CropConfig, ban_targets

    cfg = CropConfig()
    label, target = (torch.from_numpy(a)[None] for a in ban_targets(np.array([0.0, 0.0, 120.0, 80.0]), cfg))
    ellipse, box = regression_points(target, label), regression_points(target, label, "box")
    inside = (target > 0).all(dim=1)
    assert torch.equal(ellipse, label == 1) and torch.equal(box, inside | ellipse)
    assert ellipse.sum() < box.sum()  # 120 x 80 crop px on the stride-8 map: 31 points in the ellipse, 135 in the box
    # a prediction exact on the ellipse and off elsewhere costs nothing there and only in the box region
    pred = torch.where(ellipse[:, None], target, target * 0.5 + 1.0)
    assert ban_iou_loss(pred, target, label).item() == pytest.approx(0.0, abs=1e-6)
    assert ban_iou_loss(pred, target, label, "box").item() > 0.1
    bad = tmp_path / "region.toml"
    bad.write_text('[train]\nloc_region = "everywhere"\n')
    assert main(["--config", str(bad)]) == 2
    assert "'loc_region' is 'everywhere'; expected one of ellipse, box" in capsys.readouterr().err


def test_side_log_loss_weighs_a_sides_error_by_that_side(tmp_path, capsys):
    """The IoU loss charges 4 px too many on a thin box's near side (8 px) as on its far side (24 px); the
    per-side loss charges the near side more, and nothing for an exact box."""
    import torch

    from dadiff.export.losses import ban_iou_loss, ban_side_log_loss
    from dadiff.export.train import main

    label = torch.ones(1, 1, 1, dtype=torch.long)
    target = torch.tensor([8.0, 40.0, 24.0, 40.0]).view(1, 4, 1, 1)
    near, far = target.clone(), target.clone()
    near[0, 0] += 4.0
    far[0, 2] += 4.0
    assert ban_iou_loss(near, target, label).item() == pytest.approx(ban_iou_loss(far, target, label).item())
    assert ban_side_log_loss(target, target, label).item() == pytest.approx(0.0, abs=1e-7)
    assert ban_side_log_loss(near, target, label).item() > 2 * ban_side_log_loss(far, target, label).item()
    bad = tmp_path / "side.toml"
    bad.write_text("[train]\nlambda_side = -1.0\n")
    assert main(["--config", str(bad)]) == 2
    assert "'lambda_side' is -1.0; expected >= 0" in capsys.readouterr().err


def test_night_path_lamps_config_is_a_share_of_scene_lit_pairs(tmp_path, capsys):
    from dadiff.export.train import main

    for text, message in (('night_pairs = "scene"\nnight_path_lamps = 1.5', "'night_path_lamps' is 1.5; expected <= 1"),
                          ("night_path_lamps = 0.5", 'night_path_lamps needs night_pairs = "scene"'),
                          ('day = [{ kind = "sequences", root = ".", one_night = true }]',
                           'one_night needs night_pairs = "scene"')):
        bad = tmp_path / "lamps.toml"
        bad.write_text(f"[train]\n{text}\n")
        assert main(["--config", str(bad)]) == 2
        assert message in capsys.readouterr().err
