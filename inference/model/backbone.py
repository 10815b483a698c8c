"""Stage 1 point initialisation: the backbone interface and two backbones.

A backbone sees the two source images at the coarse size and returns, as MASt3R does, one point map
per view *in the left camera's frame* (MASt3R's `pts3d` and `pts3d_in_other_view`), per-pixel
confidences (DUSt3R convention: 1 + exp(x), so >= 1) and its decoder tokens, which stage 1's
attention and convolutional encoder read. Descriptors are optional (MASt3R has them; the
backbones here do not need them).

- `TinyBackbone`: a small trainable CroCo-style network (shared ViT encoder, a decoder whose blocks
  cross-attend to the other view, a linear head per patch predicting points around nominal pinhole
  rays). A few million parameters.
- `OracleBackbone`: turns ground-truth depth (the simulator's) into point maps, metric or
  normalised to canonical scale as MASt3R normalises its own, so everything after point
  initialisation can be tested without a trained backbone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.config import BackboneConfig
from inference.model.geometry import transform_points, unproject_depth


@dataclass
class PointMaps:
    """What a backbone returns. Shapes: B batch, (H, W) the coarse size, (h, w) the token grid."""

    points_left: torch.Tensor  # (B, 3, H, W) left view's points, left camera frame
    points_right: torch.Tensor  # (B, 3, H, W) right view's points, left camera frame
    conf_left: torch.Tensor  # (B, 1, H, W) >= 1
    conf_right: torch.Tensor  # (B, 1, H, W) >= 1
    tokens_left: torch.Tensor  # (B, h*w, C) decoder tokens
    tokens_right: torch.Tensor  # (B, h*w, C)
    token_grid: tuple[int, int]  # (h, w)
    descriptors_left: torch.Tensor | None = None  # (B, D, H, W), MASt3R's local features
    descriptors_right: torch.Tensor | None = None
    planes: "PlaneVolume | None" = None  # a plane-sweep backbone's depth distribution (training only)


@dataclass
class PlaneVolume:
    """The depth distribution of a plane-sweep backbone: every pixel of its volume (h, w) at each of
    its D planes, with the probability the backbone gives that plane. Training renders it (see
    inference.train.stages); inference uses only the expected depth."""

    points_left: torch.Tensor  # (B, D, 3, h, w) left frame, baseline units
    points_right: torch.Tensor  # (B, D, 3, h, w) left frame, baseline units
    prob_left: torch.Tensor  # (B, D, h, w)
    prob_right: torch.Tensor  # (B, D, h, w)


def confidence_to_opacity(conf: torch.Tensor) -> torch.Tensor:
    """Map a DUSt3R confidence (>= 1) to an opacity in [0, 1): 1 - 1/conf."""
    return 1.0 - 1.0 / conf.clamp(min=1.0)


class Backbone(nn.Module):
    """Interface: forward(left, right, left_K, right_K, right_to_left, left_depth, right_depth) -> PointMaps.

    Images (B, 3, H, W) in [0, 1] at the coarse size, intrinsics for that size, `right_to_left` the
    rigid transform from the right camera's frame to the left's. Learned backbones ignore the
    calibration and the depth (MASt3R does); the oracle needs both.
    """

    token_dim: int
    needs_depth: bool = False
    # The images it reads are this multiple of the coarse size (intrinsics for that size); its point
    # maps, confidences and token grid are at the coarse size whatever it reads.
    input_scale: int = 1


# -- tiny trainable backbone ---------------------------------------------------------------------


def sincos_2d(h: int, w: int, dim: int) -> torch.Tensor:
    """Fixed 2D sine-cosine position embedding (h*w, dim), as in MAE/CroCo."""
    quarter = dim // 4
    omega = 1.0 / (10000 ** (torch.arange(quarter, dtype=torch.float32) / quarter))
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    ax = xs.reshape(-1, 1) * omega
    ay = ys.reshape(-1, 1) * omega
    emb = torch.cat([ax.sin(), ax.cos(), ay.sin(), ay.cos()], dim=1)
    if emb.shape[1] < dim:
        emb = F.pad(emb, (0, dim - emb.shape[1]))
    return emb


class Attention(nn.Module):
    """Multi-head attention; queries from x, keys and values from `context` (self-attention when None)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        b, n, c = x.shape
        ctx = x if context is None else context
        m = ctx.shape[1]
        d = c // self.heads
        q = self.q(x).reshape(b, n, self.heads, d).transpose(1, 2)
        k, v = self.kv(ctx).reshape(b, m, 2, self.heads, d).permute(2, 0, 3, 1, 4)
        attn = torch.softmax((q @ k.transpose(-1, -2)) * (1.0 / math.sqrt(d)), dim=-1)
        out = (attn @ v).transpose(1, 2).reshape(b, n, c)
        return self.proj(out)


class EncoderBlock(nn.Module):
    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class DecoderBlock(nn.Module):
    """Self-attention within a view, then cross-attention to the other view (CroCo/DUSt3R decoder)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.self_attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim)
        self.norm_ctx = nn.LayerNorm(dim)
        self.cross_attn = Attention(dim, heads)
        self.norm3 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def forward(self, x: torch.Tensor, other: torch.Tensor) -> torch.Tensor:
        x = x + self.self_attn(self.norm1(x))
        x = x + self.cross_attn(self.norm2(x), self.norm_ctx(other))
        return x + self.mlp(self.norm3(x))


class TinyBackbone(Backbone):
    """A small two-view point-map network in the DUSt3R mould (about 4 M parameters by default)."""

    def __init__(self, cfg: BackboneConfig, coarse_size: tuple[int, int]):
        super().__init__()
        self.cfg = cfg
        p = cfg.patch
        w, h = coarse_size
        self.grid = (h // p, w // p)
        self.token_dim = cfg.dim
        self.patch_embed = nn.Conv2d(3, cfg.dim, p, stride=p)
        self.register_buffer("pos", sincos_2d(self.grid[0], self.grid[1], cfg.dim), persistent=False)
        self.view_embed = nn.Parameter(torch.zeros(2, cfg.dim))
        self.encoder = nn.ModuleList([EncoderBlock(cfg.dim, cfg.heads) for _ in range(cfg.encoder_blocks)])
        self.enc_norm = nn.LayerNorm(cfg.dim)
        self.decoder = nn.ModuleList([DecoderBlock(cfg.dim, cfg.heads) for _ in range(cfg.decoder_blocks)])
        self.dec_norm = nn.LayerNorm(cfg.dim)
        # Per patch: p*p pixels of (x, y, z, confidence) residuals; pixel shuffle puts them in place.
        self.head = nn.Linear(cfg.dim, 4 * p * p)
        nn.init.normal_(self.view_embed, std=0.02)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        # Points are predicted around the rays of a nominal pinhole (60 degrees across): an untrained
        # backbone sees a smooth plane one unit ahead rather than noise, which keeps stage 1 and
        # the depth initialisation well-conditioned from the first training step.
        f = 0.5 * w / math.tan(math.radians(30.0))
        v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
        self.register_buffer("rays", torch.stack([(u - (w - 1) / 2) / f, (v - (h - 1) / 2) / f], 0)[None], persistent=False)

    def _encode(self, images: torch.Tensor) -> torch.Tensor:
        x = self.patch_embed(images * 2.0 - 1.0).flatten(2).transpose(1, 2) + self.pos
        for blk in self.encoder:
            x = blk(x)
        return self.enc_norm(x)

    def _head(self, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b = tokens.shape[0]
        h, w = self.grid
        p = self.cfg.patch
        out = self.head(tokens)  # (B, h*w, p*p*4) ordered (pixel, channel)
        # pixel_shuffle wants channel index c * p*p + sub-pixel, i.e. (B, 4, p*p, h, w) flattened.
        out = out.reshape(b, h, w, p * p, 4).permute(0, 4, 3, 1, 2).reshape(b, 4 * p * p, h, w)
        out = F.pixel_shuffle(out, p)
        depth = torch.exp(out[:, 2:3].clamp(-10.0, 10.0))
        points = torch.cat([(self.rays + out[:, 0:2]) * depth, depth], dim=1)
        conf = 1.0 + torch.exp(out[:, 3:4].clamp(max=20.0))
        return points, conf

    def forward(self, left, right, left_K=None, right_K=None, right_to_left=None, left_depth=None, right_depth=None) -> PointMaps:
        b = left.shape[0]
        enc = self._encode(torch.cat([left, right], dim=0))
        x_l = enc[:b] + self.view_embed[0]
        x_r = enc[b:] + self.view_embed[1]
        for blk in self.decoder:
            # Both views update from the other's previous state, as in CroCo's two-branch decoder.
            x_l, x_r = blk(x_l, x_r), blk(x_r, x_l)
        x_l = self.dec_norm(x_l)
        x_r = self.dec_norm(x_r)
        pts_l, conf_l = self._head(x_l)
        pts_r, conf_r = self._head(x_r)
        return PointMaps(pts_l, pts_r, conf_l, conf_r, x_l, x_r, self.grid)


# -- oracle backbone from ground-truth depth -----------------------------------------------------


class OracleBackbone(Backbone):
    """Point maps from ground-truth depth (0 where nothing was hit).

    Tokens are the raw patches (pixel-unshuffled image), so stage 1 still has image features.
    """

    needs_depth = True

    def __init__(self, cfg: BackboneConfig, coarse_size: tuple[int, int]):
        super().__init__()
        self.cfg = cfg
        p = cfg.patch
        w, h = coarse_size
        self.grid = (h // p, w // p)
        self.token_dim = 3 * p * p

    def forward(self, left, right, left_K, right_K, right_to_left, left_depth=None, right_depth=None) -> PointMaps:
        if left_depth is None or right_depth is None:
            raise ValueError("the oracle backbone needs left_depth and right_depth")
        valid_l = (left_depth > 0).to(left.dtype)
        valid_r = (right_depth > 0).to(left.dtype)
        pts_l = unproject_depth(left_depth, left_K)
        pts_r = transform_points(right_to_left, unproject_depth(right_depth, right_K)) * valid_r
        if self.cfg.oracle_scale == "canonical":
            # MASt3R's normalisation: divide by the mean distance of all valid points to the origin.
            dist = (pts_l.norm(dim=1, keepdim=True) * valid_l).sum((1, 2, 3)) + (pts_r.norm(dim=1, keepdim=True) * valid_r).sum((1, 2, 3))
            count = valid_l.sum((1, 2, 3)) + valid_r.sum((1, 2, 3))
            scale = (dist / count.clamp(min=1.0)).clamp(min=1e-6).reshape(-1, 1, 1, 1)
            pts_l = pts_l / scale
            pts_r = pts_r / scale
        # Valid pixels get a high confidence (opacity 0.999), holes the minimum (opacity 0).
        conf_l = 1.0 + 999.0 * valid_l
        conf_r = 1.0 + 999.0 * valid_r
        p = self.cfg.patch
        tok_l = F.pixel_unshuffle(left, p).flatten(2).transpose(1, 2)
        tok_r = F.pixel_unshuffle(right, p).flatten(2).transpose(1, 2)
        return PointMaps(pts_l, pts_r, conf_l, conf_r, tok_l, tok_r, self.grid)
