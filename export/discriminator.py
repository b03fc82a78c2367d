"""Successive distribution discriminator: judges day (0) or night (1) for every state of the DDIM chain.

Built like the released discriminator (a small pre-norm ViT on the channel-softmaxed feature map, spec 10.3),
but as the paper asks (eq. 8) it sees every diffusion state X_t, and a learned embedding of t tells it which
step it is judging. There is no gradient-reversal layer: training uses the usual two-player losses instead
(spec 12, item 4).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class NoisyAttention(nn.Module):
    """Multi-head self-attention whose input gets per-token Gaussian noise scaled by a learned scalar (init 0)."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=False)
        self.proj = nn.Linear(dim, dim)
        self.noise_strength = nn.Parameter(torch.zeros(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.training:
            x = x + torch.randn_like(x[..., :1]) * self.noise_strength
        b, n, c = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class Block(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = NoisyAttention(dim, heads)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class SuccessiveDiscriminator(nn.Module):
    def __init__(self, in_ch: int, total_steps: int = 20, size: int = 32, patch: int = 4, dim: int = 128,
                 depth: int = 2, heads: int = 4) -> None:
        super().__init__()
        self.size = size
        self.patch_embed = nn.Conv2d(in_ch, dim, patch, stride=patch)
        tokens = (size // patch) ** 2
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, tokens + 1, dim))
        self.t_embed = nn.Embedding(total_steps + 1, dim)  # index t + 1; 0 stands for the final output (t = -1)
        self.blocks = nn.ModuleList([Block(dim, heads) for _ in range(depth)])
        self.norm = nn.LayerNorm(dim)
        self.out = nn.Linear(dim, 1)
        for p in (self.cls_token, self.pos_embed):
            nn.init.trunc_normal_(p, std=0.02)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    def judge(self, feature: torch.Tensor, t: int) -> torch.Tensor:
        """One state -> a (B,) night-ness score (day label 0, night 1)."""
        x = F.interpolate(feature, size=(self.size, self.size), mode="bilinear", align_corners=True)
        x = torch.softmax(x, dim=1)
        tokens = self.patch_embed(x).flatten(2).transpose(1, 2)
        t_idx = torch.full((x.shape[0],), t + 1, dtype=torch.long, device=x.device)
        cls = self.cls_token.expand(x.shape[0], -1, -1) + self.t_embed(t_idx)[:, None, :]
        h = torch.cat([cls, tokens], dim=1) + self.pos_embed
        for block in self.blocks:
            h = block(h)
        return self.out(self.norm(h[:, 0]))[:, 0]

    def forward(self, states: list[torch.Tensor], timesteps: list[int]) -> torch.Tensor:
        """Scores for every state of a chain: (B, len(states)). `timesteps[i]` is the noise level of states[i]."""
        if len(states) != len(timesteps):
            raise ValueError(f"{len(states)} states but {len(timesteps)} timesteps")
        return torch.stack([self.judge(s, t) for s, t in zip(states, timesteps, strict=True)], dim=1)


def chain_timesteps(start_t: int, timesteps: list[int]) -> list[int]:
    """Noise level of each state the sampler returns: [start, after step 1, ..., final (-1)]."""
    return [start_t, *timesteps[1:], -1]


def adversarial_loss(scores: torch.Tensor, label: float) -> torch.Tensor:
    """Eq. 8: sum over the chain's timesteps of (D(X_t) - l)^2, averaged over the batch."""
    return ((scores - label) ** 2).sum(dim=1).mean()
