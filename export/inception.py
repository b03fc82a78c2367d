"""Inception-v3 to Mixed_6e as the released DaDiff-GAT (SiamGAT) uses it, with its template ROI mask.

The release's `googlenet_ou` variant: the second max-pool is dropped (stride 8), every conv is conv (no bias) +
BN (eps 1e-3) + ReLU, pool branches average with zero padding counted. It takes BGR 0..255 and reorders and
scales to RGB in [-1, 1] itself. The template's 13 x 13 Mixed_6e map is multiplied by a box mask built from the
template ROI *before* `channel_reduce`, so masked cells hold channel_reduce's bias, not zero; the search map
(33 x 33) loses 4 cells per side. Module names follow the released checkpoint keys.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

MASK_STRIDE, MASK_OFFSET, MASK_LIMIT = 8, 13, 12  # the release's BACKBONE.STRIDE / OFFSET and its hard-coded 12
SEARCH_CROP = 4  # cells cut from each side of the search map (BACKBONE.CROP_PAD)


class BasicConv2d(nn.Module):
    def __init__(self, in_ch: int, out_ch: int, kernel: int | tuple[int, int], stride: int = 1,
                 padding: int | tuple[int, int] = 0) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_ch, out_ch, kernel, stride=stride, padding=padding, bias=False)
        self.bn = nn.BatchNorm2d(out_ch, eps=1e-3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.bn(self.conv(x)))


def _pool_branch(x: torch.Tensor, conv: BasicConv2d) -> torch.Tensor:
    return conv(F.avg_pool2d(x, 3, stride=1, padding=1))  # count_include_pad=True, as the release


class InceptionA(nn.Module):
    def __init__(self, in_ch: int, pool_features: int) -> None:
        super().__init__()
        self.branch1x1 = BasicConv2d(in_ch, 64, 1)
        self.branch5x5_1 = BasicConv2d(in_ch, 48, 1)
        self.branch5x5_2 = BasicConv2d(48, 64, 5, padding=2)
        self.branch3x3dbl_1 = BasicConv2d(in_ch, 64, 1)
        self.branch3x3dbl_2 = BasicConv2d(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = BasicConv2d(96, 96, 3, padding=1)
        self.branch_pool = BasicConv2d(in_ch, pool_features, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b5 = self.branch5x5_2(self.branch5x5_1(x))
        b3 = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
        return torch.cat([self.branch1x1(x), b5, b3, _pool_branch(x, self.branch_pool)], 1)


class InceptionB(nn.Module):
    """The stride-2 block (Mixed_6a)."""

    def __init__(self, in_ch: int) -> None:
        super().__init__()
        self.branch3x3 = BasicConv2d(in_ch, 384, 3, stride=2)
        self.branch3x3dbl_1 = BasicConv2d(in_ch, 64, 1)
        self.branch3x3dbl_2 = BasicConv2d(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = BasicConv2d(96, 96, 3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b3 = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
        return torch.cat([self.branch3x3(x), b3, F.max_pool2d(x, 3, stride=2)], 1)


class InceptionC(nn.Module):
    """Factorised 7x7 block (Mixed_6b..6e); `c7` is its inner width."""

    def __init__(self, in_ch: int, c7: int) -> None:
        super().__init__()
        self.branch1x1 = BasicConv2d(in_ch, 192, 1)
        self.branch7x7_1 = BasicConv2d(in_ch, c7, 1)
        self.branch7x7_2 = BasicConv2d(c7, c7, (1, 7), padding=(0, 3))
        self.branch7x7_3 = BasicConv2d(c7, 192, (7, 1), padding=(3, 0))
        self.branch7x7dbl_1 = BasicConv2d(in_ch, c7, 1)
        self.branch7x7dbl_2 = BasicConv2d(c7, c7, (7, 1), padding=(3, 0))
        self.branch7x7dbl_3 = BasicConv2d(c7, c7, (1, 7), padding=(0, 3))
        self.branch7x7dbl_4 = BasicConv2d(c7, c7, (7, 1), padding=(3, 0))
        self.branch7x7dbl_5 = BasicConv2d(c7, 192, (1, 7), padding=(0, 3))
        self.branch_pool = BasicConv2d(in_ch, 192, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b7 = self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x)))
        d = x
        for conv in (self.branch7x7dbl_1, self.branch7x7dbl_2, self.branch7x7dbl_3, self.branch7x7dbl_4,
                     self.branch7x7dbl_5):
            d = conv(d)
        return torch.cat([self.branch1x1(x), b7, d, _pool_branch(x, self.branch_pool)], 1)


def roi_mask(roi: torch.Tensor, size: int) -> torch.Tensor:
    """The release's template mask (1, 1, size, size) from roi (1, 4) = (x1, y1, x2, y2) in template-crop pixels.

    Cell index = trunc((roi + 1 - 13 + 4) / 8 - 1) (toward zero); rows y1..y2-1 and cols x1..x2-1, each range
    clamped to [0, 12) whatever the map's size. Written with comparisons so it exports to ONNX as it computes.
    """
    scaled = (roi[0] + 1 - MASK_OFFSET + MASK_STRIDE / 2) / MASK_STRIDE - 1
    idx = torch.sign(scaled) * torch.floor(scaled.abs())  # .int() of the release: truncation toward zero
    cells = torch.arange(size, dtype=roi.dtype)
    low, high = idx.clamp(min=0), idx.clamp(max=MASK_LIMIT)
    cols = (cells >= low[0]) & (cells < high[2])
    rows = (cells >= low[1]) & (cells < high[3])
    return (rows[:, None] & cols[None, :]).to(roi.dtype)[None, None]


class InceptionOU(nn.Module):
    """Inception-v3 stem + Mixed_5b..6e + channel_reduce (768 -> 256); stride 8, no second max-pool."""

    def __init__(self, out_ch: int = 256) -> None:
        super().__init__()
        self.Conv2d_1a_3x3 = BasicConv2d(3, 32, 3, stride=2)
        self.Conv2d_2a_3x3 = BasicConv2d(32, 32, 3)
        self.Conv2d_2b_3x3 = BasicConv2d(32, 64, 3, padding=1)
        self.Conv2d_3b_1x1 = BasicConv2d(64, 80, 1)
        self.Conv2d_4a_3x3 = BasicConv2d(80, 192, 3)
        self.Mixed_5b = InceptionA(192, 32)
        self.Mixed_5c = InceptionA(256, 64)
        self.Mixed_5d = InceptionA(288, 64)
        self.Mixed_6a = InceptionB(288)
        self.Mixed_6b = InceptionC(768, 128)
        self.Mixed_6c = InceptionC(768, 160)
        self.Mixed_6d = InceptionC(768, 160)
        self.Mixed_6e = InceptionC(768, 192)
        self.channel_reduce = nn.Sequential(nn.Conv2d(768, out_ch, 1), nn.BatchNorm2d(out_ch, eps=1e-3))

    def trunk(self, x: torch.Tensor) -> torch.Tensor:
        """Mixed_6e's 768-channel map of a BGR 0..255 crop."""
        x = (torch.cat([x[:, 2:3], x[:, 1:2], x[:, 0:1]], 1) - 127.5) / 127.5  # BGR -> RGB, [0, 255] -> [-1, 1]
        x = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x)))
        x = self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(F.max_pool2d(x, 3, stride=2)))
        for block in (self.Mixed_5b, self.Mixed_5c, self.Mixed_5d, self.Mixed_6a, self.Mixed_6b, self.Mixed_6c,
                      self.Mixed_6d, self.Mixed_6e):
            x = block(x)
        return x

    def template(self, z: torch.Tensor, roi: torch.Tensor) -> torch.Tensor:
        x = self.trunk(z)
        return self.channel_reduce(x * roi_mask(roi, x.shape[-1]))

    def search(self, x: torch.Tensor) -> torch.Tensor:
        x = self.trunk(x)
        return self.channel_reduce(x[:, :, SEARCH_CROP:-SEARCH_CROP, SEARCH_CROP:-SEARCH_CROP])
