"""Model and tracker configuration for the two families, stored inside our own checkpoints."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

FAMILIES = ("dadiff-ban-r50", "dadiff-lite")

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
    backbone: str                      # "resnet50-atrous" | "efficientnet-lite0"
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


def default_config(family: str) -> ModelConfig:
    if family == "dadiff-ban-r50":
        return ban_r50_config()
    if family == "dadiff-lite":
        return lite_config()
    raise ValueError(f"unknown model family {family!r}; expected one of {', '.join(FAMILIES)}")
