"""The conditional denoiser eps_theta([X_t || N_f], t): the single-resolution DDIM U-Net of the release.

Same layout as the released `models/diffusion.py` configuration (ch_mult [1], so no down/up-sampling), with
the width, block count, attention and GroupNorm groups configurable so that `dadiff-lite` can use a small one.
Module names follow the released checkpoint keys (`temb.dense`, `down.0.block.N`, `mid.*`, `up.0.block.N`).
"""

from __future__ import annotations

import math

import torch
from torch import nn


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding [sin(t w_k), cos(t w_k)], w_k = exp(-k ln(10000) / (dim/2 - 1))."""
    half = dim // 2
    freqs = torch.exp(torch.arange(half, dtype=torch.float32, device=t.device) * -(math.log(10000) / (half - 1)))
    args = t.float()[:, None] * freqs[None, :]
    return torch.cat([torch.sin(args), torch.cos(args)], dim=1)


def swish(x: torch.Tensor) -> torch.Tensor:
    return x * torch.sigmoid(x)


def group_norm(channels: int, groups: int) -> nn.GroupNorm:
    return nn.GroupNorm(groups, channels, eps=1e-6, affine=True)


class ResnetBlock(nn.Module):
    def __init__(self, in_ch: int, out_ch: int, temb_ch: int, groups: int, dropout: float) -> None:
        super().__init__()
        self.norm1 = group_norm(in_ch, groups)
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, padding=1)
        self.temb_proj = nn.Linear(temb_ch, out_ch)
        self.norm2 = group_norm(out_ch, groups)
        self.dropout = nn.Dropout(dropout)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, padding=1)
        self.nin_shortcut = nn.Conv2d(in_ch, out_ch, 1) if in_ch != out_ch else None

    def forward(self, x: torch.Tensor, temb: torch.Tensor) -> torch.Tensor:
        h = self.conv1(swish(self.norm1(x)))
        h = h + self.temb_proj(swish(temb))[:, :, None, None]
        h = self.conv2(self.dropout(swish(self.norm2(h))))
        skip = x if self.nin_shortcut is None else self.nin_shortcut(x)
        return skip + h


class AttnBlock(nn.Module):
    """Single-head self-attention over all H*W positions, with a residual."""

    def __init__(self, ch: int, groups: int) -> None:
        super().__init__()
        self.norm = group_norm(ch, groups)
        self.q = nn.Conv2d(ch, ch, 1)
        self.k = nn.Conv2d(ch, ch, 1)
        self.v = nn.Conv2d(ch, ch, 1)
        self.proj_out = nn.Conv2d(ch, ch, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        y = self.norm(x)
        q = self.q(y).reshape(b, c, h * w).permute(0, 2, 1)
        k = self.k(y).reshape(b, c, h * w)
        v = self.v(y).reshape(b, c, h * w)
        weights = torch.softmax(torch.bmm(q, k) * (c ** -0.5), dim=2)
        out = torch.bmm(v, weights.permute(0, 2, 1)).reshape(b, c, h, w)
        return x + self.proj_out(out)


class Denoiser(nn.Module):
    """eps_theta: input [state || condition] (2C channels), output C channels, time t as a float tensor (N,)."""

    def __init__(self, in_ch: int, ch: int, out_ch: int, num_res_blocks: int, attention: bool,
                 groups: int = 32, dropout: float = 0.1) -> None:
        super().__init__()
        self.ch = ch
        temb_ch = ch * 4
        self.temb = nn.Module()
        self.temb.dense = nn.ModuleList([nn.Linear(ch, temb_ch), nn.Linear(temb_ch, temb_ch)])
        self.conv_in = nn.Conv2d(in_ch, ch, 3, padding=1)
        down = nn.Module()
        down.block = nn.ModuleList(
            [ResnetBlock(ch, ch, temb_ch, groups, dropout) for _ in range(num_res_blocks)])
        down.attn = nn.ModuleList()
        self.down = nn.ModuleList([down])
        self.mid = nn.Module()
        self.mid.block_1 = ResnetBlock(ch, ch, temb_ch, groups, dropout)
        self.mid.attn_1 = AttnBlock(ch, groups) if attention else nn.Identity()
        self.mid.block_2 = ResnetBlock(ch, ch, temb_ch, groups, dropout)
        up = nn.Module()
        up.block = nn.ModuleList(
            [ResnetBlock(2 * ch, ch, temb_ch, groups, dropout) for _ in range(num_res_blocks + 1)])
        up.attn = nn.ModuleList()
        self.up = nn.ModuleList([up])
        self.norm_out = group_norm(ch, groups)
        self.conv_out = nn.Conv2d(ch, out_ch, 3, padding=1)

    def time_embedding(self, t: torch.Tensor) -> torch.Tensor:
        emb = timestep_embedding(t, self.ch)
        return self.temb.dense[1](swish(self.temb.dense[0](emb)))

    def forward(self, x: torch.Tensor, t: torch.Tensor, temb: torch.Tensor | None = None) -> torch.Tensor:
        if temb is None:
            temb = self.time_embedding(t)
        skips = [self.conv_in(x)]
        for block in self.down[0].block:
            skips.append(block(skips[-1], temb))
        h = self.mid.block_2(self.mid.attn_1(self.mid.block_1(skips[-1], temb)), temb)
        for block in self.up[0].block:
            h = block(torch.cat([h, skips.pop()], dim=1), temb)
        return self.conv_out(swish(self.norm_out(h)))


def noise_schedule(steps: int = 20, beta_start: float = 1e-6, beta_end: float = 0.02) -> torch.Tensor:
    """alpha-bar_t for t = 0..steps-1, computed in float32 as the release does (spec 5.1)."""
    betas = torch.linspace(beta_start, beta_end, steps, dtype=torch.float64).float()
    return torch.cumprod(1.0 - betas, dim=0)


def ddim_timesteps(total: int, steps: int) -> list[int]:
    """The uniform DDIM sub-sequence visited in reverse: [10, 0] for total 20 and 2 steps."""
    skip = total // steps
    return list(range(0, total, skip))[::-1]


class DDIMSampler(nn.Module):
    """Deterministic (eta = 0) K-step DDIM over neck features, conditioned on those features.

    The start state is the condition noised to level `start_t` with a stored tensor instead of random noise,
    as the released model does, so that inference is deterministic and exports without random ops.
    """

    def __init__(self, total_steps: int, steps: int, start_t: int | None) -> None:
        super().__init__()
        self.register_buffer("alpha_bar", noise_schedule(total_steps), persistent=False)
        self.timesteps = ddim_timesteps(total_steps, steps)
        self.start_t = self.timesteps[0] if start_t is None else start_t

    def set_steps(self, steps: int) -> None:
        total = int(self.alpha_bar.numel())
        if not 1 <= steps <= total:
            raise ValueError(f"DDIM steps must be in 1..{total}, got {steps}")
        start_is_first = self.start_t == self.timesteps[0]
        self.timesteps = ddim_timesteps(total, steps)
        if start_is_first:
            self.start_t = self.timesteps[0]

    def _ab(self, t: int) -> torch.Tensor:
        return self.alpha_bar[t] if t >= 0 else torch.ones((), dtype=self.alpha_bar.dtype)

    def start(self, cond: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        ab = self._ab(self.start_t)
        return ab.sqrt() * cond + (1.0 - ab).sqrt() * noise

    def forward(self, denoiser: Denoiser, cond: torch.Tensor, noise: torch.Tensor) -> list[torch.Tensor]:
        """Returns every state of the chain: [X_start, X_{t_1}, ..., X_0]; the last one is the output."""
        x = self.start(cond, noise)
        states = [x]
        for i, t in enumerate(self.timesteps):
            t_next = self.timesteps[i + 1] if i + 1 < len(self.timesteps) else -1
            # the embedding of a constant t depends on weights only: batch 1, broadcast, folded at export
            tt = torch.full((1,), float(t), dtype=x.dtype, device=x.device)
            eps = denoiser(torch.cat([x, cond], dim=1), tt, denoiser.time_embedding(tt))
            ab, ab_next = self._ab(t), self._ab(t_next)
            x0 = (x - eps * (1.0 - ab).sqrt()) / ab.sqrt()
            x = ab_next.sqrt() * x0 + (1.0 - ab_next).sqrt() * eps
            states.append(x)
        return states
