"""Model and tracker configuration for the two families, stored inside our own checkpoints."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

FAMILIES = ("dadiff-ban-r50", "dadiff-lite", "dadiff-mobile")
# EfficientNet-Lite0 trunks: the backbone name -> (last block, first dilated block or None, output blocks).
LITE0_TRUNKS: dict[str, tuple[int, int | None, tuple[int, ...]]] = {
    "efficientnet-lite0": (10, 5, (7, 10)),      # stride 8 (atrous from block 5), blocks 7 + 10 fused
    "efficientnet-lite0-s16": (6, None, (6,)),   # stride 16, stops in stage 3 (80 channels)
}

# [lr, penalty_k, window_influence] of the released test script (spec 8.4).
HP_PRESETS: dict[str, dict[str, float]] = {
    "UAVDark70": {"lr": 0.473, "penalty_k": 0.088, "window_influence": 0.401},
    "NUT_L": {"lr": 0.473, "penalty_k": 0.088, "window_influence": 0.403},
    "NAT": {"lr": 0.45, "penalty_k": 0.14, "window_influence": 0.30},
    "NAT_L": {"lr": 0.466, "penalty_k": 0.083, "window_influence": 0.404},
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

    @property
    def point_origin(self) -> int:
        return -(self.score_size // 2) * self.stride


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
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown model config keys: {', '.join(unknown)}")
        d = dict(d)
        tracker = TrackerConfig(**d.pop("tracker", {}))
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


def is_lite0(backbone: str) -> bool:
    """Whether a backbone is an EfficientNet-Lite0 trunk (ImageNet weights, in-graph normalisation)."""
    return backbone in LITE0_TRUNKS


def default_config(family: str) -> ModelConfig:
    if family == "dadiff-ban-r50":
        return ban_r50_config()
    if family == "dadiff-lite":
        return lite_config()
    if family == "dadiff-mobile":
        return mobile_config()
    raise ValueError(f"unknown model family {family!r}; expected one of {', '.join(FAMILIES)}")
