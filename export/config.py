"""Model and tracker configuration for the model families (`FAMILIES`), stored inside our own checkpoints."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

FAMILIES = ("dadiff-ban-r50", "dadiff-gat-googlenet", "dadiff-lite", "dadiff-mobile")
GAT_FAMILY, GAT_BACKBONE = "dadiff-gat-googlenet", "inception-v3-ou"
# EfficientNet-Lite0 trunks: the backbone name -> (last block, first dilated block or None, output blocks).
LITE0_TRUNKS: dict[str, tuple[int, int | None, tuple[int, ...]]] = {
    "efficientnet-lite0": (10, 5, (7, 10)),      # stride 8 (atrous from block 5), blocks 7 + 10 fused
    "efficientnet-lite0-s16": (6, None, (6,)),   # stride 16, stops in stage 3 (80 channels)
}
# Output stride of each trunk: stem 2 x each subsampling block (tests/test_export_bad_input.py checks the Lite0
# ones against the trunks). The tracker's stride is this; another one decodes boxes wrongly.
BACKBONE_STRIDES = {"resnet50-atrous": 8, GAT_BACKBONE: 8, "efficientnet-lite0": 8, "efficientnet-lite0-s16": 16}

# [lr, penalty_k, window_influence] of the released test script (spec 8.4).
HP_PRESETS: dict[str, dict[str, float]] = {
    "UAVDark70": {"lr": 0.473, "penalty_k": 0.088, "window_influence": 0.401},
    "NUT_L": {"lr": 0.473, "penalty_k": 0.088, "window_influence": 0.403},
    "NAT": {"lr": 0.45, "penalty_k": 0.14, "window_influence": 0.30},
    "NAT_L": {"lr": 0.466, "penalty_k": 0.083, "window_influence": 0.404},
}
# DaDiff-GAT's [lr, penalty_k, window_influence] (`HP_SEARCH` of its config.py; the test script defaults to NUT_L).
GAT_HP_PRESETS: dict[str, dict[str, float]] = {
    name: {"lr": lr, "penalty_k": k, "window_influence": wi} for name, (lr, k, wi) in {
        "NUT_L": (0.24, 0.04, 0.04), "UAVDark70": (0.35, 0.05, 0.18), "NAT": (0.24, 0.04, 0.04),
        "OTB100": (0.28, 0.16, 0.4), "GOT_10k": (0.7, 0.02, 0.35), "LaSOT": (0.35, 0.05, 0.18),
        "UAV123": (0.24, 0.04, 0.04)}.items()
}


@dataclass(frozen=True)
class TrackerConfig:
    """Crop geometry and decoding constants the runtime reads from the exported metadata."""

    exemplar_size: int = 127
    instance_size: int = 255
    stride: int = 8
    score_size: int = 25
    context_amount: float = 0.5
    min_size: float = 10.0
    hp_presets: dict[str, dict[str, float]] = field(default_factory=lambda: dict(HP_PRESETS))
    default_preset: str = "UAVDark70"
    decoder: str = "siamban"           # "siamgat": the SiamGAT/SiamCAR post-processing (runtime/decode_gat.py)
    origin: int | None = None          # point (0, 0) when the grid is not centred on the crop (SiamGAT: -98)
    region_s: float = 0.1              # siamgat: the fine stage's region, as a share of exemplar_size, at least
    region_l: float = 0.44             # ... and at most

    @property
    def point_origin(self) -> int:
        return -(self.score_size // 2) * self.stride if self.origin is None else self.origin


@dataclass(frozen=True)
class ModelConfig:
    family: str
    backbone: str                      # "resnet50-atrous" | a key of LITE0_TRUNKS
    level_names: tuple[int, ...]       # key suffixes of the neck and head levels
    backbone_channels: tuple[int, ...]  # channels entering the neck, per level
    channels: int                      # neck output width C
    template_feature_size: int         # template map side after the neck's centre crop
    search_feature_size: int
    head_hidden: int
    denoiser_ch: int
    denoiser_res_blocks: int
    denoiser_attention: bool
    denoiser_groups: int
    diffusion_total_steps: int = 20
    ddim_steps: int = 2
    ddim_start_t: int | None = 1       # noise level of the start state; None = the first visited timestep
    align: str = "released"            # "released" (LN(x + pos)) | "paper" (eq. 7) | "none" (ablation)
    use_dadiff: bool = True            # False: the baseline tracker, neck features go straight to the head
    align_residual: bool = False       # True: the head gets N_f + s * TL(X_0), s per channel from 0 (ours)
    align_heads: int = 8
    align_ffn: int = 2048
    head_search_padding: int = 0       # padding of the head's search-side 3x3 convs (keeps a small map's size)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["level_names"] = list(self.level_names)
        d["backbone_channels"] = list(self.backbone_channels)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        d = without_retired(d)
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown model config keys: {', '.join(unknown)}")
        if "tracker" not in d:  # guessing the crop geometry would export a model that decodes boxes wrongly
            raise ValueError("'tracker' is missing (the crop geometry: exemplar_size, instance_size, stride, ...)")
        raw_tracker = d.pop("tracker")
        if not isinstance(raw_tracker, dict):
            raise ValueError(f"'tracker' must be a table, got {raw_tracker!r}")
        unknown = sorted(set(raw_tracker) - {f.name for f in fields(TrackerConfig)})
        if unknown:
            raise ValueError(f"unknown tracker config keys: {', '.join(unknown)}")
        tracker = TrackerConfig(**raw_tracker)
        d["level_names"] = tuple(d["level_names"])
        d["backbone_channels"] = tuple(d["backbone_channels"])
        return cls(tracker=tracker, **d)

    def with_steps(self, steps: int) -> ModelConfig:
        return replace(self, ddim_steps=steps)


def ban_r50_config() -> ModelConfig:
    """The released DaDiff-BAN: SiamBAN r50_l234 with the DaDiff block (spec 2-5)."""
    return ModelConfig(
        family="dadiff-ban-r50", backbone="resnet50-atrous", level_names=(2, 3, 4),
        backbone_channels=(512, 1024, 2048), channels=256, template_feature_size=7, search_feature_size=31,
        head_hidden=256, denoiser_ch=256, denoiser_res_blocks=2, denoiser_attention=True, denoiser_groups=32,
        ddim_steps=2, ddim_start_t=1, align="released", align_heads=8, align_ffn=2048,
    )


def gat_googlenet_config() -> ModelConfig:
    """The released DaDiff-GAT: SiamGAT (Inception-v3 to Mixed_6e, Graph Attention Union, CAR head) with the DaDiff
    block. Search crop 287 -> 25 x 25 map whose cell (i, j) sits at 8j - 98 crop pixels from the centre (the
    release's offset 45 minus its centre 143); the released clip has no minimum size."""
    return ModelConfig(
        family=GAT_FAMILY, backbone=GAT_BACKBONE, level_names=(0,), backbone_channels=(768,), channels=256,
        template_feature_size=13, search_feature_size=25, head_hidden=256, denoiser_ch=256, denoiser_res_blocks=2,
        denoiser_attention=True, denoiser_groups=32, ddim_steps=2, ddim_start_t=1, align="released",
        tracker=TrackerConfig(instance_size=287, min_size=0.0, hp_presets=dict(GAT_HP_PRESETS),
                              default_preset="NUT_L", decoder="siamgat", origin=45 - (287 - 1) // 2),
    )


def lite_config() -> ModelConfig:
    """Our onboard model: EfficientNet-Lite0 (blocks 7 and 10 fused, stride 8), small denoiser, paper layer."""
    return ModelConfig(
        family="dadiff-lite", backbone="efficientnet-lite0", level_names=(0,), backbone_channels=(192,),
        channels=64, template_feature_size=8, search_feature_size=32, head_hidden=64,
        denoiser_ch=32, denoiser_res_blocks=1, denoiser_attention=False, denoiser_groups=8,
        ddim_steps=2, ddim_start_t=None, align="paper", align_heads=4, align_ffn=256,
    )


def mobile_config() -> ModelConfig:
    """NanoTrack-class cost: Lite0 to block 6 at stride 16, a one-block denoiser, two DDIM steps.

    Template 127 -> 8x8 map, centre 6x6 -> 4x4 head kernel; search 255 -> 16x16 map (padded head convs keep
    it) -> 13x13 score map, centred on the crop (see docs/model-format.md). 0.47 GFLOP per search frame.
    """
    return ModelConfig(
        family="dadiff-mobile", backbone="efficientnet-lite0-s16", level_names=(0,), backbone_channels=(80,),
        channels=48, template_feature_size=6, search_feature_size=16, head_hidden=48,
        denoiser_ch=16, denoiser_res_blocks=1, denoiser_attention=False, denoiser_groups=4,
        ddim_steps=2, ddim_start_t=None, align="paper", align_heads=4, align_ffn=96, head_search_padding=1,
        tracker=TrackerConfig(stride=16, score_size=13),
    )


_INT_FIELDS = ("channels", "template_feature_size", "search_feature_size", "head_hidden", "denoiser_ch",
               "denoiser_res_blocks", "denoiser_groups", "diffusion_total_steps", "ddim_steps", "align_heads",
               "align_ffn")
_TRACKER_INTS = ("exemplar_size", "instance_size", "stride", "score_size")
ALIGNS = ("released", "paper", "none")


# Keys of experiments that did not ship: a saved state may hold them, at these values only (the one behaviour
# this version builds); another value names a network this version cannot build.
RETIRED_KEYS: dict[str, Any] = {"head_upsample": 1, "antialias_blocks": [], "fine_skip": False,
                                "align_template": False, "align_template_gate": 0.0}


def without_retired(d: dict[str, Any]) -> dict[str, Any]:
    """A stored model config without the retired keys; ValueError naming a key set to anything but its value."""
    for key, value in RETIRED_KEYS.items():
        if key in d and d[key] != value and not (key == "antialias_blocks" and list(d[key]) == value):
            raise ValueError(f"'{key}' is {d[key]!r}: a retired experiment this version cannot build (only "
                             f"{value!r}); export it with the dadiff release that trained it")
    return {k: v for k, v in d.items() if k not in RETIRED_KEYS}


def lite0_subsampling_blocks(backbone: str) -> tuple[int, ...]:
    """The stride-2 blocks a Lite0 trunk builds, as the trunk itself computes them."""
    from .efficientnet_lite import subsampling_blocks  # torch: the trunk's own rule

    last, dilate, _ = LITE0_TRUNKS[backbone]
    return subsampling_blocks(last, dilate)


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _check_model_fields(cfg: ModelConfig) -> None:
    if cfg.family not in FAMILIES:
        raise ValueError(f"'family' is {cfg.family!r}; expected one of {', '.join(FAMILIES)}")
    if cfg.backbone not in ("resnet50-atrous", GAT_BACKBONE) and not is_lite0(cfg.backbone):
        known = ", ".join(("resnet50-atrous", GAT_BACKBONE, *LITE0_TRUNKS))
        raise ValueError(f"'backbone' is {cfg.backbone!r}; expected one of {known}")
    for name in _INT_FIELDS:
        value = getattr(cfg, name)
        if not _is_int(value) or value < 1:
            raise ValueError(f"'{name}' is {value!r}; expected a positive integer")
    if not 1 <= cfg.ddim_steps <= cfg.diffusion_total_steps:
        raise ValueError(f"'ddim_steps' is {cfg.ddim_steps}; expected 1..{cfg.diffusion_total_steps} "
                         "(diffusion_total_steps)")
    start, total = cfg.ddim_start_t, cfg.diffusion_total_steps
    if start is not None and (not _is_int(start) or not 0 <= start < total):
        raise ValueError(f"'ddim_start_t' is {start!r}; expected an integer in 0..{total - 1} "
                         f"(below diffusion_total_steps {total}) or none")
    if cfg.align not in ALIGNS:
        raise ValueError(f"'align' is {cfg.align!r}; expected one of {', '.join(ALIGNS)}")
    for name in ("use_dadiff", "align_residual", "denoiser_attention"):
        if not isinstance(getattr(cfg, name), bool):
            raise ValueError(f"'{name}' is {getattr(cfg, name)!r}; expected true or false")
    levels = (cfg.level_names, cfg.backbone_channels)
    if not cfg.level_names or len(cfg.level_names) != len(cfg.backbone_channels):
        raise ValueError(f"'level_names' and 'backbone_channels' must be non-empty and of one length, got {levels}")
    if not all(_is_int(v) and v >= 0 for v in cfg.level_names) or not all(
            _is_int(v) and v >= 1 for v in cfg.backbone_channels):
        raise ValueError(f"'level_names' / 'backbone_channels' must hold integers (>= 0 / >= 1), got {levels}")
    if (2 * cfg.denoiser_ch) % cfg.denoiser_groups or cfg.denoiser_ch % cfg.denoiser_groups:
        raise ValueError(f"'denoiser_groups' {cfg.denoiser_groups} does not divide 'denoiser_ch' {cfg.denoiser_ch}")
    if cfg.align != "none" and cfg.channels % cfg.align_heads:
        raise ValueError(f"'align_heads' {cfg.align_heads} does not divide 'channels' {cfg.channels}")
    if not _is_int(cfg.head_search_padding) or cfg.head_search_padding < 0:
        raise ValueError(f"'head_search_padding' is {cfg.head_search_padding!r}; expected an integer >= 0")
    if (cfg.family == GAT_FAMILY) != (cfg.backbone == GAT_BACKBONE):
        raise ValueError(f"'backbone' {cfg.backbone!r} does not fit family {cfg.family!r} ({GAT_BACKBONE} is "
                         f"{GAT_FAMILY}'s alone)")


def _check_tracker_fields(tr: TrackerConfig) -> None:
    # torch-free: the runtime's decoders, its bounds on the crop settings and the keys it reads from a preset
    from dadiff.runtime.config import DECODERS, GEOMETRY_LIMITS, TUNABLE_KEYS

    for name in _TRACKER_INTS:
        value = getattr(tr, name)
        if not _is_int(value):
            raise ValueError(f"'tracker.{name}' is {value!r}; expected an integer")
    if tr.decoder not in DECODERS:
        raise ValueError(f"'tracker.decoder' is {tr.decoder!r}; expected one of {', '.join(DECODERS)}")
    if tr.origin is not None and not _is_int(tr.origin):
        raise ValueError(f"'tracker.origin' is {tr.origin!r}; expected an integer or none")

    for name in ("context_amount", "min_size"):
        value = getattr(tr, name)
        if not _is_number(value):
            raise ValueError(f"'tracker.{name}' is {value!r}; expected a number")
        if value > GEOMETRY_LIMITS[name]:  # negative ones: the runtime's checks below
            raise ValueError(f"'tracker.{name}' is {value!r}; expected at most {GEOMETRY_LIMITS[name]:g}")
    if not isinstance(tr.hp_presets, dict) or not all(isinstance(v, dict) for v in tr.hp_presets.values()):
        raise ValueError("'tracker.hp_presets' must map preset names to tables")
    if tr.default_preset not in tr.hp_presets:
        known = ", ".join(sorted(tr.hp_presets)) or "none"
        raise ValueError(f"'tracker.default_preset' is {tr.default_preset!r}; the presets are {known}")
    for name, table in tr.hp_presets.items():
        for key in ("lr", "penalty_k", "window_influence"):
            if not _is_number(table.get(key)):
                raise ValueError(f"'tracker.hp_presets.{name}.{key}' is {table.get(key)!r}; expected a number")
        unknown = sorted(set(table) - set(TUNABLE_KEYS))
        if unknown:  # the runtime skips them: a misspelt key would silently not apply
            raise ValueError(f"'tracker.hp_presets.{name}' has unknown key {unknown[0]!r} "
                             f"(known: {', '.join(TUNABLE_KEYS)})")


def _check_tracker_against_model(cfg: ModelConfig) -> None:
    """The tracker's grid must be the network's: a stride the network does not have decodes every box wrongly."""
    tr = cfg.tracker
    if (tr.decoder == "siamgat") != (cfg.family == GAT_FAMILY):
        raise ValueError(f"'tracker.decoder' is {tr.decoder!r}; {cfg.family} outputs need "
                         f"{'siamgat' if cfg.family == GAT_FAMILY else 'siamban'}")
    trunk = BACKBONE_STRIDES[cfg.backbone]
    if tr.stride != trunk:
        raise ValueError(f"'tracker.stride' is {tr.stride}; the network ({cfg.backbone}) has stride {trunk}")


def with_overrides(cfg: ModelConfig, overrides: dict[str, Any]) -> ModelConfig:
    """`cfg` with a training config's `model = {...}` table applied."""
    return replace(cfg, **overrides)


def tracker_metadata(tr: TrackerConfig) -> dict[str, str]:
    """The tracker keys of the exported metadata, as the runtime reads them (docs/model-format.md)."""
    hp = tr.hp_presets[tr.default_preset]
    decoder = {} if tr.decoder == "siamban" else {
        "decoder": tr.decoder, "region_s": repr(tr.region_s), "region_l": repr(tr.region_l)}
    return decoder | {
        "dadiff_format": "1", "exemplar_size": str(tr.exemplar_size), "instance_size": str(tr.instance_size),
        "stride": str(tr.stride), "score_size": str(tr.score_size), "point_origin": str(tr.point_origin),
        "context_amount": repr(tr.context_amount), "min_size": repr(tr.min_size),
        "penalty_k": repr(hp["penalty_k"]), "window_influence": repr(hp["window_influence"]), "lr": repr(hp["lr"]),
        "hp_presets": json.dumps(tr.hp_presets, sort_keys=True), "default_preset": tr.default_preset,
    }


def validate_config(cfg: ModelConfig) -> None:
    """ValueError naming the key when a stored config cannot give a model the runtime loads.

    The model's own fields first (types, ranges, known names), then the runtime's metadata checks on the
    tracker settings it would export, so an export either yields a loadable model or fails before any work.
    """
    from dadiff.runtime.config import check_metadata  # torch-free; imported here to keep this module light
    from dadiff.runtime.errors import ModelError

    _check_model_fields(cfg)
    _check_tracker_fields(cfg.tracker)
    try:
        check_metadata(tracker_metadata(cfg.tracker), "tracker settings")
    except ModelError as e:
        raise ValueError(str(e).replace("tracker settings: metadata key ", "tracker key ")) from None
    _check_tracker_against_model(cfg)


def is_lite0(backbone: str) -> bool:
    """Whether a backbone is an EfficientNet-Lite0 trunk (ImageNet weights, in-graph normalisation)."""
    return backbone in LITE0_TRUNKS


def default_config(family: str) -> ModelConfig:
    if family == "dadiff-ban-r50":
        return ban_r50_config()
    if family == GAT_FAMILY:
        return gat_googlenet_config()
    if family == "dadiff-lite":
        return lite_config()
    if family == "dadiff-mobile":
        return mobile_config()
    raise ValueError(f"unknown model family {family!r}; expected one of {', '.join(FAMILIES)}")
