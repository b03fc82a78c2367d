"""Tracking-oriented layer (paper eq. 7) and the released alignment layer that stands in for it.

The paper's layer: X_c = LN(MHA(X_b) + X_b); W = Conv(Cat(GAP(X_c), MAP(X_c))); X_d = X_c + gamma * W * X_c;
N_f^a = LN(FFN(X_d) + X_d), on tokens X_b = features + learned 2-D position code. The released DaDiff-BAN
runs that encoder but throws its output away (0 decoder layers), so what it computes is LN(x + pos)
(spec 5.4); `ReleasedAlignLayer` reproduces that while declaring the encoder under the released keys.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def position_tables(channels: int, max_size: int = 50) -> tuple[nn.Embedding, nn.Embedding]:
    """Learned row and column tables (U[0, 1) at construction, as the release)."""
    row, col = nn.Embedding(max_size, channels // 2), nn.Embedding(max_size, channels // 2)
    nn.init.uniform_(row.weight)
    nn.init.uniform_(col.weight)
    return row, col


def position_code(row_embed: nn.Embedding, col_embed: nn.Embedding, h: int, w: int) -> torch.Tensor:
    """pos[c, y, x] = col_embed[x, c] for c < C/2, row_embed[y, c - C/2] otherwise: (1, C, h, w)."""
    cols = col_embed.weight[:w]
    rows = row_embed.weight[:h]
    pos = torch.cat([cols[None, :, :].expand(h, w, -1), rows[:, None, :].expand(h, w, -1)], dim=-1)
    return pos.permute(2, 0, 1)[None]


def attend(mha: nn.MultiheadAttention, x: torch.Tensor, keys: torch.Tensor | None, training: bool) -> torch.Tensor:
    """Multi-head attention of the tokens `x` (B, N, C) over `keys` (B, M, C; `x` itself when None) with
    nn.MultiheadAttention's weights, written out with matmuls so that the FLOP counter sees the attention itself
    and the ONNX graph stays plain MatMul/Softmax."""
    b, n, c = x.shape
    heads = mha.num_heads
    if keys is None:
        m = n
        q, k, v = F.linear(x, mha.in_proj_weight, mha.in_proj_bias).chunk(3, dim=-1)
    else:
        m = keys.shape[1]
        q = F.linear(x, mha.in_proj_weight[:c], mha.in_proj_bias[:c])
        k, v = F.linear(keys, mha.in_proj_weight[c:], mha.in_proj_bias[c:]).chunk(2, dim=-1)
    q = q.reshape(b, n, heads, c // heads).transpose(1, 2)
    k, v = (t.reshape(b, m, heads, c // heads).transpose(1, 2) for t in (k, v))
    weights = torch.softmax(torch.matmul(q, k.transpose(-2, -1)) * (c // heads) ** -0.5, dim=-1)
    weights = F.dropout(weights, mha.dropout, training)
    out = torch.matmul(weights, v).transpose(1, 2).reshape(b, n, c)
    return mha.out_proj(out)


class TrackingOrientedEncoderLayer(nn.Module):
    """One encoder layer of eq. 7 on batch-first tokens (B, N, C); key names are the released ones."""

    def __init__(self, d_model: int, heads: int, ffn: int, reduction: int = 8, dropout: float = 0.1) -> None:
        super().__init__()
        hidden = max(d_model // reduction, 4)
        self.self_attn = nn.MultiheadAttention(d_model, heads, dropout=dropout, batch_first=True)
        self.norm0 = nn.LayerNorm(d_model)  # declared by the release, unused there and here
        self.norm1 = nn.LayerNorm(d_model)
        self.norm2 = nn.LayerNorm(d_model)
        # channel weights W: a bottleneck per pooled vector, then a 1x1 (transposed) conv over both
        self.linear11 = nn.Conv2d(d_model, hidden, 1, bias=False)
        self.linear22 = nn.Conv2d(hidden, d_model, 1, bias=False)
        self.linear33 = nn.Conv2d(d_model, hidden, 1, bias=False)
        self.linear44 = nn.Conv2d(hidden, d_model, 1, bias=False)
        self.conv = nn.Sequential(nn.ConvTranspose2d(2 * d_model, d_model, 1), nn.BatchNorm2d(d_model),
                                  nn.ReLU(inplace=True))
        self.gamma = nn.Parameter(torch.zeros(1))
        self.linear1 = nn.Linear(d_model, ffn)
        self.linear2 = nn.Linear(ffn, d_model)
        self.dropout = nn.Dropout(dropout)
        self.dropout_w = nn.Dropout(0.5)
        self.relu = nn.ReLU(inplace=True)

    def channel_weights(self, xc: torch.Tensor) -> torch.Tensor:
        """W from global average and max pooling over the tokens, per channel: (B, 1, C)."""
        avg = xc.mean(dim=1)[:, :, None, None]
        mx = xc.amax(dim=1)[:, :, None, None]
        wa = self.linear22(self.dropout_w(self.relu(self.linear11(avg))))
        wm = self.linear44(self.dropout_w(self.relu(self.linear33(mx))))
        w = self.conv(torch.cat([wa, wm], dim=1))
        return w.flatten(1)[:, None, :]

    def attention(self, x: torch.Tensor) -> torch.Tensor:
        return attend(self.self_attn, x, None, self.training)

    def forward(self, xb: torch.Tensor) -> torch.Tensor:
        attn = self.attention(xb)
        xc = self.norm1(xb + self.dropout(attn))
        xd = xc + self.gamma * self.channel_weights(xc) * xc
        ffn = self.linear2(self.dropout(self.relu(self.linear1(xd))))
        return self.norm2(xd + self.dropout(ffn))


class TrackingOrientedLayer(nn.Module):
    """The paper's layer (used by dadiff-lite): maps (B, C, H, W) to aligned features of the same shape."""

    def __init__(self, d_model: int, heads: int, ffn: int, reduction: int = 8) -> None:
        super().__init__()
        self.row_embed, self.col_embed = position_tables(d_model)
        self.layer = TrackingOrientedEncoderLayer(d_model, heads, ffn, reduction)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        pos = position_code(self.row_embed, self.col_embed, h, w)
        tokens = (x + pos).flatten(2).transpose(1, 2)  # (B, HW, C)
        out = self.layer(tokens)
        return out.transpose(1, 2).reshape(b, c, h, w)


class _Stack(nn.Module):
    def __init__(self, layers: list[nn.Module], norm: nn.Module) -> None:
        super().__init__()
        self.layers = nn.ModuleList(layers)
        self.norm = norm


class _ReleasedTransformer(nn.Module):
    """Container with the released key layout: encoder.layers.0.*, encoder.norm, decoder.norm."""

    def __init__(self, d_model: int, heads: int, ffn: int) -> None:
        super().__init__()
        self.encoder = _Stack([TrackingOrientedEncoderLayer(d_model, heads, ffn)], nn.LayerNorm(d_model))
        self.decoder = nn.Module()
        self.decoder.norm = nn.LayerNorm(d_model)


class ReleasedAlignLayer(nn.Module):
    """What the released DaDiff-BAN computes: LN(x + pos) per position (spec 5.4).

    The encoder is declared only so that released checkpoints load strictly; its output never reached the
    head in the release, so it is not run here (an ONNX export would prune it anyway).
    """

    def __init__(self, d_model: int = 256, heads: int = 8, ffn: int = 2048) -> None:
        super().__init__()
        self.row_embed, self.col_embed = position_tables(d_model)
        self.transformer = _ReleasedTransformer(d_model, heads, ffn)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        tokens = (x + position_code(self.row_embed, self.col_embed, h, w)).flatten(2).transpose(1, 2)
        out = self.transformer.decoder.norm(tokens)
        return out.transpose(1, 2).reshape(b, c, h, w)
