"""Neck: per level a 1x1 conv + BN to a common width; template maps are centre-cropped (spec 4)."""

from __future__ import annotations

import torch
from torch import nn


def centre_crop(x: torch.Tensor, size: int) -> torch.Tensor:
    start = (x.shape[3] - size) // 2
    return x[:, :, start:start + size, start:start + size]


class AdjustLayer(nn.Module):
    def __init__(self, in_ch: int, out_ch: int, center_size: int) -> None:
        super().__init__()
        self.downsample = nn.Sequential(nn.Conv2d(in_ch, out_ch, 1, bias=False), nn.BatchNorm2d(out_ch))
        self.center_size = center_size

    def forward(self, x: torch.Tensor, template: bool) -> torch.Tensor:
        x = self.downsample(x)
        # a template keeps the centre: 15 -> 4..11 for SiamBAN (the release's x[:, :, 4:11, 4:11]), 16 -> 4..12
        return centre_crop(x, self.center_size) if template else x


class AdjustAllLayer(nn.Module):
    def __init__(self, level_names: tuple[int, ...], in_channels: tuple[int, ...], out_ch: int,
                 center_size: int) -> None:
        super().__init__()
        self.level_names = level_names
        for name, in_ch in zip(level_names, in_channels, strict=True):
            self.add_module(f"downsample{name}", AdjustLayer(in_ch, out_ch, center_size))

    def forward(self, features: list[torch.Tensor], template: bool) -> list[torch.Tensor]:
        return [getattr(self, f"downsample{name}")(f, template)
                for name, f in zip(self.level_names, features, strict=True)]

