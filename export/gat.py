"""DaDiff-GAT: SiamGAT (Inception-v3 -> Graph Attention Union -> CAR head) with the released DaDiff block.

The DaDiff block is the BAN family's (denoiser, two-step DDIM sampler, LN(x + pos) alignment layer), run on
one 256-channel level; what is new here is the backbone (export/inception.py), the graph attention that
replaces the depthwise correlation, and the anchor-free CAR head with its centerness map. The template side
takes the template ROI (its box in template-crop pixels) besides the crop: the backbone masks it.
Module names follow the released `checkpoint_e45.pth` keys (613 of them).
"""

from __future__ import annotations

import torch
from torch import nn

from .align import ReleasedAlignLayer
from .config import ModelConfig
from .denoiser import DDIMSampler, Denoiser
from .inception import InceptionOU
from .network import BranchOutput


def _conv_bn_relu(in_ch: int, out_ch: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(in_ch, out_ch, 1), nn.BatchNorm2d(out_ch), nn.ReLU(inplace=True))


class GraphAttentionUnion(nn.Module):
    """Each search position gathers the template's `g` features weighted by a softmax over the template positions.

    As released: `support` transforms the template and `query` the search (the names are swapped relative to
    the release's comments), the similarity has no 1/sqrt(d) scaling, masked template cells take part, and the
    output is `fi`([gathered, g(search)]).
    """

    def __init__(self, channels: int = 256) -> None:
        super().__init__()
        self.support = nn.Conv2d(channels, channels, 1)
        self.query = nn.Conv2d(channels, channels, 1)
        self.g = _conv_bn_relu(channels, channels)
        self.fi = _conv_bn_relu(2 * channels, channels)

    def forward(self, zf: torch.Tensor, xf: torch.Tensor) -> torch.Tensor:
        b, c, h, w = xf.shape
        queries = self.query(xf).flatten(2).transpose(1, 2)        # (B, HxWx, C)
        keys = self.support(zf).flatten(2)                          # (B, C, HzWz)
        values = self.g(zf).flatten(2).transpose(1, 2)              # (B, HzWz, C)
        weights = torch.softmax(torch.matmul(queries, keys), dim=2)
        gathered = torch.matmul(weights, values).transpose(1, 2).reshape(b, c, h, w)
        return self.fi(torch.cat([gathered, self.g(xf)], 1))


def _tower(channels: int, convs: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for _ in range(convs):
        layers += [nn.Conv2d(channels, channels, 3, padding=1), nn.GroupNorm(32, channels), nn.ReLU()]
    return nn.Sequential(*layers)


class CARHead(nn.Module):
    """cls logits (2) and centerness (1) from the cls tower, exp(bbox_pred) (l, t, r, b) from the bbox tower."""

    def __init__(self, channels: int = 256, convs: int = 4) -> None:
        super().__init__()
        self.cls_tower = _tower(channels, convs)
        self.bbox_tower = _tower(channels, convs)
        self.cls_logits = nn.Conv2d(channels, 2, 3, padding=1)
        self.bbox_pred = nn.Conv2d(channels, 4, 3, padding=1)
        self.centerness = nn.Conv2d(channels, 1, 3, padding=1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        tower = self.cls_tower(x)
        return self.cls_logits(tower), torch.exp(self.bbox_pred(self.bbox_tower(x))), self.centerness(tower)


class DaDiffGAT(nn.Module):
    """template(z, roi) once per target -> aligned template features; track(x, zf) per frame -> cls, loc, cen."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        c = cfg.channels
        self.backbone = InceptionOU(c)
        self.diffusion = Denoiser(2 * c, cfg.denoiser_ch, c, cfg.denoiser_res_blocks, cfg.denoiser_attention,
                                  cfg.denoiser_groups)
        self.sampler = DDIMSampler(cfg.diffusion_total_steps, cfg.ddim_steps, cfg.ddim_start_t)
        gen = torch.Generator().manual_seed(1234)  # the release's (never trained) start tensors are parameters
        t, s = cfg.template_feature_size, cfg.search_feature_size
        self.e_zf = nn.Parameter(torch.randn(1, c, t, t, generator=gen))
        self.e_xf = nn.Parameter(torch.randn(1, c, s, s, generator=gen))
        self.align_track = ReleasedAlignLayer(c, cfg.align_heads, cfg.align_ffn)
        self.car_head = CARHead(c)
        self.attention = GraphAttentionUnion(c)

    def _dadiff(self, feature: torch.Tensor, noise: torch.Tensor) -> BranchOutput:
        states = self.sampler(self.diffusion, feature, noise.expand(feature.shape[0], -1, -1, -1))
        return BranchOutput([feature], [states], [self.align_track(states[-1])])

    def template_branch(self, z: torch.Tensor, roi: torch.Tensor) -> BranchOutput:
        return self._dadiff(self.backbone.template(z, roi), self.e_zf)

    def search_branch(self, x: torch.Tensor) -> BranchOutput:
        return self._dadiff(self.backbone.search(x), self.e_xf)

    def template(self, z: torch.Tensor, roi: torch.Tensor) -> torch.Tensor:
        """The aligned template features the graph attention reads (the release's cached `zf_diff`)."""
        return self.template_branch(z, roi).aligned[0]

    def track(self, x: torch.Tensor, zf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.car_head(self.attention(zf, self.search_branch(x).aligned[0]))

    def reads_template(self) -> bool:
        return True
