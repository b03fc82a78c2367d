"""Reading released DaDiff checkpoints and our own, strictly and without executing pickled code.

Released files are {'epoch', 'state_dict', 'optimizer'} or a bare state_dict, possibly with `module.`
prefixes (DataParallel). Ours add the model config: {'dadiff_format': 1, 'config': {...}, 'state_dict'}.
Every failure is a CheckpointError whose message is one line naming the file and the problem.
"""

from __future__ import annotations

import pickle
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dadiff.runtime.errors import DadiffError
from dadiff.runtime.ort_cache import file_sha256

from .config import FAMILIES, GAT_FAMILY, ModelConfig, default_config, validate_config
from .network import DaDiffNet, build_model

FORMAT_VERSION = 1


class CheckpointError(DadiffError):
    """A checkpoint that cannot be used; str() is a one-line message for the user."""


@dataclass
class LoadedCheckpoint:
    model: DaDiffNet
    config: ModelConfig
    source: str          # "released" | "dadiff"
    sha256: str
    extra: dict[str, Any]


def _numpy_safe_globals() -> list[Any]:
    """Numpy scalars and dtypes that old pysot-style checkpoints pickle; data only, no code."""
    core = getattr(np, "_core", None) or np.core
    allowed: list[Any] = [core.multiarray.scalar, np.dtype]
    allowed += [type(np.dtype(t)) for t in ("float64", "float32", "int64", "int32", "bool")]
    return allowed


def stopped_run(path: Path) -> bool:
    """A run's final.pt that is missing because the run stopped early (--max-steps/--max-minutes leave last.pt
    only): "no such file" alone reads as a wrong path."""
    return path.name == "final.pt" and not path.exists() and (path.parent / "last.pt").is_file()


def read_checkpoint_file(path: str | Path) -> Any:
    """torch.load with weights_only=True; turns every failure into one clear line."""
    p = Path(path)
    if not p.exists():
        hint = " (the run has not finished: export its last.pt, or resume it)" if stopped_run(p) else ""
        raise CheckpointError(f"{p}: no such file{hint}")
    if p.is_dir():
        raise CheckpointError(f"{p}: is a folder, expected a checkpoint file (.pt/.pth)")
    if p.stat().st_size == 0:
        raise CheckpointError(f"{p}: empty file")
    try:
        with torch.serialization.safe_globals(_numpy_safe_globals()), warnings.catch_warnings():
            # torch warns of a pickle protocol it may not support: two lines before the refusal or a clean load
            warnings.filterwarnings("ignore", message="Detected pickle protocol", category=UserWarning)
            return torch.load(p, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        first = str(e).strip().splitlines()
        reason = next((ln.strip() for ln in first if "GLOBAL" in ln or "Unsupported" in ln), first[0] if first else "")
        if "weights only" in str(e).lower() or "GLOBAL" in str(e):
            raise CheckpointError(f"{p}: refused, the file pickles objects or code that weights-only loading "
                                  f"does not execute ({reason})") from None
        raise CheckpointError(f"{p}: not a PyTorch checkpoint ({reason})") from None
    except Exception as e:  # torch reports a damaged file through many exception types
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if "central directory" in msg or "zip archive" in msg or isinstance(e, EOFError):
            raise CheckpointError(f"{p}: truncated or corrupt checkpoint ({msg})") from None
        raise CheckpointError(f"{p}: not a PyTorch checkpoint ({msg})") from None


def _state_dict_of(obj: Any, path: Path) -> dict[str, torch.Tensor]:
    sd = obj.get("state_dict", obj) if isinstance(obj, dict) else None
    if not isinstance(sd, dict) or not sd or not all(isinstance(k, str) for k in sd):
        raise CheckpointError(f"{path}: no state_dict inside (expected a dict of tensors or a dict with 'state_dict')")
    tensors = {k: v for k, v in sd.items() if isinstance(v, torch.Tensor)}
    if not tensors:
        raise CheckpointError(f"{path}: the state_dict holds no tensors")
    if all(k.startswith("module.") for k in tensors):
        tensors = {k[len("module."):]: v for k, v in tensors.items()}
    return tensors


def detect_family(sd: dict[str, torch.Tensor]) -> str | None:
    """The family whose signature keys the state_dict has, or None."""
    if "backbone.layer1.0.conv1.weight" in sd and "diffusion.conv_in.weight" in sd:
        return "dadiff-ban-r50"
    if "backbone.Mixed_6e.branch1x1.conv.weight" in sd and "diffusion.conv_in.weight" in sd:
        return GAT_FAMILY
    if "backbone._conv_stem.weight" in sd and "diffusion.conv_in.weight" in sd:
        return "dadiff-lite" if "backbone._blocks.10._project_conv.weight" in sd else "dadiff-mobile"
    return None


def _describe_unknown(sd: dict[str, torch.Tensor]) -> str:
    if "backbone.Mixed_6e.branch1x1.conv.weight" in sd:
        return "it looks like a plain SiamGAT checkpoint without the DaDiff block (no diffusion.* keys)"
    if "backbone.layer1.0.conv1.weight" in sd and not any(k.startswith("diffusion.") for k in sd):
        return "it looks like a plain SiamBAN checkpoint without the DaDiff block (no diffusion.* keys)"
    return f"its keys match neither {' nor '.join(FAMILIES)} (first keys: {', '.join(list(sd)[:3])})"


def _names(keys: list[str], limit: int = 5) -> str:
    shown = ", ".join(keys[:limit])
    return shown + (f", … ({len(keys) - limit} more)" if len(keys) > limit else "")


def shape_mismatches(own: dict[str, torch.Tensor], sd: dict[str, torch.Tensor]) -> list[str]:
    """'key [its shape] vs model [the model's]' for every key both hold with different shapes."""
    return [f"{k} {list(sd[k].shape)} vs model {list(own[k].shape)}"
            for k in own if k in sd and sd[k].shape != own[k].shape]


def load_state_dict_strict(model: DaDiffNet, sd: dict[str, torch.Tensor], path: Path) -> None:
    """Like load_state_dict(strict=True) but lists every problem by name on one line."""
    own = model.state_dict()
    missing = [k for k in own if k not in sd]
    unexpected = [k for k in sd if k not in own]
    shapes = shape_mismatches(own, sd)
    problems = []
    if missing:
        problems.append(f"missing {len(missing)} key(s): {_names(missing)}")
    if unexpected:
        problems.append(f"unexpected {len(unexpected)} key(s): {_names(unexpected)}")
    if shapes:
        problems.append(f"shape mismatch in {len(shapes)} key(s): {_names(shapes, 3)}")
    if problems:
        raise CheckpointError(f"{path}: state_dict does not fit {model.cfg.family}: " + "; ".join(problems))
    model.load_state_dict(sd, strict=True)


def _check_format(version: Any, path: Path) -> None:
    """Our checkpoints say which layout they hold; a later one may mean its keys differently."""
    if type(version) is not int or version != FORMAT_VERSION:
        raise CheckpointError(f"{path}: 'dadiff_format' is {version!r}; this exporter reads format {FORMAT_VERSION}")


def check_finite(sd: dict[str, torch.Tensor], path: Path) -> None:
    """CheckpointError naming the first tensor holding NaN or inf (a diverged run or a damaged file): such
    weights give NaN outputs, which no parity tolerance catches."""
    for key, tensor in sd.items():
        if (tensor.is_floating_point() or tensor.is_complex()) and not bool(torch.isfinite(tensor).all()):
            bad = int((~torch.isfinite(tensor)).sum())
            raise CheckpointError(f"{path}: tensor '{key}' holds {bad} NaN or inf value(s) of {tensor.numel()}; "
                                  "the training diverged or the file is damaged")


def load_checkpoint(path: str | Path, family: str | None = None, steps: int | None = None,
                    preset: str | None = None) -> LoadedCheckpoint:
    """Build the right model for a checkpoint and load it strictly (eval mode)."""
    p = Path(path)
    obj = read_checkpoint_file(p)
    sd = _state_dict_of(obj, p)
    extra: dict[str, Any] = {}
    if isinstance(obj, dict) and isinstance(obj.get("config"), dict):
        _check_format(obj.get("dadiff_format"), p)
        try:
            cfg = ModelConfig.from_dict(obj["config"])
        except (TypeError, ValueError, KeyError) as e:
            raise CheckpointError(f"{p}: invalid model config ({e})") from None
        source = "dadiff"
        extra = {k: v for k, v in obj.items() if k in ("step", "epoch", "train_config")}
    else:
        detected = detect_family(sd)
        if detected is None:
            raise CheckpointError(f"{p}: unrecognised model: {_describe_unknown(sd)}")
        cfg = default_config(detected)
        source = "released" if detected in ("dadiff-ban-r50", GAT_FAMILY) else "dadiff"
    if family is not None and family != cfg.family:
        raise CheckpointError(f"{p}: holds a {cfg.family} model, not {family}")
    if steps is not None and steps != cfg.ddim_steps:
        cfg = cfg.with_steps(steps)
    if preset is not None:
        if preset not in cfg.tracker.hp_presets:
            raise CheckpointError(f"{p}: unknown preset {preset!r}; known: {', '.join(sorted(cfg.tracker.hp_presets))}")
        cfg = replace(cfg, tracker=replace(cfg.tracker, default_preset=preset))
    try:
        validate_config(cfg)
        model = build_model(cfg)
    except (TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{p}: invalid model config: {e}") from None
    load_state_dict_strict(model, sd, p)
    check_finite(sd, p)
    model.eval()
    return LoadedCheckpoint(model, cfg, source, file_sha256(p), extra)


def save_checkpoint(path: str | Path, model: DaDiffNet, **extra: Any) -> None:
    """Our format: config + state_dict (+ optimiser state, step, ... for resuming training)."""
    payload = {"dadiff_format": FORMAT_VERSION, "config": model.cfg.to_dict(), "state_dict": model.state_dict()}
    payload.update(extra)
    tmp = Path(f"{path}.tmp")
    torch.save(payload, tmp)
    tmp.replace(path)
