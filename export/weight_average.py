"""An exponential moving average of a network's weights, kept beside the training (Polyak averaging).

A short fine-tuning run ends wherever its last noisy steps leave it; two seeds of the same run differ on the
test sets by more than the run's own effect. The average of the last steps' weights is less at the mercy of
where they end (over three seeds of a fine-tuning stage of the default it was level or ahead on every set's
mean; docs/lab-notebook.md, "A moving average of the weights"). BatchNorm statistics are averaged alike; integer
buffers (BN's step counters) are copied.
"""

from __future__ import annotations

import copy

import torch
from torch import nn


class WeightAverage:
    """state = decay * state + (1 - decay) * weights, after every optimiser step; starts at the weights."""

    def __init__(self, net: nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"ema_decay must be between 0 and 1 (exclusive), got {decay}")
        self.decay = decay
        self.state = {k: v.detach().clone() for k, v in net.state_dict().items()}

    @torch.no_grad()
    def update(self, net: nn.Module) -> None:
        for name, value in net.state_dict().items():
            average = self.state[name]
            if average.is_floating_point():
                average.mul_(self.decay).add_(value.detach(), alpha=1.0 - self.decay)
            else:
                average.copy_(value)

    def load(self, state: dict[str, torch.Tensor]) -> None:
        """Continue from a saved average (resume); it must hold the same tensors as the network."""
        if state.keys() != self.state.keys():
            raise ValueError("the saved weight average does not match the network's tensors")
        self.state = {k: v.detach().clone().to(self.state[k].device) for k, v in state.items()}

    def averaged(self, net: nn.Module) -> nn.Module:
        """A copy of `net` holding the averaged weights (to save as an ordinary checkpoint)."""
        twin = copy.deepcopy(net)
        twin.load_state_dict(self.state, strict=True)
        return twin
