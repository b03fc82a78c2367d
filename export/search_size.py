"""Exporting a trained network at a smaller search crop than it was trained on.

Backbone, neck, denoiser, tracking-oriented layer and head are all convolutional or per-token, so the same
weights run on a smaller search crop: 223 px instead of 255 px gives `dadiff-mobile` a 14 x 14 feature map
and an 11 x 11 score map for about 24 % less arithmetic per frame. Two things tie a network to its trained
size, and this module handles both. The fixed DDIM start noise of the search branch is stored at the
trained map size; the smaller map takes its centre. The decoder centres its grid of points on a map cell,
which needs an odd map whose centre cell lies under the crop's centre: true exactly when the crop shrinks
by a whole number of feature cells on each side, that is by a multiple of twice the stride.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import nn

from .checkpoint import CheckpointError, LoadedCheckpoint


def search_sizes(current: int, stride: int, exemplar: int) -> list[int]:
    """Search sizes a network set up for `current` px can be exported at, largest first (`current` included).

    Larger ones are not offered: the stored start noise covers the current map only.
    """
    return list(range(current, exemplar, -2 * stride))


def _feature_side(net: nn.Module, size: int) -> int:
    """Side of the search feature map the network makes from a size x size crop."""
    with torch.no_grad():
        return net.neck(net.backbone_features(torch.zeros(1, 3, size, size)), False)[0].shape[-1]


def _score_side(net: nn.Module, exemplar: int, size: int) -> int:
    """Side of the score map the network gives on a size x size search crop."""
    with torch.no_grad():
        zf = net.template(torch.zeros(1, 3, exemplar, exemplar))
        kcls, kloc = net.head.kernels(zf)
        cls, _ = net.track(torch.zeros(1, 3, size, size), kcls, kloc)
    return cls.shape[-1]


def _centre(noise: torch.Tensor, side: int) -> torch.Tensor:
    start = (noise.shape[-1] - side) // 2
    cropped = noise[..., start:start + side, start:start + side].detach().clone()
    return nn.Parameter(cropped, requires_grad=False) if isinstance(noise, nn.Parameter) else cropped


def with_search_size(loaded: LoadedCheckpoint, size: int) -> LoadedCheckpoint:
    """`loaded` set up to track on size x size search crops (a CheckpointError names the allowed sizes)."""
    cfg, net = loaded.config, loaded.model
    tr = cfg.tracker
    if size == tr.instance_size:
        return loaded
    if tr.origin is not None:  # DaDiff-GAT: the release's grid is not centred on the crop (offset 45)
        raise CheckpointError(f"search size {size}: this {cfg.family} checkpoint exports at its "
                              f"{tr.instance_size} px search crop only (its score-map grid is fixed to that crop)")
    if size > tr.instance_size:
        raise CheckpointError(
            f"search size {size} is larger than this {cfg.family} checkpoint's {tr.instance_size} px: its stored "
            f"search start noise covers that map only; export from a checkpoint at {size} px (a training state)")
    allowed = search_sizes(tr.instance_size, tr.stride, tr.exemplar_size)  # the map's cells
    if size not in allowed:
        raise CheckpointError(
            f"search size {size} does not fit this {cfg.family} checkpoint (search crop {tr.instance_size} px, "
            f"stride {tr.stride}): its score map must stay odd and centred, so the size must be one of "
            f"{', '.join(map(str, allowed))}")
    side = _feature_side(net, size)
    noise = net.e_xf
    net.e_xf = _centre(noise, side)  # the search branch needs start noise of its own map size
    score = _score_side(net, tr.exemplar_size, size)
    expected = tr.score_size - (tr.instance_size - size) // tr.stride
    if score != expected:
        net.e_xf = noise
        raise CheckpointError(f"at search size {size} this network gives a {score} x {score} score map, "
                              f"not the {expected} x {expected} the decoder's grid needs")
    new_cfg = replace(cfg, search_feature_size=side,
                      tracker=replace(tr, instance_size=size, score_size=score))
    net.cfg = new_cfg
    return replace(loaded, config=new_cfg)
