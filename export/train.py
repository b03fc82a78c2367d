"""`dadiff-train --config FILE.toml`: the paper's two-stage training, resumable, single process or torchrun.

Stage "baseline": the Siamese tracker alone (no DaDiff block) on labelled day pairs with the BAN losses.
Stage "dadiff": the DaDiff block inserted; L_total = l1 L_trc (day) + l2 L_adv + l3 L_align, with the
successive discriminator judging day/night at every state of the DDIM chain and gradients flowing through
the sampler into the denoiser and the tracking-oriented layer (paper sec. III; spec 12).
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader

from dadiff.runtime.errors import DadiffError, os_error_line

from .checkpoint import (
    CheckpointError,
    load_checkpoint,
    read_checkpoint_file,
    save_checkpoint,
    shape_mismatches,
    stopped_run,
)
from .config import ModelConfig, default_config, is_lite0, with_overrides
from .discriminator import SuccessiveDiscriminator, adversarial_loss, chain_timesteps
from .losses import (
    align_loss,
    ban_cls_loss,
    ban_iou_loss,
    ban_side_log_loss,
    chain_align_loss,
    distill_cls_loss,
    distill_loc_loss,
    feature_distill_loss,
    restore_loss,
)
from .network import DaDiffNet, build_model
from .train_check import SetupError, check_train_values, resolved
from .train_cli import build_parser, finish_line
from .train_data import CropConfig, PairStream, make_day_source
from .train_stages import STAGES, StagePlan, plan_stages
from .train_toml import config_chain, format_toml, key_file
from .weight_average import WeightAverage

DAY, NIGHT = 0.0, 1.0
DADIFF_BLOCK = ("diffusion.", "align_track.", "align_scale")  # parameter names of the DaDiff block


@dataclass
class TrainConfig:
    out: str = "runs/lite"
    stage: str = "dadiff"                 # "baseline" | "dadiff"
    family: str = "dadiff-lite"
    init: str = "imagenet"                # "imagenet" | path to a checkpoint (ours) to start from
    model: dict[str, Any] = field(default_factory=dict)   # ModelConfig overrides (align, ddim_steps, ...)
    day: list[dict[str, Any]] = field(default_factory=lambda: [{"kind": "scenes", "split": "train"}])
    night: str | None = None              # folder of night images/videos; None = render night from day
    steps: int = 1000
    batch_size: int = 16
    workers: int = 0
    optimizer: str = "sgd"                # "sgd" (release) | "adamw"
    lr: float = 0.0015                    # DaDiff base lr (paper)
    backbone_lr_mult: float = 0.1
    dadiff_lr_mult: float = 1.0           # the DaDiff block's factor (denoiser, tracking-oriented layer, gate)
    warmup_steps: int = 50
    weight_decay: float = 1e-4
    freeze_backbone_blocks: int = 5       # EfficientNet-Lite0 blocks 0..N-1 stay ImageNet
    train_only: list[str] = field(default_factory=list)  # parameter-name prefixes to train; [] trains all
    disc_lr: float = 0.005                # paper: discriminator base lr 0.005, poly decay power 0.8
    disc_poly_power: float = 0.8
    lambda_trc: float = 1.0
    lambda_loc: float = 1.0               # the box (IoU) loss within L_trc, day and night, relative to cls
    lambda_adv: float = 0.1
    lambda_align: float = 1.0
    adversarial: bool = True              # ablation switches (Table IV)
    align_loss: bool = True
    block: bool = True                    # false: stage dadiff without the DaDiff block, L_adv on the neck features
    align_target: str = "eps"             # "eps": paper eq. 6; "chain": the sampler's output vs the day output;
    #                                       "restore": aligned night features vs the paired day neck features
    search_scale: float = CropConfig.search_scale  # search crops rescaled by exp(U(-s, s)) around the target
    search_shift: float = CropConfig.search_shift  # search crops moved U(-s, s) crop px each way off the target
    loc_region: str = "ellipse"           # box regression at BAN's positive points, or "box": every point inside
    lambda_side: float = 0.0              # per-side log-distance loss beside the IoU loss, within the box loss
    grad_clip: float = 10.0
    checkpoint_every: int = 100
    keep_checkpoints: bool = False        # also keep each periodic checkpoint as OUT/step-NNNNNN.pt
    seed: int = 0
    teacher: str | None = None            # NanoTrack v3 ONNX folder: distil its responses and search features
    lambda_distill: float = 1.0           # teacher cls + loc responses (stride-16 families)
    lambda_feature: float = 0.5           # teacher search features through a training-only 1x1 adapter
    lambda_night_trc: float = 0.0         # L_trc on the rendered night pairs too (their boxes are the day boxes)
    lambda_night_distill: float = 0.0     # the teacher's responses on the day crops as targets on the night pairs
    night_styles: list[str] = field(default_factory=lambda: ["real"])  # rendered night: one style per pair
    night_pairs: str = "frame"            # "scene": one night camera and fixed lights over a scene's pair
    night_path_lamps: float = 0.0         # share of scene-lit night pairs given lamp heads beside the target
    negative_pairs: float = 0.0           # share of pairs whose search crop holds another object (release: 0.2)
    ema_decay: float = 0.0                # > 0: also keep a moving average of the weights (OUT/final-ema.pt)

    @classmethod
    def from_toml(cls, path: str | Path) -> TrainConfig:
        """The config in `path`, after the files it `extends`; each file's keys are checked where they are
        written (unknown keys, types and ranges), so an error names the file that holds the bad key."""
        return cls.from_chain(config_chain(path), path)

    @classmethod
    def from_chain(cls, chain: Sequence[tuple[str | Path, dict[str, Any]]], path: str | Path) -> TrainConfig:
        """The config of (file or stage, its own keys) pairs, later ones replacing earlier keys; `path` names
        the whole in errors that need more than one key."""
        known = set(cls.__dataclass_fields__)
        flat: dict[str, Any] = {}
        for file, own in chain:
            unknown = sorted(set(own) - known)
            if unknown:
                raise ValueError(f"{file}: unknown config keys: {', '.join(unknown)} (dadiff-train --help lists "
                                 f"them)")
            flat.update(own)
            check_train_values(cls(), flat, file)  # types and ranges, before any work
        cfg = cls(**flat)
        if cfg.stage not in ("baseline", "dadiff"):
            raise ValueError(f"{path}: stage must be 'baseline' or 'dadiff', got {cfg.stage!r}")
        if cfg.align_target in ("chain", "restore") and cfg.night is not None:
            raise ValueError(f"{path}: align_target '{cfg.align_target}' needs night rendered from the day frames "
                             f"(paired); drop 'night' or use align_target 'eps'")
        if not cfg.block and (cfg.stage != "dadiff" or not cfg.adversarial):
            raise ValueError(f"{path}: block = false is the dadiff stage's adversary alone (on the neck features); "
                             f"it needs stage 'dadiff' and adversarial = true")
        if cfg.lambda_night_distill and (cfg.teacher is None or cfg.night is not None):
            raise ValueError(f"{path}: lambda_night_distill needs a teacher and night rendered from the day frames "
                             f"(paired); set 'teacher' and drop 'night'")
        if cfg.night_path_lamps and (cfg.night_pairs != "scene" or cfg.night is not None):
            raise ValueError(f"{path}: night_path_lamps needs night_pairs = \"scene\" (night rendered over the "
                             f"generated scene); set it or drop night_path_lamps")
        if any(source.get("one_night") for source in cfg.day) and cfg.night_pairs != "scene":
            raise ValueError(f"{path}: a day source's one_night needs night_pairs = \"scene\" (a night over each "
                             f"pair); set it or drop one_night")
        if cfg.batch_size < 2:  # BatchNorm layers (head, channel weights) need 2+ samples per process
            raise ValueError(f"{path}: batch_size must be at least 2 per process, got {cfg.batch_size}")
        return cfg


def model_config(cfg: TrainConfig) -> ModelConfig:
    base = default_config(cfg.family)
    mc = with_overrides(base, cfg.model or {})
    return replace(mc, use_dadiff=cfg.stage == "dadiff" and cfg.block)


def build_network(cfg: TrainConfig) -> DaDiffNet:
    mc = model_config(cfg)
    if cfg.init == "imagenet":
        net = build_model(mc, pretrained_backbone=is_lite0(mc.backbone))
        for box in net.head.levels():  # start the box distances near a typical target half-size (32 crop px)
            nn.init.constant_(box.loc.head[3].bias, math.log(32.0))
        return net
    net = build_model(mc)
    loaded = load_init(cfg.init)
    source = loaded.model.state_dict()  # strict for the checkpoint's own config
    own = net.state_dict()
    # the stages share every key; an ablation without the tracking-oriented layer only drops align_track.*, and
    # a residual DaDiff block joining a trained tracker adds its gate align_scale (from 0)
    optional = {k for k in set(source) | set(own) if k.startswith("align_track.") or k == "align_scale"}
    missing, unexpected = sorted(set(own) - set(source) - optional), sorted(set(source) - set(own) - optional)
    if missing or unexpected:
        parts = [f"{what}: {_some(keys)}" for what, keys in (("missing from the checkpoint", missing),
                                                              ("unexpected, not in the configured model", unexpected))
                 if keys]
        family = loaded.config.family
        advice = f"; set family = \"{family}\" or start from a {mc.family} checkpoint" if family != mc.family else ""
        raise SetupError("init", f"'init' is {cfg.init!r}: its {family} model does not fit the configured "
                                 f"{mc.family} model ({'; '.join(parts)}){advice}")
    reshaped = shape_mismatches(own, source)
    if reshaped:  # e.g. a model folder's checkpoint set to a smaller search crop than training uses
        raise SetupError("init", f"'init' is {cfg.init!r}: holds tensors of other shapes than the configured model: "
                                 f"{', '.join(reshaped[:3])}; start from a training state (export/resume/) instead")
    net.load_state_dict({k: v for k, v in source.items() if k in own}, strict=False)
    return net


def _some(keys: list[str], limit: int = 4) -> str:
    return ", ".join(keys[:limit]) + (f" and {len(keys) - limit} more" if len(keys) > limit else "")


def load_init(init: str) -> Any:
    """The `init` checkpoint; a path that is not there says where it was looked for (relative paths are
    taken from the working folder) and when its run has only got as far as last.pt."""
    path = Path(init).expanduser()
    if not path.exists():
        unfinished = "; that run has not finished: start from its last.pt, or finish the run first"
        hint = unfinished if stopped_run(path) else ""
        raise SetupError("init", f"'init' is {init!r}: no such file ({resolved(init)}); expected \"imagenet\" or "
                                 f"a dadiff checkpoint{hint}")
    try:
        return load_checkpoint(path)
    except CheckpointError as e:
        raise SetupError("init", f"'init': {e}") from None


def freeze_early_blocks(net: DaDiffNet, blocks: int) -> list[nn.Module]:
    """Keep the stem and the first backbone blocks at their ImageNet weights (and BN statistics)."""
    frozen: list[nn.Module] = []
    if not is_lite0(net.cfg.backbone) or blocks <= 0:
        return frozen
    bb = net.backbone
    frozen = [bb._conv_stem, bb._bn0, *list(bb._blocks)[:blocks]]
    for m in frozen:
        for p in m.parameters():
            p.requires_grad_(False)
    return frozen


def freeze_all_but(net: DaDiffNet, prefixes: Sequence[str]) -> list[nn.Module]:
    """Train only the parameters named with one of `prefixes` (e.g. the head's box branch, so a fine-tune
    cannot move the features that find the target); the other leaf modules stay in eval mode, BN statistics
    and dropout included. No prefixes: nothing frozen."""
    if not prefixes:
        return []
    names = [n for n, _ in net.named_parameters()]
    for prefix in prefixes:
        if not any(n.startswith(prefix) for n in names):
            tops = sorted({n.split(".")[0] + "." for n in names})
            raise SetupError("train_only", f"'train_only' has {prefix!r}, but no parameter of the network starts "
                                           f"with {prefix!r} (its parameter names start with {', '.join(tops)})")
    keep = tuple(prefixes)
    for name, p in net.named_parameters():
        if not name.startswith(keep):
            p.requires_grad_(False)
    return [m for name, m in net.named_modules() if not list(m.children()) and not (name + ".").startswith(keep)]


def param_groups(net: DaDiffNet, cfg: TrainConfig) -> list[dict[str, Any]]:
    """Backbone, the rest, then the DaDiff block as a group of its own only when its factor differs (so that
    the optimiser states of earlier runs, with two groups, still resume)."""
    backbone = [p for p in net.backbone.parameters() if p.requires_grad]
    own = [(DADIFF_BLOCK, cfg.dadiff_lr_mult)] if cfg.dadiff_lr_mult != 1.0 else []
    named = [(n, p) for n, p in net.named_parameters() if p.requires_grad and not n.startswith("backbone.")]
    groups = [{"params": backbone, "lr_mult": cfg.backbone_lr_mult}]
    for prefixes, mult in own:
        groups.append({"params": [p for n, p in named if n.startswith(prefixes)], "lr_mult": mult})
        named = [(n, p) for n, p in named if not n.startswith(prefixes)]
    groups.insert(1, {"params": [p for _, p in named], "lr_mult": 1.0})
    return groups


def make_optimizer(groups: list[dict[str, Any]], cfg: TrainConfig) -> torch.optim.Optimizer:
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(groups, lr=cfg.lr, momentum=0.9, weight_decay=cfg.weight_decay)
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(groups, lr=cfg.lr, weight_decay=cfg.weight_decay)
    raise ValueError(f"unknown optimizer {cfg.optimizer!r}; expected sgd or adamw")


def tracker_lr(cfg: TrainConfig, step: int) -> float:
    """Linear warm-up, then cosine decay to 1 % of the base rate."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    progress = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    return cfg.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(1.0, progress))))


def disc_lr(cfg: TrainConfig, step: int) -> float:
    """The paper's poly policy: lr = base * (1 - step / steps) ^ 0.8."""
    return cfg.disc_lr * (1 - min(step, cfg.steps - 1) / cfg.steps) ** cfg.disc_poly_power


class Trainer:
    def __init__(self, cfg: TrainConfig, rank: int = 0, world: int = 1, device: str = "cpu") -> None:
        self.cfg, self.rank, self.world = cfg, rank, world
        self.device = torch.device(device)
        torch.manual_seed(cfg.seed)
        self.out = Path(cfg.out)
        self.net = build_network(cfg).to(self.device)
        self.layout = torch.channels_last if self.device.type == "cpu" else torch.contiguous_format
        self.net.to(memory_format=self.layout)  # a CPU step runs a quarter faster so (mostly the trunk's convolutions)
        self.frozen = freeze_early_blocks(self.net, cfg.freeze_backbone_blocks)
        self.frozen += freeze_all_but(self.net, cfg.train_only)
        self.dadiff = cfg.stage == "dadiff"
        self.use_adv = self.dadiff and cfg.adversarial
        self.disc = SuccessiveDiscriminator(self.net.cfg.channels, self.net.cfg.diffusion_total_steps).to(
            self.device) if self.use_adv else None
        self.opt = make_optimizer(param_groups(self.net, cfg), cfg)
        self.disc_opt = torch.optim.Adam(self.disc.parameters(), lr=cfg.disc_lr, betas=(0.9, 0.99)) \
            if self.disc is not None else None
        self.teacher, self.adapter = self.build_teacher()
        if self.adapter is not None:
            self.opt.add_param_group({"params": list(self.adapter.parameters()), "lr_mult": 1.0})
        self.ema = WeightAverage(self.net, cfg.ema_decay) if cfg.ema_decay else None
        self.step = 0
        self.start_step = 0  # where this process's run began (a resumed run: the state's step)
        forward = TrainForward(self.net, cfg.seed * 1000 + rank, self.device, cfg.align_target, cfg.loc_region,
                               cfg.lambda_side)
        self.model = DistributedDataParallel(forward, find_unused_parameters=True) if world > 1 else forward
        self.dmodel = (DistributedDataParallel(self.disc) if world > 1 else self.disc) if self.disc else None

    def build_teacher(self) -> tuple[Any, nn.Module | None]:
        """The teacher and the 1x1 conv mapping our search neck to its feature width (never exported)."""
        if not self.cfg.teacher:
            return None, None
        from .teacher import BACKBONE, HEAD, TEACHER_STRIDE, NanoTrackTeacher

        where = f"'teacher' is {self.cfg.teacher!r}"
        if self.net.cfg.tracker.stride != TEACHER_STRIDE or len(self.net.cfg.level_names) != 1:
            raise SetupError("teacher", f"{where}, but teacher distillation needs a one-level stride-{TEACHER_STRIDE} "
                                        f"family (dadiff-mobile), not {self.net.cfg.family}; set family = "
                                        f"\"dadiff-mobile\" or drop 'teacher'")
        folder = Path(self.cfg.teacher).expanduser()
        if not folder.is_dir():
            raise SetupError("teacher", f"{where}: {'not a folder' if folder.exists() else 'no such folder'} "
                                        f"({resolved(self.cfg.teacher)}); expected the NanoTrack v3 ONNX folder")
        missing = [name for name in (BACKBONE, HEAD) if not (folder / name).is_file()]
        if missing:
            raise SetupError("teacher", f"{where}: the folder ({resolved(self.cfg.teacher)}) lacks "
                                        f"{', '.join(missing)} (NanoTrack v3 ONNX)")
        teacher = NanoTrackTeacher(folder)
        adapter = nn.Conv2d(self.net.cfg.channels, 96, 1)
        if self.cfg.init != "imagenet":  # a stage that continues one with the teacher keeps its adapter
            saved = read_checkpoint_file(Path(self.cfg.init).expanduser()).get("teacher_adapter")
            if saved is not None:
                adapter.load_state_dict(saved)
        return teacher, adapter.to(self.device)

    # ---- checkpoints -------------------------------------------------------------------------------
    @property
    def last_path(self) -> Path:
        return self.out / "last.pt"

    def save(self, path: Path | None = None) -> None:
        if self.rank != 0:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        extra = self.state_extras() | {"optimizer": self.opt.state_dict()}
        if self.disc is not None:
            extra["discriminator"] = self.disc.state_dict()
            extra["disc_optimizer"] = self.disc_opt.state_dict()
        if self.ema is not None:
            extra["ema_state_dict"] = self.ema.state
        save_checkpoint(path or self.last_path, self.net, **extra)

    def save_average(self, path: Path) -> None:
        """The weight average as an ordinary checkpoint, for dadiff-export and as a later run's `init` (with the
        teacher adapter, which a run from it keeps; no optimiser: not a state to resume)."""
        if self.rank == 0 and self.ema is not None:
            save_checkpoint(path, self.ema.averaged(self.net), ema_decay=self.cfg.ema_decay, **self.state_extras())

    def state_extras(self) -> dict[str, Any]:
        """What every saved state carries beside the weights: its step, its config and the teacher adapter
        (a run that starts from the state keeps the adapter)."""
        extra: dict[str, Any] = {"step": self.step, "train_config": self.cfg.__dict__}
        if self.adapter is not None:
            extra["teacher_adapter"] = self.adapter.state_dict()
        return extra

    def resume(self) -> bool:
        if not self.last_path.exists():
            return False
        obj = read_checkpoint_file(self.last_path)
        self.net.load_state_dict(obj["state_dict"], strict=True)
        if self.adapter is not None and "teacher_adapter" in obj:
            self.adapter.load_state_dict(obj["teacher_adapter"])
        self.opt.load_state_dict(obj["optimizer"])
        if self.disc is not None and "discriminator" in obj:
            self.disc.load_state_dict(obj["discriminator"])
            self.disc_opt.load_state_dict(obj["disc_optimizer"])
        if self.ema is not None and "ema_state_dict" in obj:  # else the average starts at the resumed weights
            self.ema.load(obj["ema_state_dict"])
        self.step = int(obj["step"])
        return True

    # ---- one step ----------------------------------------------------------------------------------
    def set_lr(self) -> None:
        lr = tracker_lr(self.cfg, self.step)
        for g in self.opt.param_groups:
            g["lr"] = lr * g["lr_mult"]
        if self.disc_opt is not None:
            for g in self.disc_opt.param_groups:
                g["lr"] = disc_lr(self.cfg, self.step)

    def train_mode(self) -> None:
        self.net.train()
        for m in self.frozen:
            m.eval()  # frozen ImageNet blocks keep their BN statistics
        if self.disc is not None:
            self.disc.train()

    def step_on(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        cfg = self.cfg
        self.set_lr()
        self.train_mode()
        cpu_batch = batch
        batch = {k: v.to(self.device, non_blocking=True) for k, v in batch.items()}
        batch = {k: v.contiguous(memory_format=self.layout) if v.dim() == 4 else v for k, v in batch.items()}
        night_inputs = (batch["z_night"], batch["x_night"]) if uses_night(cfg) else ()
        out = self.model(batch["z"], batch["x"], batch["label"], batch["loc"], bool(batch["paired"].all()),
                         *night_inputs)
        l_align, day_states, night_states = out["align"], out["day_states"], out["night_states"]
        cls, loc = out["cls_map"], out["loc_map"]
        total = cfg.lambda_trc * (out["cls"] + cfg.lambda_loc * out["loc"])
        logs = {"cls": out["cls"].item(), "loc": out["loc"].item()}
        if cfg.lambda_night_trc and bool(batch["paired"].all()):
            total = total + cfg.lambda_night_trc * (out["night_cls"] + cfg.lambda_loc * out["night_loc"])
            logs |= {"night_cls": out["night_cls"].item(), "night_loc": out["night_loc"].item()}
        if self.teacher is not None:
            t_feat, t_prob, t_loc = (t.to(self.device) for t in self.teacher(
                cpu_batch["z"], cpu_batch["x"], cls.shape[-1]))
            l_distill = distill_cls_loss(cls, t_prob) + distill_loc_loss(loc, t_loc, t_prob)
            if cfg.lambda_night_distill and out["night_cls_map"] is not None:
                # the teacher sees the day crop, the student the same crop rendered at night
                l_night_kd = distill_cls_loss(out["night_cls_map"], t_prob) + \
                    distill_loc_loss(out["night_loc_map"], t_loc, t_prob)
                total = total + cfg.lambda_night_distill * l_night_kd
                logs["night_distill"] = l_night_kd.item()
            l_feature = feature_distill_loss(self.adapter(out["x_neck"]), t_feat)
            total = total + cfg.lambda_distill * l_distill + cfg.lambda_feature * l_feature
            logs |= {"distill": l_distill.item(), "feature": l_feature.item()}
        if self.dadiff and cfg.align_loss:
            total = total + cfg.lambda_align * l_align
            logs["align"] = l_align.item()
        ts = self.state_timesteps(len(day_states))
        if self.use_adv:
            l_adv = adversarial_loss(self.dmodel(night_states, ts), DAY)  # night chains should look like day
            total = total + cfg.lambda_adv * l_adv
            logs["adv"] = l_adv.item()
        self.opt.zero_grad(set_to_none=True)
        total.backward()  # under torchrun, DDP averages the gradients of every replica here
        torch.nn.utils.clip_grad_norm_([p for g in self.opt.param_groups for p in g["params"]], cfg.grad_clip)
        self.opt.step()
        if self.ema is not None:
            self.ema.update(self.net)
        if self.use_adv:
            logs["disc"] = self.discriminator_step(day_states, night_states, ts)
        logs["total"] = total.item()
        self.step += 1
        return logs

    def state_timesteps(self, n_states: int) -> list[int]:
        if not self.net.cfg.use_dadiff:  # no block: the states are the neck features, judged as a chain's output
            return [-1] * n_states
        steps = chain_timesteps(self.net.sampler.start_t, self.net.sampler.timesteps)
        return (steps * (n_states // len(steps)))[:n_states]

    def discriminator_step(self, day_states: list[torch.Tensor], night_states: list[torch.Tensor],
                           ts: list[int]) -> float:
        """D learns day = 0, night = 1 on every chain state (detached from the tracker)."""
        loss = adversarial_loss(self.dmodel([s.detach() for s in day_states], ts), DAY) + \
            adversarial_loss(self.dmodel([s.detach() for s in night_states], ts), NIGHT)
        self.disc_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.disc_opt.step()
        return loss.item()


class TrainForward(nn.Module):
    """The tracker's side of one step in a single forward, so that DistributedDataParallel can wrap it."""

    def __init__(self, net: DaDiffNet, seed: int, device: torch.device | str = "cpu",
                 align_target: str = "eps", loc_region: str = "ellipse", lambda_side: float = 0.0) -> None:
        super().__init__()
        self.net = net
        self.gen = torch.Generator(device=device).manual_seed(seed)
        self.align_target = align_target
        self.loc_region = loc_region
        self.lambda_side = lambda_side

    def box_loss(self, loc: torch.Tensor, loc_target: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
        """The IoU loss, plus each side's own log error when `lambda_side` asks for it."""
        loss = ban_iou_loss(loc, loc_target, label, self.loc_region)
        if self.lambda_side:
            loss = loss + self.lambda_side * ban_side_log_loss(loc, loc_target, label, self.loc_region)
        return loss

    def forward(self, z: torch.Tensor, x: torch.Tensor, label: torch.Tensor, loc_target: torch.Tensor, paired: bool,
                z_night: torch.Tensor | None = None, x_night: torch.Tensor | None = None):
        net = self.net
        zb = net.template_branch(z)
        xb = net.search_branch(x)
        cls, loc = net.head(xb.aligned, *net.head.kernels(zb.aligned))
        zero = cls.sum() * 0
        out = {"cls": ban_cls_loss(cls, label), "loc": self.box_loss(loc, loc_target, label), "align": zero,
               "night_cls": zero, "night_loc": zero, "night_states": [],
               "day_states": [s for b in (zb, xb) for level in b.states for s in level],
               "cls_map": cls, "loc_map": loc, "x_neck": xb.neck[0],  # the maps and neck: the teacher's losses
               "night_cls_map": None, "night_loc_map": None}
        if z_night is None:
            return out
        zn = net.template_branch(z_night)
        xn = net.search_branch(x_night)
        out["night_states"] = [s for b in (zn, xn) for level in b.states for s in level]
        if paired:  # rendered from the day frames: the day boxes hold
            cls_n, loc_n = net.head(xn.aligned, *net.head.kernels(zn.aligned))
            out["night_cls"] = ban_cls_loss(cls_n, label)
            out["night_loc"] = self.box_loss(loc_n, loc_target, label)
            out["night_cls_map"], out["night_loc_map"] = cls_n, loc_n
        if net.cfg.use_dadiff and self.align_target == "chain" and paired:
            # L_align on the inference chain itself: the sampler's output from the night features should be
            # what it gives for the same frame by day (detached), so the head sees day-like features at night
            losses = [chain_align_loss(n[-1], d[-1])
                      for db, nb in ((zb, zn), (xb, xn)) for d, n in zip(db.states, nb.states, strict=True)]
            out["align"] = torch.stack(losses).mean()
        elif net.cfg.use_dadiff and self.align_target == "restore" and paired:
            # L_align as paired restoration: what the head receives at night should be the day features of the
            # same frame, and by day the block should change nothing (the block learns to act only at night)
            losses = [restore_loss(n, d, dn) for db, nb in ((zb, zn), (xb, xn))
                      for n, d, dn in zip(nb.aligned, db.aligned, db.neck, strict=True)]
            out["align"] = torch.stack(losses).mean()
        elif net.cfg.use_dadiff:
            # L_align: recover day features from noise, conditioned on the night features of the same content
            # (night rendered from day), or on the day features themselves when the night data is unpaired
            losses = [align_loss(net.diffusion, net.sampler.alpha_bar, d.detach(), n if paired else d, self.gen)
                      for db, nb in ((zb, zn), (xb, xn)) for d, n in zip(db.neck, nb.neck, strict=True)]
            out["align"] = torch.stack(losses).mean()
        return out


def uses_night(cfg: TrainConfig) -> bool:
    """Night crops are made for the DaDiff stage, and for any stage that tracks on them."""
    return cfg.stage == "dadiff" or cfg.lambda_night_trc > 0 or cfg.lambda_night_distill > 0


def day_source(i: int, spec: dict[str, Any]) -> Any:
    """Day source `i` (from 1) of the config; what only reading its data can find (a folder that is not
    there, a library not fetched) names the entry, and for a missing folder, where it was looked for."""
    where = f"'day' entry {i} (kind {spec.get('kind')!r})"
    for key in ("root", "cutouts"):
        if isinstance(spec.get(key), str) and not Path(spec[key]).expanduser().exists():
            raise SetupError("day", f"{where}: '{key}' is {spec[key]!r}: no such folder ({resolved(spec[key])})")
    try:
        return make_day_source(spec)
    except ValueError as e:
        raise SetupError("day", f"{where}: {e}") from None


def data_loader(cfg: TrainConfig, net: DaDiffNet, rank: int, start_step: int = 0) -> DataLoader:
    """The pair stream from `start_step` on: a resumed run continues with pairs it has not seen (the stream
    is seeded by the step it starts at; step 0 is the stream of a run that was never interrupted)."""
    tr = net.cfg.tracker
    crop = CropConfig(exemplar=tr.exemplar_size, instance=tr.instance_size, stride=tr.stride,
                      score_size=tr.score_size, context=tr.context_amount, search_scale=cfg.search_scale,
                      search_shift=cfg.search_shift)
    stream = PairStream([day_source(i, s) for i, s in enumerate(cfg.day, 1)], cfg.night, crop, cfg.seed, rank,
                        with_night=uses_night(cfg), night_styles=cfg.night_styles, start_step=start_step,
                        night_pairs=cfg.night_pairs, night_path_lamps=cfg.night_path_lamps,
                        negative_pairs=cfg.negative_pairs)
    return DataLoader(stream, batch_size=cfg.batch_size, num_workers=cfg.workers,
                      persistent_workers=cfg.workers > 0)


def pick_device(name: str, rank: int = 0) -> str:
    """'auto' takes the GPU when PyTorch sees one (one per rank under torchrun), else the CPU."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        if not torch.cuda.is_available():
            raise ValueError("--device cuda: PyTorch sees no GPU here")
        return f"cuda:{rank % torch.cuda.device_count()}"
    if name != "cpu":
        raise ValueError(f"--device must be auto, cpu or cuda, got {name!r}")
    return name


def run(cfg: TrainConfig, max_steps: int | None = None, progress: bool = True, device: str = "cpu",
        max_minutes: float | None = None, stop_at: int | None = None) -> Trainer:
    """Train `cfg` from its last.pt (or its start) to its `steps` (or `stop_at`, within the same schedule)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    trainer = Trainer(cfg, rank, world, pick_device(device, rank))
    deadline = time.monotonic() + 60 * max_minutes if max_minutes else math.inf
    resumed = trainer.resume()
    trainer.start_step = trainer.step
    loader = iter(data_loader(cfg, trainer.net, rank, trainer.step))
    log_path = trainer.out / "log.csv"
    fields = ["step", "lr", "total", "cls", "loc", "align", "adv", "disc", "distill", "feature", "night_cls",
              "night_loc", "sec_per_step", "night_distill"]
    if rank == 0:
        trainer.out.mkdir(parents=True, exist_ok=True)
        new_log = not log_path.exists() or not resumed
        if not new_log:  # a log from before a column was added keeps its own header
            with open(log_path, newline="") as f:
                fields = next(csv.reader(f), None) or fields
        log_file = open(log_path, "w" if new_log else "a", newline="")
        writer = csv.DictWriter(log_file, fieldnames=fields, extrasaction="ignore")
        if new_log:
            writer.writeheader()
    end = min(cfg.steps, stop_at or cfg.steps, trainer.step + max_steps if max_steps is not None else cfg.steps)
    bar = None
    if progress and rank == 0:
        from tqdm import tqdm

        bar = tqdm(total=cfg.steps, initial=trainer.step, desc=f"{cfg.stage}", dynamic_ncols=True)
    try:
        while trainer.step < end and time.monotonic() < deadline:
            t0 = time.perf_counter()
            logs = trainer.step_on(next(loader))
            logs["sec_per_step"] = time.perf_counter() - t0
            if rank == 0:
                writer.writerow({"step": trainer.step, "lr": f"{tracker_lr(cfg, trainer.step - 1):.3g}",
                                 **{k: f"{v:.5g}" for k, v in logs.items()}})
                log_file.flush()
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix({k: f"{v:.3f}" for k, v in logs.items() if k != "sec_per_step"})
            if trainer.step % cfg.checkpoint_every == 0:
                trainer.save()
                if cfg.keep_checkpoints:  # states to choose from by held-out tracking, not by the loss
                    trainer.save(trainer.out / f"step-{trainer.step:06d}.pt")
                    trainer.save_average(trainer.out / f"step-{trainer.step:06d}-ema.pt")
    finally:
        trainer.save()
        if rank == 0:
            if trainer.step >= cfg.steps:
                trainer.save(trainer.out / "final.pt")
                trainer.save_average(trainer.out / "final-ema.pt")
            log_file.close()
            if bar is not None:
                bar.close()
    return trainer


@dataclass
class Stage:
    """A stage of a recipe, its config resolved; a plain config is a recipe of one stage."""

    plan: StagePlan
    cfg: TrainConfig

    @property
    def result(self) -> Path:
        """The state the next stage continues from (the weight average where the stage keeps one)."""
        out = Path(self.cfg.out)
        return out / "final-ema.pt" if self.cfg.ema_decay > 0 and self.plan.stop_at is None else out / "final.pt"

    @property
    def finished(self) -> bool:
        return (Path(self.cfg.out) / "final.pt").exists()


def load_recipe(path: str | Path, out: str | None = None) -> list[Stage]:
    """The stages of the config in `path` (export/train_stages.py): each stage's keys over the shared ones,
    its folder `<out>/NN-name`, its `init` the previous stage's final state. A config without stages is a
    recipe of one stage named ""; `out` replaces the config's output folder."""
    chain = config_chain(path)
    stages = next((own[STAGES] for _, own in reversed(chain) if STAGES in own), None)
    chain = [(file, {k: v for k, v in own.items() if k != STAGES}) for file, own in chain]
    if out is not None:
        chain.append(("--out", {"out": out}))
    if stages is None:
        return [Stage(StagePlan(1, "", {}), TrainConfig.from_chain(chain, path))]
    plans = plan_stages(stages, path, set(TrainConfig.__dataclass_fields__))
    out = TrainConfig.from_chain([*chain, (plans[0].label(path), plans[0].keys)], path).out
    recipe: list[Stage] = []
    for plan in plans:
        keys = {**plan.keys, "out": str(plan.folder(out))}
        if recipe:
            keys["init"] = str(recipe[-1].result)
        cfg = TrainConfig.from_chain([*chain, (plan.label(path), keys)], plan.label(path))
        if plan.stop_at is not None and plan.stop_at > cfg.steps:
            raise ValueError(f"{plan.label(path)}: 'stop_at' is {plan.stop_at}; expected <= its steps ({cfg.steps})")
        recipe.append(Stage(plan, cfg))
    return recipe


def run_recipe(recipe: list[Stage], max_steps: int | None = None, device: str = "cpu",
               max_minutes: float | None = None) -> tuple[Stage, Trainer | None]:
    """Each unfinished stage in order, within one budget of steps and minutes; (the stage it stopped in or
    the last, its trainer or None when every stage had finished before)."""
    deadline = time.monotonic() + 60 * max_minutes if max_minutes else math.inf
    trainer = None
    for before, stage in zip([None, *recipe], recipe, strict=False):
        if stage.finished:
            continue
        last = Path(stage.cfg.out) / "last.pt"
        if stage.plan.resume and not last.exists():  # go on with the previous stage's run: its step and optimiser
            last.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(Path(before.cfg.out) / "last.pt", last)
        end = stage.plan.stop_at or stage.cfg.steps
        minutes = None if deadline == math.inf else max(0.0, (deadline - time.monotonic()) / 60)
        trainer = run(stage.cfg, max_steps, device=device, max_minutes=minutes,
                      stop_at=stage.plan.stop_at)
        if max_steps is not None:
            max_steps -= trainer.step - trainer.start_step
        if trainer.step < end:
            return stage, trainer
        if stage.plan.stop_at is not None:  # the state the next stage continues from
            trainer.save(Path(stage.cfg.out) / "final.pt")
        if (max_steps is not None and max_steps <= 0) or time.monotonic() >= deadline:
            following = recipe[stage.plan.index:]
            return (following[0], None) if following else (stage, trainer)
    return recipe[-1], trainer


def replica_divergence(net: nn.Module) -> float:
    """Max-abs difference of every parameter from rank 0's copy (0.0 when DDP kept the replicas in sync)."""
    flat = torch.cat([p.detach().reshape(-1) for p in net.parameters()])
    ref = flat.clone()
    dist.broadcast(ref, src=0)
    diff = (flat - ref).abs().max()
    dist.all_reduce(diff, op=dist.ReduceOp.MAX)
    return float(diff)


def show_recipe(recipe: list[Stage]) -> str:
    """A staged recipe written out whole: every stage's keys, in a file that reads back to the same stages."""
    out = Path(recipe[0].cfg.out).parent
    parts = [format_toml({"out": str(out)})]
    for stage in recipe:
        own = {k: v for k, v in asdict(stage.cfg).items() if k != "out" and (k != "init" or stage.plan.index == 1)}
        values = {"name": stage.plan.name, "resume": stage.plan.resume, "stop_at": stage.plan.stop_at, **own}
        parts.append(f"# stage {stage.plan.index}: {stage.cfg.out}\n" + format_toml(values, "[[stages]]"))
    return "\n".join(parts)


def recipe_line(stage: Stage, trainer: Trainer | None, count: int) -> str:
    """Where a staged run stands: the stage it stopped in, or the final state to export."""
    if trainer is not None and trainer.step < (stage.plan.stop_at or stage.cfg.steps):
        return (f"stage {stage.plan.index}/{count} '{stage.plan.name}' stopped at step {trainer.step}/"
                f"{stage.cfg.steps}; resume with the same command (state in {Path(stage.cfg.out) / 'last.pt'})")
    if stage.plan.index < count or not stage.finished:
        return f"stopped before stage {stage.plan.index}/{count} '{stage.plan.name}'; resume with the same command"
    return f"all {count} stages done: export {stage.result} with dadiff-export"


def main_recipe(args: Any, recipe: list[Stage]) -> int:
    """`dadiff-train` on a staged config (one process): every stage in order, resumable."""
    if args.seed is not None:
        raise ValueError(f"{args.config}: --seed applies to a config without stages; each stage sets its own seed")
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise ValueError(f"{args.config}: a config in stages runs in one process (dadiff-train, not torchrun)")
    if args.show_config:
        print(show_recipe(recipe), end="")
        return 0
    stage, trainer = run_recipe(recipe, args.max_steps, args.device, args.max_minutes)
    print(f"dadiff-train: {recipe_line(stage, trainer, len(recipe))}")
    return 0


def main(argv: list[str] | argparse.Namespace | None = None) -> int:
    """dadiff-train; `argv` may be the arguments dadiff-train's launcher already parsed (notes print once)."""
    args = argv if isinstance(argv, argparse.Namespace) else build_parser().parse_args(argv)
    try:
        recipe = load_recipe(args.config, args.output)
        if recipe[0].plan.name:
            return main_recipe(args, recipe)
        cfg = recipe[0].cfg
        if args.seed is not None:
            cfg.seed = args.seed
        if args.show_config:
            print(format_toml(asdict(cfg)), end="")
            return 0
        trainer = run(cfg, args.max_steps, device=args.device, max_minutes=args.max_minutes)
    except SetupError as e:  # found as the run is set up: name the file that sets the key
        print(f"dadiff-train: error: {key_file(args.config, e.key)}: {e}", file=sys.stderr)
        return 2
    except (DadiffError, ValueError, CheckpointError) as e:
        print(f"dadiff-train: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # `out` on a read-only filesystem, a full disk, a data folder the user may not read
        print(f"dadiff-train: error: {os_error_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("dadiff-train: interrupted; resume with the same command", file=sys.stderr)
        return 130
    if trainer.world > 1:
        divergence = replica_divergence(trainer.net)
        if trainer.rank == 0:
            print(f"dadiff-train: {trainer.world} replicas, max parameter difference {divergence:.3g}")
        dist.destroy_process_group()
    if trainer.rank == 0:
        print(f"dadiff-train: {finish_line(trainer.step, cfg.steps, trainer.out, trainer.ema is not None)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
