"""ResNet-50 in the pysot "atrous" form used by SiamBAN and the released DaDiff-BAN.

Layers 3 and 4 keep stride 8 by dilation instead of striding; layer 2 strides with zero padding, and
the stem convolution has no padding. Module names follow the released checkpoint keys exactly.
"""

from __future__ import annotations

import torch
from torch import nn


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int, padding: int, dilation: int,
                 downsample: nn.Module | None) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=stride, padding=padding, dilation=dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        shortcut = x if self.downsample is None else self.downsample(x)
        return self.relu(out + shortcut)


def _shortcut(inplanes: int, outplanes: int, kernel: int, stride: int, padding: int, dilation: int) -> nn.Module:
    return nn.Sequential(
        nn.Conv2d(inplanes, outplanes, kernel, stride=stride, padding=padding, dilation=dilation, bias=False),
        nn.BatchNorm2d(outplanes),
    )


class AtrousResNet50(nn.Module):
    """Stem + layers 1-4; returns the outputs of layers 2, 3 and 4 (512/1024/2048 channels, stride 8)."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=0, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        self.layer1 = self._layer(64, 64, 3, stride=1, dilation=1)
        self.layer2 = self._layer(256, 128, 4, stride=2, dilation=1)
        self.layer3 = self._layer(512, 256, 6, stride=1, dilation=2)
        self.layer4 = self._layer(1024, 512, 3, stride=1, dilation=4)

    @staticmethod
    def _layer(inplanes: int, planes: int, blocks: int, stride: int, dilation: int) -> nn.Sequential:
        outplanes = planes * 4
        if stride == 2:  # layer 2: 3x3 strided conv without padding, also on the shortcut
            first = Bottleneck(inplanes, planes, 2, 0, 1, _shortcut(inplanes, outplanes, 3, 2, 0, 1))
        elif dilation == 1:  # layer 1: plain 1x1 projection
            first = Bottleneck(inplanes, planes, 1, 1, 1, _shortcut(inplanes, outplanes, 1, 1, 0, 1))
        else:  # layers 3, 4: the first block uses half the dilation, its shortcut is a 3x3 conv
            half = dilation // 2
            first = Bottleneck(inplanes, planes, 1, half, half, _shortcut(inplanes, outplanes, 3, 1, half, half))
        rest = [Bottleneck(outplanes, planes, 1, dilation, dilation, None) for _ in range(blocks - 1)]
        return nn.Sequential(first, *rest)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x1 = self.layer1(x)
        x2 = self.layer2(x1)
        x3 = self.layer3(x2)
        x4 = self.layer4(x3)
        return [x2, x3, x4]
