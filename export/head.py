"""MultiBAN head: per level a depthwise cross-correlation for classification and for box regression.

The template-side convolutions (`conv_kernel`) depend only on the template, so they are split out and run
once per sequence (`kernels`); `forward` takes those kernels and the search features (spec 5.5).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def conv_bn_relu(in_ch: int, out_ch: int, kernel: int, padding: int = 0) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(in_ch, out_ch, kernel, padding=padding, bias=False), nn.BatchNorm2d(out_ch),
                         nn.ReLU(inplace=True))


def xcorr_depthwise(search: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Per-channel correlation (no flip) of each sample's search map with its own kernel."""
    b, c, h, w = search.shape
    out = F.conv2d(search.reshape(1, b * c, h, w), kernel.reshape(b * c, 1, kernel.shape[2], kernel.shape[3]),
                   groups=b * c)
    return out.reshape(b, c, out.shape[2], out.shape[3])


class DepthwiseBAN(nn.Module):
    def __init__(self, in_ch: int, hidden: int, out_ch: int, search_padding: int = 0) -> None:
        super().__init__()
        self.conv_kernel = conv_bn_relu(in_ch, hidden, 3)
        self.conv_search = conv_bn_relu(in_ch, hidden, 3, search_padding)
        self.head = nn.Sequential(nn.Conv2d(hidden, hidden, 1, bias=False), nn.BatchNorm2d(hidden),
                                  nn.ReLU(inplace=True), nn.Conv2d(hidden, out_ch, 1))

    def forward(self, search: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
        return self.head(xcorr_depthwise(self.conv_search(search), kernel))


class BoxLevel(nn.Module):
    def __init__(self, in_ch: int, hidden: int, search_padding: int = 0) -> None:
        super().__init__()
        self.cls = DepthwiseBAN(in_ch, hidden, 2, search_padding)
        self.loc = DepthwiseBAN(in_ch, hidden, 4, search_padding)


class MultiBAN(nn.Module):
    """cls = sum_l softmax(cls_weight)_l cls_l; loc = sum_l softmax(loc_weight)_l exp(loc_scale_l loc_l)."""

    def __init__(self, level_names: tuple[int, ...], in_ch: int, hidden: int, search_padding: int = 0) -> None:
        super().__init__()
        self.level_names = level_names
        for name in level_names:
            self.add_module(f"box{name}", BoxLevel(in_ch, hidden, search_padding))
        n = len(level_names)
        self.cls_weight = nn.Parameter(torch.ones(n))
        self.loc_weight = nn.Parameter(torch.ones(n))
        self.loc_scale = nn.Parameter(torch.ones(n))

    def levels(self) -> list[BoxLevel]:
        return [getattr(self, f"box{name}") for name in self.level_names]

    def kernels(self, zfs: list[torch.Tensor]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        kcls = [box.cls.conv_kernel(z) for box, z in zip(self.levels(), zfs, strict=True)]
        kloc = [box.loc.conv_kernel(z) for box, z in zip(self.levels(), zfs, strict=True)]
        return kcls, kloc

    def forward(self, xfs: list[torch.Tensor], kcls: list[torch.Tensor],
                kloc: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        cls_w = torch.softmax(self.cls_weight, dim=0)
        loc_w = torch.softmax(self.loc_weight, dim=0)
        cls, loc = 0.0, 0.0
        for i, (box, x) in enumerate(zip(self.levels(), xfs, strict=True)):
            cls = cls + cls_w[i] * box.cls(x, kcls[i])
            loc = loc + loc_w[i] * torch.exp(self.loc_scale[i] * box.loc(x, kloc[i]))
        return cls, loc
