"""The transformer of the MASt3R backbone: 2-D rotary position embedding, attention, encoder and
decoder blocks (CroCo's block layout, as MASt3R's public checkpoints hold them).

Parameter names are those of the official checkpoint (`norm1`, `attn.qkv`, `cross_attn.projq`, ...),
so its state dict loads without renaming (inference.model.mast3r_weights). The rotary embedding is
plain tensor arithmetic: the official code's CUDA extension (curope) does not export to ONNX.

RoPE 2-D: each head's channels are split in two halves; the first half is rotated by the token's row,
the second by its column. Within a half of D channels, channel i (i < D/2) and channel i + D/2 form
a pair rotated by the angle  position * freq^(-2i/D)  (freq = 100 for MASt3R's "RoPE100").
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn

LAYER_NORM_EPS = 1e-6  # the checkpoint's norm layers (CroCo: partial(nn.LayerNorm, eps=1e-6))


def token_positions(h: int, w: int, device=None) -> torch.Tensor:
    """(h*w, 2) integer (row, column) of each token, row-major as the patch embedding flattens them."""
    rows = torch.arange(h, device=device).repeat_interleave(w)
    cols = torch.arange(w, device=device).repeat(h)
    return torch.stack([rows, cols], dim=1)


def rope_tables(h: int, w: int, head_dim: int, freq: float, device=None, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """cos and sin tables (h*w, head_dim) for a token grid: the first head_dim/2 columns follow the
    row position, the rest the column position (each half laid out [angles, angles])."""
    half = head_dim // 2
    inv_freq = 1.0 / (freq ** (torch.arange(0, half, 2, device=device).float() / half))  # (half/2,)
    pos = token_positions(h, w, device).float()
    tables = []
    for axis in (0, 1):
        angles = pos[:, axis : axis + 1] * inv_freq[None, :]  # (N, half/2)
        angles = torch.cat([angles, angles], dim=1)  # (N, half)
        tables.append(angles)
    angles = torch.cat(tables, dim=1).to(dtype)  # (N, head_dim)
    return angles.cos(), angles.sin()


def _halves(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    # Slices rather than chunk: the exporter's constant folding skips (and logs) multi-output Splits.
    n = x.shape[-1] // 2
    return x[..., :n], x[..., n:]


def _rotate_half(x: torch.Tensor) -> torch.Tensor:
    a, b = _halves(x)
    return torch.cat([-b, a], dim=-1)


def apply_rope(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """x (B, heads, N, head_dim) rotated per token by the tables of `rope_tables`."""
    (y, xx), (cy, cx), (sy, sx) = _halves(x), _halves(cos), _halves(sin)
    return torch.cat([y * cy + _rotate_half(y) * sy, xx * cx + _rotate_half(xx) * sx], dim=-1)


class Mlp(nn.Module):
    """Linear -> GELU (exact) -> Linear; names fc1, fc2 as in the checkpoint."""

    def __init__(self, dim: int, hidden: int, out: int | None = None):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, out or dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


def _attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Softmax attention of (B, heads, N, d) queries over (B, heads, M, d) keys; returns (B, N, heads*d)."""
    b, heads, n, d = q.shape
    attn = torch.softmax((q @ k.transpose(-2, -1)) * (1.0 / math.sqrt(d)), dim=-1)
    return (attn @ v).transpose(1, 2).reshape(b, n, heads * d)


class SelfAttention(nn.Module):
    """One qkv projection (with bias), rotary positions on q and k, output projection."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]
        return self.proj(_attend(apply_rope(q, cos, sin), apply_rope(k, cos, sin), v))


class CrossAttention(nn.Module):
    """Queries from one view, keys and values from the other; rotary positions of each side's tokens."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.projq = nn.Linear(dim, dim)
        self.projk = nn.Linear(dim, dim)
        self.projv = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)

    def _split(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        return x.reshape(b, n, self.heads, c // self.heads).transpose(1, 2)

    def forward(self, x: torch.Tensor, memory: torch.Tensor, cos, sin, mem_cos, mem_sin) -> torch.Tensor:
        q = apply_rope(self._split(self.projq(x)), cos, sin)
        k = apply_rope(self._split(self.projk(memory)), mem_cos, mem_sin)
        return self.proj(_attend(q, k, self._split(self.projv(memory))))


class EncoderBlock(nn.Module):
    """Pre-norm self-attention and MLP (ratio 4)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.attn = SelfAttention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.mlp = Mlp(dim, 4 * dim)

    def forward(self, x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), cos, sin)
        return x + self.mlp(self.norm2(x))


class DecoderBlock(nn.Module):
    """Self-attention, cross-attention to the other view's tokens (normalised by norm_y), MLP."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.attn = SelfAttention(dim, heads)
        self.cross_attn = CrossAttention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.norm3 = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)
        self.mlp = Mlp(dim, 4 * dim)
        self.norm_y = nn.LayerNorm(dim, eps=LAYER_NORM_EPS)

    def forward(self, x: torch.Tensor, other: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        # Both views share one token grid here (the same coarse size), hence one pair of tables.
        x = x + self.attn(self.norm1(x), cos, sin)
        mem = self.norm_y(other)
        x = x + self.cross_attn(self.norm2(x), mem, cos, sin, cos, sin)
        return x + self.mlp(self.norm3(x))


class PatchEmbed(nn.Module):
    """16x16 patches to tokens (B, h*w, dim) by one strided convolution (`patch_embed.proj`)."""

    def __init__(self, dim: int, patch: int):
        super().__init__()
        self.patch = patch
        self.proj = nn.Conv2d(3, dim, patch, stride=patch)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.proj(images).flatten(2).transpose(1, 2)
