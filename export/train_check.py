"""Type and range checks of a `dadiff-train` config, before any training (and without torch).

Every key is checked against the type of its default in TrainConfig, so `steps = "3"` or `day = "scenes"`
is one line naming the file and the key instead of a traceback minutes into a run.
"""

from __future__ import annotations

import difflib
import math
import os
from dataclasses import fields
from pathlib import Path
from typing import Any

from dadiff.runtime.datamaking.camera_night import MODEL as CAMERA_NIGHT
from dadiff.runtime.datamaking.night import NIGHT_STYLES
from dadiff.runtime.errors import DadiffError

from .config import FAMILIES, GAT_FAMILY, ModelConfig, default_config, validate_config, with_overrides
from .train_cli import SEED_MAX

# The keys of each day data kind (export/train_data.py make_day_source reads them) and what each takes;
# `kind` aside, all optional but `root` (ROOT_KINDS: the folder to read).
_SCENE_KEYS = {"kind": "a string", "split": "a string", "pairs": "an integer", "source": "a string",
               "companions": "a number", "stretch": "a number", "cutouts": "a string"}
_SEQUENCE_KEYS = {"kind": "a string", "root": "a string", "match": "a string", "far": "a number",
                  "one_night": "true or false"}
DAY_KEYS: dict[str, dict[str, str]] = {"scenes": _SCENE_KEYS, "got10k": _SEQUENCE_KEYS, "otb": _SEQUENCE_KEYS,
                                       "sequences": _SEQUENCE_KEYS, "images": {"kind": "a string", "root": "a string"}}
DAY_KINDS = tuple(DAY_KEYS)
ROOT_KINDS = ("got10k", "otb", "sequences", "images")
SOURCE_SHARES = ("companions", "stretch", "far")  # shares 0-1 of a source's scenes or pairs
LIBRARY_ONLY = ("companions", "stretch", "cutouts")  # scene options that only library scenes have
SCENE_SOURCES = ("skimage", "library")


class SetupError(DadiffError, ValueError):
    """A config key whose value fails only as the run is set up (a path, the network's parameter names):
    `key` lets dadiff-train name the config file that sets it."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


def resolved(path: str) -> str:
    """`path` as the run reads it: relative paths are taken from the working folder, not the config's, which
    a user running from elsewhere cannot tell from the path alone."""
    full = Path(path).expanduser()
    if full.is_absolute():
        return os.path.normpath(full)
    return f"{os.path.abspath(full)}; a relative path is taken from the working folder, {Path.cwd()}"


# (low, inclusive) per numeric key; keys not listed only need the right type.
MINIMUM: dict[str, tuple[float, bool]] = {
    "steps": (1, True), "batch_size": (2, True), "workers": (0, True), "warmup_steps": (0, True),
    "checkpoint_every": (1, True), "freeze_backbone_blocks": (0, True), "lr": (0, False),
    "backbone_lr_mult": (0, True), "dadiff_lr_mult": (0, True),
    "weight_decay": (0, True),
    "disc_lr": (0, False), "disc_poly_power": (0, True),
    "lambda_trc": (0, True), "lambda_loc": (0, True), "lambda_adv": (0, True), "lambda_align": (0, True),
    "grad_clip": (0, False), "search_scale": (0, True), "search_shift": (0, True),
    "lambda_distill": (0, True), "lambda_feature": (0, True), "lambda_night_trc": (0, True),
    "lambda_night_distill": (0, True), "night_path_lamps": (0, True), "negative_pairs": (0, True),
    "lambda_side": (0, True), "ema_decay": (0, True), "seed": (0, True),
}
MAXIMUM: dict[str, tuple[float, bool]] = {  # (high, inclusive), as MINIMUM
    "night_path_lamps": (1.0, True), "negative_pairs": (1.0, True), "search_scale": (1.0, True),
    "ema_decay": (1.0, False), "search_shift": (128.0, True), "seed": (SEED_MAX, True),
}
TRAIN_FAMILIES = tuple(f for f in FAMILIES if f != GAT_FAMILY)  # dadiff-gat-googlenet: export and tracking only
CHOICES: dict[str, tuple[str, ...]] = {"stage": ("baseline", "dadiff"), "family": TRAIN_FAMILIES,
                                       "optimizer": ("sgd", "adamw"), "align_target": ("eps", "chain", "restore"),
                                       "loc_region": ("ellipse", "box"), "night_pairs": ("frame", "scene")}
# night styles: the generator's, and the independent camera model (camera_night.py) as a training night too
TRAIN_NIGHT_STYLES = (*NIGHT_STYLES, CAMERA_NIGHT)
ITEM_CHOICES: dict[str, tuple[str, ...]] = {"night_styles": TRAIN_NIGHT_STYLES}  # lists of strings
KINDS: dict[str, str] = {"train_only": "a list of names"}  # where the default (empty) does not tell


def _kind(default: Any) -> str:
    if isinstance(default, bool):
        return "true or false"
    if isinstance(default, int):
        return "an integer"
    if isinstance(default, float):
        return "a number"
    if isinstance(default, dict):
        return "a table"
    if isinstance(default, list):
        return "a list of strings" if default and isinstance(default[0], str) else "a list of tables"
    return "a string"  # str, or None for optional paths (TOML has no null)


def _fits(value: Any, kind: str) -> bool:
    if kind == "true or false":
        return isinstance(value, bool)
    if kind == "an integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if kind == "a number":
        return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if kind == "a table":
        return isinstance(value, dict)
    if kind == "a list of strings":
        return isinstance(value, list) and bool(value) and all(isinstance(v, str) for v in value)
    if kind == "a list of names":  # may be empty
        return isinstance(value, list) and all(isinstance(v, str) for v in value)
    if kind == "a list of tables":
        return isinstance(value, list) and all(isinstance(v, dict) for v in value)
    return isinstance(value, str)


def _bound(limit: float) -> str:
    return str(limit) if isinstance(limit, int) else f"{limit:g}"  # SEED_MAX in full, not 4.29497e+09


def _check_day(sources: list[dict[str, Any]]) -> None:
    """At least one known day source: an empty list or a misspelt kind is refused here, not once training runs."""
    if not sources:
        raise ValueError("'day' is []; expected at least one day source (e.g. [{kind = \"scenes\"}])")
    for i, source in enumerate(sources, 1):
        kind = source.get("kind")
        if not isinstance(kind, str):
            raise ValueError(f"'day' entry {i} has no 'kind' (e.g. {{kind = \"scenes\"}})")
        if kind not in DAY_KINDS:
            raise ValueError(f"'day' entry {i} has kind {kind!r}; expected one of {', '.join(DAY_KINDS)}")
        if kind in ROOT_KINDS and not isinstance(source.get("root"), str):
            raise ValueError(f"'day' entry {i} (kind {kind!r}) has no 'root' (the folder to read)")
        _check_source(f"'day' entry {i} (kind {kind!r})", kind, source)


def _unknown_source_key(key: str, value: Any, kind: str) -> str:
    """`key = value`, and the key it is likely a misspelling of, or the kinds it belongs to."""
    close = difflib.get_close_matches(key, DAY_KEYS[kind], n=1)
    others = [k for k, keys in DAY_KEYS.items() if key in keys]
    hint = f" (did you mean {close[0]!r}?)" if close else f" (a key of {', '.join(others)} sources)" if others else ""
    return f"{key} = {value!r}{hint}"


def _check_source(where: str, kind: str, source: dict[str, Any]) -> None:
    """Each key of one day source: a misspelt option (`strech`) or a sequence option on scenes is refused, not
    dropped silently, and a bad value is named with the file's name here, not as the run starts."""
    keys = DAY_KEYS[kind]
    unknown = [_unknown_source_key(k, v, kind) for k, v in source.items() if k not in keys]
    if unknown:
        raise ValueError(f"{where} has unknown keys: {', '.join(unknown)}; kind {kind!r} takes "
                         f"{', '.join(keys)}")
    for key, value in source.items():
        if not _fits(value, keys[key]):
            raise ValueError(f"{where}: '{key}' is {value!r}; expected {keys[key]}")
        if key in SOURCE_SHARES and not 0 <= value <= 1:
            raise ValueError(f"{where}: '{key}' is {value!r}; expected a share from 0 to 1")
    if source.get("pairs", 1) < 1:
        raise ValueError(f"{where}: 'pairs' is {source['pairs']!r}; expected >= 1 (pairs drawn from each scene)")
    if source.get("split", "train") != "train":
        raise ValueError(f"{where}: 'split' is {source['split']!r}; expected \"train\" (the test split is held "
                         f"out: the evaluation scores trackers on it)")
    scenes = source.get("source", "skimage")
    if kind == "scenes" and scenes not in SCENE_SOURCES:
        raise ValueError(f"{where}: 'source' is {scenes!r}; expected one of {', '.join(SCENE_SOURCES)}")
    for key in LIBRARY_ONLY if kind == "scenes" and scenes != "library" else ():
        if key in source and (key == "cutouts" or source[key]):  # a share of 0 asks for nothing
            raise ValueError(f"{where}: '{key}' is {source[key]!r}, which applies to library scenes only; add "
                             f"source = \"library\" or drop '{key}'")


def _check_range(key: str, value: Any) -> None:
    if key in MINIMUM:
        low, inclusive = MINIMUM[key]
        if value < low or (not inclusive and value == low):
            raise ValueError(f"'{key}' is {value!r}; expected {'>=' if inclusive else '>'} {_bound(low)}")
    if key in MAXIMUM:
        high, inclusive = MAXIMUM[key]
        if value > high or (not inclusive and value == high):
            raise ValueError(f"'{key}' is {value!r}; expected {'<=' if inclusive else '<'} {_bound(high)}")
    if key in CHOICES and value not in CHOICES[key]:
        raise ValueError(f"'{key}' is {value!r}; expected one of {', '.join(CHOICES[key])}")
    for item in value if key in ITEM_CHOICES else ():
        if item not in ITEM_CHOICES[key]:
            raise ValueError(f"'{key}' has {item!r}; expected items from {', '.join(ITEM_CHOICES[key])}")


def _check_model(values: dict[str, Any]) -> None:
    """`model = {...}` overrides: known ModelConfig keys whose result the exporter would accept."""
    overrides = values.get("model") or {}
    known = {f.name for f in fields(ModelConfig)} - {"family", "tracker"}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"'model' has unknown keys {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    family = values.get("family", "dadiff-lite")
    try:
        validate_config(with_overrides(default_config(family), overrides))
    except (TypeError, ValueError) as e:
        raise ValueError(f"'model': {e}") from None


def check_train_values(defaults: Any, values: dict[str, Any], path: str | Path) -> None:
    """ValueError `<path>: '<key>' is <value>; expected ...` for the first bad key of `values`."""
    try:
        for key, value in values.items():
            kind = KINDS.get(key) or _kind(getattr(defaults, key))
            if not _fits(value, kind):
                raise ValueError(f"'{key}' is {value!r}; expected {kind}")
            _check_range(key, value)
        if "day" in values:
            _check_day(values["day"])
        _check_model(values)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
