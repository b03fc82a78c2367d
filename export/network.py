"""The DaDiff Siamese tracker network: backbone -> neck -> DDIM alignment -> tracking-oriented layer -> BAN.

The BAN families (dadiff-ban-r50, dadiff-lite, dadiff-mobile) are this one module with different
configurations (config.py); dadiff-gat-googlenet is export/gat.py. The template branch produces
per-level aligned features and the head's template kernels once per sequence; the search branch runs per
frame and only needs those kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .align import ReleasedAlignLayer, TrackingOrientedLayer
from .config import GAT_FAMILY, LITE0_TRUNKS, ModelConfig, is_lite0
from .denoiser import DDIMSampler, Denoiser
from .head import MultiBAN
from .neck import AdjustAllLayer
from .resnet import AtrousResNet50


@dataclass
class BranchOutput:
    """Everything one branch computes; training needs the chain states, inference only `aligned`."""

    neck: list[torch.Tensor]
    states: list[list[torch.Tensor]]  # per level: [X_start, ..., X_0]
    aligned: list[torch.Tensor]


def build_backbone(cfg: ModelConfig) -> nn.Module:
    if cfg.backbone == "resnet50-atrous":
        return AtrousResNet50()
    if is_lite0(cfg.backbone):
        from .efficientnet_lite import EfficientNetLite0

        last, dilate, outs = LITE0_TRUNKS[cfg.backbone]
        return EfficientNetLite0(last_block=last, dilate_from_block=dilate, out_blocks=outs)
    raise ValueError(f"unknown backbone {cfg.backbone!r}")


class DaDiffNet(nn.Module):
    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c = cfg.channels
        self.backbone = build_backbone(cfg)
        self.neck = AdjustAllLayer(cfg.level_names, cfg.backbone_channels, c, cfg.template_feature_size)
        self.diffusion = Denoiser(2 * c, cfg.denoiser_ch, c, cfg.denoiser_res_blocks, cfg.denoiser_attention,
                                  cfg.denoiser_groups)
        self.sampler = DDIMSampler(cfg.diffusion_total_steps, cfg.ddim_steps, cfg.ddim_start_t)
        gen = torch.Generator().manual_seed(1234)
        e_zf = torch.randn(1, c, cfg.template_feature_size, cfg.template_feature_size, generator=gen)
        e_xf = torch.randn(1, c, cfg.search_feature_size, cfg.search_feature_size, generator=gen)
        if cfg.align == "released":  # the release declares the start tensors as (never trained) parameters
            self.e_zf, self.e_xf = nn.Parameter(e_zf), nn.Parameter(e_xf)
            self.align_track: nn.Module = ReleasedAlignLayer(c, cfg.align_heads, cfg.align_ffn)
        else:  # ours: a fixed noise tensor stored in the checkpoint, as the paper's X_T but deterministic
            self.register_buffer("e_zf", e_zf)
            self.register_buffer("e_xf", e_xf)
            if cfg.align == "paper":
                self.align_track = TrackingOrientedLayer(c, cfg.align_heads, cfg.align_ffn)
            elif cfg.align == "none":
                self.align_track = nn.Identity()
            else:
                raise ValueError(f"unknown alignment layer {cfg.align!r}")
        if cfg.align_residual:  # LayerScale-style gate: the block starts as the identity of the tracker it joins
            self.align_scale = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.head = MultiBAN(cfg.level_names, c, cfg.head_hidden, cfg.head_search_padding)

    def backbone_features(self, img: torch.Tensor) -> list[torch.Tensor]:
        """The levels the neck takes (a Lite0 trunk's output blocks fused into one)."""
        feats = self.backbone(img)
        if is_lite0(self.cfg.backbone) and len(feats) > 1:
            feats = [torch.cat(feats, dim=1)]  # one fused level
        return feats

    def diffuse(self, neck: list[torch.Tensor], noise: torch.Tensor) -> list[list[torch.Tensor]]:
        """Run the sampler on every level; levels of one shape go through the denoiser as one batch."""
        n = neck[0].shape[0]
        if len(neck) > 1 and all(f.shape == neck[0].shape for f in neck):
            cond = torch.cat(neck, dim=0)
            states = self.sampler(self.diffusion, cond, noise.expand(cond.shape[0], -1, -1, -1))
            return [[s[i * n:(i + 1) * n] for s in states] for i in range(len(neck))]
        return [self.sampler(self.diffusion, f, noise.expand(n, -1, -1, -1)) for f in neck]

    def branch(self, img: torch.Tensor, noise: torch.Tensor, template: bool) -> BranchOutput:
        neck = self.neck(self.backbone_features(img), template)
        if not self.cfg.use_dadiff:
            return BranchOutput(neck, [[f] for f in neck], neck)
        states = self.diffuse(neck, noise)
        aligned = [self.align_track(s[-1]) for s in states]
        if self.cfg.align_residual:
            aligned = [n + self.align_scale * a for n, a in zip(neck, aligned, strict=True)]
        return BranchOutput(neck, states, aligned)

    def template_branch(self, z: torch.Tensor) -> BranchOutput:
        """The branch on a template crop: its own start noise, the neck's centre crop."""
        return self.branch(z, self.e_zf, template=True)

    def search_branch(self, x: torch.Tensor) -> BranchOutput:
        """The branch on a search crop: its own start noise, the whole map."""
        return self.branch(x, self.e_xf, template=False)

    def template(self, z: torch.Tensor) -> list[torch.Tensor]:
        """Aligned template features per level (what the head receives)."""
        return self.template_branch(z).aligned

    def template_kernels(self, z: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
        zf = self.template(z)
        kcls, kloc = self.head.kernels(zf)
        return zf, kcls, kloc

    def reads_template(self) -> bool:
        """Whether the search graph takes the template's features besides the head's kernels (DaDiff-GAT's
        does; this network's search side reads the kernels alone)."""
        return False

    def track(self, x: torch.Tensor, kcls: list[torch.Tensor], kloc: list[torch.Tensor]
              ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.head(self.search_branch(x).aligned, kcls, kloc)

    def forward(self, z: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Template + search in one call (training and tests)."""
        zf = self.template(z)
        kcls, kloc = self.head.kernels(zf)
        return self.track(x, kcls, kloc)


def build_model(cfg: ModelConfig, pretrained_backbone: bool = False) -> DaDiffNet:
    """A new network; `pretrained_backbone` loads the ImageNet EfficientNet-Lite0 weights (lite, mobile)."""
    if cfg.family == GAT_FAMILY:
        if pretrained_backbone:
            raise ValueError(f"no bundled pretrained weights for backbone {cfg.backbone!r}")
        from .gat import DaDiffGAT

        return DaDiffGAT(cfg)  # type: ignore[return-value]  # the same checkpoint, export and parity interface
    net = DaDiffNet(cfg)
    if pretrained_backbone:
        if not is_lite0(cfg.backbone):
            raise ValueError(f"no bundled pretrained weights for backbone {cfg.backbone!r}")
        from .efficientnet_lite import load_imagenet_weights

        load_imagenet_weights(net.backbone)
    return net
