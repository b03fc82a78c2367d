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


class FineSkip(nn.Module):
    """Stride-8 features folded into the stride-16 cells and added to the neck's output (``fine_skip``, ours).

    A stride-16 cell cannot say where inside it a target narrower than the cell lies; the stride-8 map can.
    Space-to-depth (2 x 2 -> 4x the channels) keeps that position as channels and a 1 x 1 conv brings them
    to the neck's width. The conv starts at 0 (no BN, whose batch statistics of a zero map would blow its
    gradient up), so a trained tracker gains the branch as its identity and training opens it.
    """

    def __init__(self, in_ch: int, out_ch: int, center_size: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(4 * in_ch, out_ch, 1, bias=False)
        nn.init.zeros_(self.conv.weight)
        self.center_size = center_size

    def forward(self, fine: torch.Tensor, template: bool) -> torch.Tensor:
        x = self.conv(nn.functional.pixel_unshuffle(fine, 2))
        return centre_crop(x, self.center_size) if template else x  # the neck's crop, cell for cell
