"""Stage 1 affine transform: canonical point maps to metric ones, X_t = S * X + T.

- Scaling S (3 values, shared by both views): an MLP on the averaged self-attention of the left
  view's tokens, the averaged cross-attention from left to right tokens (shared W^Q, W^K, W^V, the
  paper's Eq. 2) and a NeRF positional encoding of the focal lengths and the baseline.
  The MLP's last layer starts at zero and S = baseline * exp(r tanh(MLP / r)) (r the
  scale_log_range bound, exp(MLP) near zero): an untrained model scales a
  canonical point map (mean distance 1) by the baseline, the right order for a rig whose cameras
  stand about as far from the actors as from each other. For metric point maps (the MASt3R metric
  checkpoint; Stage1Config.scale_reference = "one") S = exp(r tanh(MLP / r)) starts at 1.
- Translation T (per pixel): a RAFT-style ConvGRU at 1/stride of the coarse size. Each iteration
  projects the current points S X + T of view i into the other view j, samples j's features there
  (4-D grid_sample), correlates them with i's, and updates T by at most translation_step
  baselines per axis (tanh). Its output layer starts at zero, so an untrained model leaves T = 0.
  Translations are predicted in units of the baseline.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.config import Stage1Config
from inference.model.backbone import PointMaps, confidence_to_opacity
from inference.model.scale_search import ScaleSearch, rescale
from inference.model.geometry import (
    in_image,
    invert_pose,
    pixel_rays,
    project,
    resize_intrinsics,
    sample,
    transform_points,
)


@dataclass
class AffineOutput:
    points_left: torch.Tensor  # (B, 3, H, W) X_t of the left view, left camera frame, metres
    points_right: torch.Tensor  # (B, 3, H, W) X_t of the right view, left camera frame, metres
    scale: torch.Tensor  # (B, 3) S
    translation_left: torch.Tensor  # (B, 3, H, W) T
    translation_right: torch.Tensor


def positional_encoding(x: torch.Tensor, frequencies: int) -> torch.Tensor:
    """NeRF's encoding of (B, D) values: [x, sin(2^k pi x), cos(2^k pi x)] for k < frequencies."""
    scales = (2.0 ** torch.arange(frequencies, dtype=x.dtype, device=x.device)) * math.pi
    xs = x[..., None] * scales  # (B, D, L)
    return torch.cat([x, xs.sin().flatten(1), xs.cos().flatten(1)], dim=1)


class ScaleHead(nn.Module):
    def __init__(self, cfg: Stage1Config, token_dim: int):
        super().__init__()
        d = cfg.attention_dim
        self.heads = cfg.attention_heads
        self.proj = nn.Linear(token_dim, d)
        self.wq = nn.Linear(d, d)
        self.wk = nn.Linear(d, d)
        self.wv = nn.Linear(d, d)
        self.frequencies = cfg.pe_frequencies
        self.log_range = cfg.scale_log_range
        self.per_baseline = cfg.scale_reference == "baseline"
        pe_dim = 5 * (1 + 2 * cfg.pe_frequencies)
        self.mlp = nn.Sequential(
            nn.Linear(2 * d + pe_dim, cfg.mlp_hidden), nn.ReLU(), nn.Linear(cfg.mlp_hidden, cfg.mlp_hidden), nn.ReLU(), nn.Linear(cfg.mlp_hidden, 3)
        )
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def _attend(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        b, n, c = q.shape
        m = k.shape[1]
        h = self.heads
        d = c // h
        q = q.reshape(b, n, h, d).transpose(1, 2)
        k = k.reshape(b, m, h, d).transpose(1, 2)
        v = v.reshape(b, m, h, d).transpose(1, 2)
        attn = torch.softmax((q @ k.transpose(-1, -2)) * (1.0 / math.sqrt(d)), dim=-1)
        return (attn @ v).transpose(1, 2).reshape(b, n, c)

    def forward(self, tokens_left, tokens_right, focal_left, focal_right, baseline) -> torch.Tensor:
        f_l = self.proj(tokens_left)
        f_r = self.proj(tokens_right)
        q_l = self.wq(f_l)
        f_s = self._attend(q_l, self.wk(f_l), self.wv(f_l)).mean(dim=1)
        f_c = self._attend(q_l, self.wk(f_r), self.wv(f_r)).mean(dim=1)
        # Focal lengths are normalised by the image width (resolution-free); the baseline enters as its log.
        e = positional_encoding(torch.cat([focal_left, focal_right, torch.log(baseline.clamp(min=1e-6))[:, None]], dim=1), self.frequencies)
        raw = self.mlp(torch.cat([f_s, f_c, e], dim=1))
        s = torch.exp(self.log_range * torch.tanh(raw / self.log_range))
        # Canonical point maps start scaled by the baseline; metric ones (MASt3R's) at S = 1.
        return baseline[:, None] * s if self.per_baseline else s


class ConvGRU(nn.Module):
    def __init__(self, hidden: int, inputs: int):
        super().__init__()
        self.convz = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)
        self.convr = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)
        self.convq = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        hx = torch.cat([h, x], dim=1)
        z = torch.sigmoid(self.convz(hx))
        r = torch.sigmoid(self.convr(hx))
        q = torch.tanh(self.convq(torch.cat([r * h, x], dim=1)))
        return (1 - z) * h + z * q


class TranslationGRU(nn.Module):
    def __init__(self, cfg: Stage1Config, token_dim: int):
        super().__init__()
        c = cfg.feature_dim
        self.cfg = cfg
        # E_c: the lightweight convolutional encoder of the backbone's token features.
        self.token_proj = nn.Conv2d(token_dim, c, 1)
        self.encoder = nn.Sequential(nn.Conv2d(c, c, 3, padding=1), nn.ReLU(), nn.Conv2d(c, c, 3, padding=1))
        self.context = nn.Conv2d(c, cfg.hidden_dim + c, 3, padding=1)
        motion_in = c + 1 + 3 + 3 + 1  # other view's features, correlation, points, translation, visibility
        self.motion = nn.Sequential(nn.Conv2d(motion_in, 64, 3, padding=1), nn.ReLU(), nn.Conv2d(64, 64, 3, padding=1), nn.ReLU())
        self.gru = ConvGRU(cfg.hidden_dim, c + 64)
        self.delta = nn.Sequential(nn.Conv2d(cfg.hidden_dim, 64, 3, padding=1), nn.ReLU(), nn.Conv2d(64, 3, 3, padding=1))
        nn.init.zeros_(self.delta[-1].weight)
        nn.init.zeros_(self.delta[-1].bias)

    def features(self, tokens: torch.Tensor, grid: tuple[int, int], size: tuple[int, int]) -> torch.Tensor:
        b, _, c = tokens.shape
        fmap = tokens.transpose(1, 2).reshape(b, c, grid[0], grid[1])
        fmap = F.interpolate(self.token_proj(fmap), size=size, mode="bilinear", align_corners=False)
        return self.encoder(fmap)

    def forward(self, points, feats, other_feats, to_other, other_K, baseline) -> torch.Tensor:
        """points (N, 3, h, w) = S X at the GRU size; `to_other` maps them into the other camera,
        whose intrinsics `other_K` are for the GRU size. Returns T (N, 3, h, w) in metres."""
        _, _, h, w = points.shape
        unit = baseline.reshape(-1, 1, 1, 1)
        net, ctx = torch.split(self.context(feats), [self.cfg.hidden_dim, feats.shape[1]], dim=1)
        net = torch.tanh(net)
        ctx = torch.relu(ctx)
        t = torch.zeros_like(points)
        scale = 1.0 / math.sqrt(feats.shape[1])
        for _ in range(self.cfg.iterations):
            x = points + t
            uv, z = project(transform_points(to_other, x), other_K)
            sampled = sample(other_feats, uv)
            visible = in_image(uv, z, w, h)
            corr = (sampled * feats).sum(dim=1, keepdim=True) * scale
            motion = self.motion(torch.cat([sampled * visible, corr * visible, x / unit, t / unit, visible], dim=1))
            net = self.gru(net, torch.cat([ctx, motion], dim=1))
            t = t + self.cfg.translation_step * torch.tanh(self.delta(net)) * unit
        return t


def _weighted_pool(x: torch.Tensor, weight: torch.Tensor, stride: int) -> torch.Tensor:
    """Average-pool a point map, ignoring low-weight (invalid) pixels."""
    if stride == 1:
        return x
    num = F.avg_pool2d(x * weight, stride)
    den = F.avg_pool2d(weight, stride)
    return num / den.clamp(min=1e-6)


class AffineTransform(nn.Module):
    """X_t = S X + T for both views. With affine='bypass' it returns the points unchanged (metric input)."""

    def __init__(self, cfg: Stage1Config, token_dim: int, coarse_size: tuple[int, int]):
        super().__init__()
        self.cfg = cfg
        self.coarse_size = coarse_size
        self.gru_size = (coarse_size[0] // cfg.stride, coarse_size[1] // cfg.stride)
        if cfg.affine == "learned":
            self.scale_head = ScaleHead(cfg, token_dim)
            self.translation = TranslationGRU(cfg, token_dim)
            if cfg.scale_search:
                self.scale_search = ScaleSearch(cfg.scale_search, cfg.scale_search_range, cfg.scale_search_floor)

    def forward(self, pm: PointMaps, left_K: torch.Tensor, right_K: torch.Tensor, right_to_left: torch.Tensor,
                left_image: torch.Tensor | None = None, right_image: torch.Tensor | None = None) -> AffineOutput:
        """Intrinsics and images are for the coarse size; the images serve the scale search (cfg.scale_search)."""
        if self.cfg.affine == "bypass":
            zeros = torch.zeros_like(pm.points_left)
            one = torch.ones(pm.points_left.shape[0], 3, dtype=zeros.dtype, device=zeros.device)
            return AffineOutput(pm.points_left, pm.points_right, one, zeros, zeros)
        b = pm.points_left.shape[0]
        cw, ch = self.coarse_size
        gw, gh = self.gru_size
        # The relative transform's translation is the right camera's centre seen from the left camera.
        baseline = torch.sqrt((right_to_left[:, :3, 3] ** 2).sum(-1))
        focal_l = torch.stack([left_K[:, 0, 0] / cw, left_K[:, 1, 1] / ch], dim=1)
        focal_r = torch.stack([right_K[:, 0, 0] / cw, right_K[:, 1, 1] / ch], dim=1)
        s = self.scale_head(pm.tokens_left, pm.tokens_right, focal_l, focal_r, baseline)  # (B, 3)
        if self.cfg.isotropic_scale:
            s = s[:, 2:3].repeat(1, 3)

        # Both views in one batch of 2B: view i looks into the other view j.
        w_l = pm.conf_left - 1.0
        w_r = pm.conf_right - 1.0
        pts = torch.cat([_weighted_pool(pm.points_left, w_l, self.cfg.stride), _weighted_pool(pm.points_right, w_r, self.cfg.stride)], dim=0)
        s2 = torch.cat([s, s], dim=0).reshape(2 * b, 3, 1, 1)
        feats = self.translation.features(torch.cat([pm.tokens_left, pm.tokens_right], dim=0), pm.token_grid, (gh, gw))
        other_feats = torch.cat([feats[b:], feats[:b]], dim=0)
        left_to_right = invert_pose(right_to_left)
        eye = torch.eye(4, dtype=left_to_right.dtype, device=left_to_right.device).expand(b, 4, 4)
        to_other = torch.cat([left_to_right, eye], dim=0)  # points are in the left frame
        other_K = torch.cat([right_K, left_K], dim=0)
        other_K = resize_intrinsics(other_K, (cw, ch), (gw, gh))
        t = self.translation(pts * s2, feats, other_feats, to_other, other_K, torch.cat([baseline, baseline], dim=0))
        t = F.interpolate(t, size=(ch, cw), mode="bilinear", align_corners=False)
        t_l, t_r = t[:b], t[b:]
        if self.cfg.translation_gate:
            # T scaled by each point's opacity to the power gate: the backbone's unsure points (on
            # the held-out takes, people: opacity 0.1 against 0.8) keep their place along their
            # ray instead of being moved by a translation field learned mostly from the rest.
            p = self.cfg.translation_gate
            t_l = t_l * confidence_to_opacity(pm.conf_left) ** p
            t_r = t_r * confidence_to_opacity(pm.conf_right) ** p
        sv = s.reshape(b, 3, 1, 1)
        if self.cfg.translation_along_rays:
            # Each pixel's ray from the calibration (the left frame; no backbone's units involved).
            rot = right_to_left[:, :3, :3]
            t_l = _along(t_l, pixel_rays(left_K, cw, ch))
            t_r = _along(t_r, torch.einsum("bij,bjhw->bihw", rot, pixel_rays(right_K, cw, ch)))
        points_left, points_right = sv * pm.points_left + t_l, sv * pm.points_right + t_r
        if self.cfg.scale_search:
            if left_image is None or right_image is None:
                raise ValueError("the scale search needs both coarse images")
            k = self.scale_search(points_left, points_right, left_image, right_image, left_K, right_K, right_to_left)
            points_left, points_right = rescale(points_left, points_right, k, right_to_left)
            s = s * k[:, None]
        return AffineOutput(points_left, points_right, s, t_l, t_r)


def _along(t: torch.Tensor, ray: torch.Tensor) -> torch.Tensor:
    """The part of t (B, 3, H, W) along ray (B, 3, H, W, from the camera's centre to the point)."""
    unit = ray / torch.sqrt((ray ** 2).sum(1, keepdim=True)).clamp(min=1e-9)
    return (t * unit).sum(1, keepdim=True) * unit
