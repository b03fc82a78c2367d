"""Tracker settings read from model metadata (docs/model-format.md), presets and user overrides.

Every number the tracker uses comes from here, so a model carries its own geometry and defaults. The
lost/found thresholds are optional metadata keys; their runtime defaults live in `LOST_DEFAULTS` only.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields

from .errors import InputError, ModelError

FORMAT_VERSION = "1"
HP_KEYS = ("lr", "penalty_k", "window_influence")
GEOMETRY_KEYS = (
    "exemplar_size",
    "instance_size",
    "stride",
    "score_size",
    "point_origin",
    "context_amount",
    "min_size",
)
REQUIRED_KEYS = ("dadiff_format", *GEOMETRY_KEYS, *HP_KEYS)


@dataclass(frozen=True)
class Geometry:
    """Crop sizes and score-map layout of one model."""

    exemplar_size: int
    instance_size: int
    stride: float
    score_size: int
    point_origin: float
    context_amount: float
    min_size: float
    channel_order: str = "BGR"
    decoder: str = "siamban"  # "siamgat": runtime/decode_gat.py, with region_s / region_l
    region_s: float = 0.1
    region_l: float = 0.44


@dataclass(frozen=True)
class Params:
    """Tunable tracking parameters: released hyper-parameters plus lost/found and plausibility settings.

    `uncertain_score`, `track_score`: the state is decided on a smoothed confidence with hysteresis: it
    enters 'tracking' at `track_score` or above and leaves it below `uncertain_score`, so a score hovering
    near one threshold does not flip the state at frame rate. These two only label frames: what the tracker
    does does not depend on them, so they can be set for what a follow controller should be told.
    `score_smoothing`: weight of the newest frame in that confidence (an EMA; 1 = no smoothing).
    `lost_score`, `lost_frames`: that many consecutive raw scores below `lost_score` make the state 'lost'
    (a single one is never 'tracking'); a raw score of `found_score` or more ends the streak, and ends
    'lost' (the target is found again: the box moves again). `lost_score=0` is the released tracker
    exactly: no lost state, no smoothing, no size bounds.
    `search_growth`, `search_growth_max`: while lost, the search region grows by this factor per frame,
    up to this multiple of its normal size.
    `max_scale_step`: width and height each change by at most this factor per frame.
    `max_scale_change`, `max_aspect_change`: the box's sqrt(area) and its w/h aspect stay within this factor
    of the initial box's; a frame whose box these limits hold back is never 'tracking'.
    `max_frame_cover`: a box covering more than this share of the frame is implausible, never 'tracking'.
    `motion_compensation`: above 0, the search region moves with the whole picture's jolts (runtime/motion.py:
    a gust, a quick yaw; not its steady flow) wherever the phase-correlation peak of two consecutive frames
    reaches this value; 0 turns it off, and the released tracker (`lost_score=0`) ignores it.
    `still_frames`, `still_travel`: a box that has moved on the ground and then stays within `still_travel`
    of its size against the ground around it for `still_frames` frames is 'uncertain', never 'tracking'
    (runtime/still.py: the lock on a post or a lamp a follow controller must not chase); `still_frames=0`
    turns it off, and the released tracker ignores it.
    `swap_frames`, `swap_distance`: a box whose colours (hue and saturation of its upper and lower half) have
    stayed further than `swap_distance` from the start box's, as the median over `swap_frames` frames, is
    'uncertain', never 'tracking' (runtime/swap.py: the lock on another walker after a crossing);
    `swap_frames=0` turns it off, and the released tracker ignores it.
    `colour_prior`: above 0, each cell's score is weighted by (1 − colour_prior) + colour_prior · how much the
    colours around it are the start box's rather than its surroundings' when the cell is picked
    (runtime/colour_prior.py: against a look-alike at a crossing); 0 turns it off, and the released tracker
    and SiamGAT's decoder ignore it.
    """

    lr: float
    penalty_k: float
    window_influence: float
    uncertain_score: float = 0.85
    found_score: float = 0.5
    lost_score: float = 0.25
    lost_frames: int = 3
    search_growth: float = 1.25
    search_growth_max: float = 2.5
    track_score: float = 0.9
    score_smoothing: float = 0.2
    max_scale_step: float = 1.1
    max_scale_change: float = 8.0
    max_aspect_change: float = 4.0
    max_frame_cover: float = 0.5
    motion_compensation: float = 0.2
    still_frames: int = 30
    still_travel: float = 0.15
    swap_frames: int = 9
    swap_distance: float = 0.6
    colour_prior: float = 0.0

    @property
    def released(self) -> bool:
        """`lost_score=0`: the released tracker's behaviour exactly (every runtime addition off)."""
        return self.lost_score == 0


INTEGER_KEYS = tuple(f.name for f in fields(Params) if f.type in (int, "int"))  # counts, read as integers
LOST_KEYS = tuple(f.name for f in fields(Params) if f.name not in HP_KEYS)
TUNABLE_KEYS = (*HP_KEYS, *LOST_KEYS)
LOST_DEFAULTS = {k: getattr(Params(0.0, 0.0, 0.0), k) for k in LOST_KEYS}

# (low, high) inclusive bounds; None = unbounded. Growth and size factors have an upper bound too, so that
# a search region never grows past what the crop arithmetic holds (1e308 overflows it).
_BOUNDS: dict[str, tuple[float | None, float | None]] = {
    "lr": (0.0, 1.0),
    "penalty_k": (0.0, 100.0),  # released 0.04-0.2; exp(-k·change) underflows to 0 everywhere far above
    "window_influence": (0.0, 1.0),
    "uncertain_score": (0.0, 1.0),
    "found_score": (0.0, 1.0),
    "lost_score": (0.0, 1.0),
    "lost_frames": (1, 1_000_000),
    "search_growth": (1.0, 10.0),
    "search_growth_max": (1.0, 100.0),
    "track_score": (0.0, 1.0),
    "score_smoothing": (0.01, 1.0),
    "max_scale_step": (1.0, 10.0),
    "max_scale_change": (1.0, 1000.0),
    "max_aspect_change": (1.0, 1000.0),
    "max_frame_cover": (0.01, 1.0),
    "motion_compensation": (0.0, 1.0),
    "still_frames": (0, 1000),  # 16 KB of ring per frame kept: 1000 frames is 16 MB
    "still_travel": (0.0, 100.0),
    "swap_frames": (0, 1000),
    "swap_distance": (0.0, 1.0),
    "colour_prior": (0.0, 1.0),
}


def _as_number(raw: object, integer: bool) -> float | int | None:
    """Parse a metadata/override value; None when it is not a finite number (or not integral)."""
    if isinstance(raw, bool):  # True is 1.0 to float(): a setting given as a flag is a mistake, not 1
        return None
    try:
        value = float(raw)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int of 400 digits
        return None
    if not math.isfinite(value):
        return None
    if integer:
        return int(value) if value.is_integer() else None
    return value


def _meta_number(meta: Mapping[str, str], key: str, source: str, integer: bool = False) -> float | int:
    if key not in meta:
        raise ModelError(f"{source}: metadata key '{key}' is missing")
    value = _as_number(meta[key], integer)
    if value is None:
        kind = "an integer" if integer else "a number"
        raise ModelError(f"{source}: metadata key '{key}' is {meta[key]!r}, expected {kind}")
    return value


# Far past any model's values (released: 127 / 255 px crops, context 0.5, floor 10 px) and far below the sizes
# that overflow the crop arithmetic (a 1e308 floor or context makes every window infinite).
GEOMETRY_LIMITS = {"exemplar_size": 4096, "instance_size": 4096, "score_size": 4096, "context_amount": 10.0,
                    "min_size": 1000.0}


def parse_geometry(meta: Mapping[str, str], source: str) -> Geometry:
    """Read and sanity-check the geometry keys; `source` names the file in error messages."""
    if "dadiff_format" not in meta:
        raise ModelError(
            f"{source}: metadata key 'dadiff_format' is missing "
            "(not a dadiff model; write it with dadiff-export)"
        )
    if str(meta["dadiff_format"]).strip() != FORMAT_VERSION:
        raise ModelError(
            f"{source}: metadata key 'dadiff_format' is {meta['dadiff_format']!r}; "
            f"this runtime reads format {FORMAT_VERSION}"
        )
    ints = {"exemplar_size", "instance_size", "score_size"}
    values = {k: _meta_number(meta, k, source, integer=k in ints) for k in GEOMETRY_KEYS}
    for key in ("exemplar_size", "instance_size", "score_size", "stride"):
        if values[key] <= 0:
            raise ModelError(f"{source}: metadata key '{key}' must be positive, got {meta[key]!r}")
    for key in ("context_amount", "min_size"):
        if values[key] < 0:
            raise ModelError(f"{source}: metadata key '{key}' must not be negative, got {meta[key]!r}")
    for key, most in GEOMETRY_LIMITS.items():
        if values[key] > most:
            raise ModelError(f"{source}: metadata key '{key}' is {meta[key]!r}, expected at most {most:g}")
    for key in ("stride", "point_origin"):  # a grid larger than its own search crop cannot be this model's
        if abs(values[key]) > values["instance_size"]:
            raise ModelError(f"{source}: metadata key '{key}' is {meta[key]!r}, larger than the "
                             f"{values['instance_size']} px search crop")
    order = str(meta.get("channel_order", "BGR")).strip().upper()
    if order not in ("BGR", "RGB"):
        raise ModelError(
            f"{source}: metadata key 'channel_order' is {meta['channel_order']!r}, expected BGR or RGB"
        )
    pixel_range = str(meta.get("pixel_range", "0-255")).replace(" ", "")
    if pixel_range != "0-255":
        raise ModelError(
            f"{source}: metadata key 'pixel_range' is {meta['pixel_range']!r}; this runtime feeds 0-255"
        )
    return Geometry(channel_order=order, **values, **_decoder(meta, source))  # type: ignore[arg-type]


DECODERS = ("siamban", "siamgat")


def _decoder(meta: Mapping[str, str], source: str) -> dict[str, object]:
    """The post-processing a model's outputs need (`decoder`, absent = siamban) and SiamGAT's region bounds."""
    decoder = str(meta.get("decoder", "siamban")).strip()
    if decoder not in DECODERS:
        raise ModelError(f"{source}: metadata key 'decoder' is {meta['decoder']!r}, expected one of "
                         f"{', '.join(DECODERS)}")
    if decoder == "siamban":
        return {"decoder": decoder}
    if not float(meta["stride"]).is_integer():  # its upsampled map has one point per crop pixel
        raise ModelError(f"{source}: metadata key 'stride' is {meta['stride']!r}; the siamgat decoder needs an integer")
    region = {k: _meta_number(meta, k, source) for k in ("region_s", "region_l")}
    if not 0 < region["region_s"] <= region["region_l"] <= 1:
        raise ModelError(f"{source}: metadata keys 'region_s' {meta['region_s']!r} and 'region_l' "
                         f"{meta['region_l']!r} must satisfy 0 < region_s <= region_l <= 1")
    return {"decoder": decoder, **region}


def presets(meta: Mapping[str, str], source: str) -> dict[str, dict[str, float]]:
    """Named presets from the JSON `hp_presets` key ({} when the model has none)."""
    raw = meta.get("hp_presets")
    if raw is None or not str(raw).strip():
        return {}
    try:
        table = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise ModelError(f"{source}: metadata key 'hp_presets' is not valid JSON ({exc.msg})") from None
    except RecursionError:  # json recurses once per nesting level
        raise ModelError(f"{source}: metadata key 'hp_presets' is not valid JSON (nested too deeply)") from None
    if not isinstance(table, dict) or not all(isinstance(v, dict) for v in table.values()):
        raise ModelError(f"{source}: metadata key 'hp_presets' must map preset names to objects")
    return table


def _apply(
    values: dict[str, float | int],
    updates: Mapping[str, object],
    fail: Callable[[str], Exception],
    what: str,
    strict: bool,
) -> None:
    """Merge `updates` into `values`, parsing and bound-checking each tunable key."""
    for key, raw in updates.items():
        if key not in TUNABLE_KEYS:
            if strict:
                raise fail(f"unknown {what} '{key}' (known: {', '.join(TUNABLE_KEYS)})")
            continue
        integer = key in INTEGER_KEYS
        value = _as_number(raw, integer)
        if value is None:
            kind = "an integer" if integer else "a number"
            raise fail(f"{what} '{key}' is {raw!r}, expected {kind}")
        low, high = _BOUNDS[key]
        if (low is not None and value < low) or (high is not None and value > high):
            span = f"[{low}, {high}]" if high is not None else f">= {low}"
            shown = value if abs(value) < 1e15 else f"{value:.6g}"  # 1e300 as an int has 301 digits
            raise fail(f"{what} '{key}' is {shown}, expected {span}")
        values[key] = value


def resolve_params(
    meta: Mapping[str, str],
    source: str,
    preset: str | None = None,
    overrides: Mapping[str, object] | None = None,
) -> Params:
    """Metadata values (or runtime defaults), then the named preset, then the overrides, in that order."""
    for key in HP_KEYS:
        if key not in meta:
            raise ModelError(f"{source}: metadata key '{key}' is missing")
    values: dict[str, float | int] = dict(LOST_DEFAULTS)
    _apply(
        values,
        {k: meta[k] for k in TUNABLE_KEYS if k in meta},
        lambda m: ModelError(f"{source}: {m}"),
        "metadata key",
        strict=True,
    )
    if preset is not None:
        table = presets(meta, source)
        if preset not in table:
            known = ", ".join(sorted(table)) or "none"
            raise InputError(f"unknown preset '{preset}' (this model has: {known})")
        _apply(
            values,
            table[preset],
            lambda m: ModelError(f"{source}: preset '{preset}': {m}"),
            "key",
            strict=False,
        )
    if overrides:
        if not isinstance(overrides, Mapping):  # "lr=1" or [("lr", 1)] has no .items()
            raise InputError(f"overrides must be a mapping of setting to value, got {type(overrides).__name__}")
        _apply(values, overrides, InputError, "override", strict=True)
    return Params(**values)  # type: ignore[arg-type]


def check_metadata(meta: Mapping[str, str], source: str) -> None:
    """Raise ModelError naming `source` and the key when the metadata cannot drive the tracker."""
    parse_geometry(meta, source)
    resolve_params(meta, source)
    for name in presets(meta, source):
        resolve_params(meta, source, preset=name)
