"""Depth initialisation: forward-splat the transformed point maps of both views into the target view.

Every point is splatted onto the (2r+1)^2 target pixels around its projection with a smooth kernel
k(d) = (1 - d^2/rho^2)^2 (rho = r + 1/2, so its support always lies inside the window) times the
point's opacity: its coverage of the pixel. The contributions at a pixel then blend by weight after
a soft visibility test (`zbuffer`):

- "occlusion" (the default): a contribution keeps exp(-gain C) of its weight, where C is the
  coverage at that pixel nearer than it by more than a margin (35 % in depth). C is read from a
  histogram of the pixel's coverage over log-depth bins (each contribution split linearly between
  its two nearest bins, a cumulative sum over the bins, read back between bins), so it is
  continuous in every point, and it is linear in the coverages: a faint splat (the rim of a kernel,
  whose weight turns fast with its position) can only occlude as much as it covers. Points of one
  surface, within the margin, blend by their weights. Radius 2 covers the gaps between stage 1's
  points (about 2 target pixels apart), so a nearer surface occludes with full coverage.
- "reference": the z-buffer of models saved before "occlusion": each contribution is preferred by
  exp(-clip(log(z / z_ref) / tolerance, +-8)) against a front-leaning mean depth z_ref of the pixel.
  A rim splat 8 nats of preference ahead wins against a well-covered surface, so where the two
  compete the depth swings with the rim's weight, and z_ref feeds back through the clip with a gain
  of 1 / tolerance: trained stage-1 depth with sharp edges made ONNX Runtime's float rounding
  (1e-5 m) move its depth by centimetres (docs/model.md).

Pixels no point reached are filled by push-pull interpolation. Everything is scatter/gather on flat
tensors and a cumulative sum: exportable to ONNX (ScatterElements, GatherElements, CumSum).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.config import DepthInitConfig
from inference.model.geometry import project, resize_intrinsics, transform_points

FRONT_RANGE = 8.0  # "reference": a nearer surface is preferred by at most e^8 (in units of weight)


@dataclass
class SplatDepth:
    depth: torch.Tensor  # (B, 1, H, W) blended front-surface depth, holes filled
    coverage: torch.Tensor  # (B, 1, H, W) sum of blended splat weights (0 where no point reached)
    raw_depth: torch.Tensor  # (B, 1, H, W) before hole filling (0 in holes)


def splat_depth(
    points: torch.Tensor,
    opacity: torch.Tensor,
    to_target: torch.Tensor,
    target_K: torch.Tensor,
    size: tuple[int, int],
    cfg: DepthInitConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Splat points (B, 3, N) with opacities (B, 1, N) into a (W, H) target. Returns raw depth and coverage."""
    b = points.shape[0]
    w, h = size
    radius = cfg.radius
    uv, z = project(transform_points(to_target, points), target_K)  # (B, 2, N), (B, 1, N)
    u, v, z = uv[:, 0], uv[:, 1], z[:, 0]
    alpha = opacity[:, 0]
    if cfg.opacity_power != 1.0:
        # opacity ** p; p = 0: every point that has any opacity covers fully.
        alpha = alpha.clamp(min=0.0) ** cfg.opacity_power if cfg.opacity_power > 0 else (alpha > 0).to(alpha.dtype)
    u0 = torch.round(u)
    v0 = torch.round(v)
    rho2 = (radius + 0.5) ** 2
    # Every window offset at once, offset-major (dy outer, dx inner): (B, K, N) -> (B, K * N). One
    # broadcast op per step instead of one per offset keeps the exported graph small.
    offsets = torch.arange(-radius, radius + 1, dtype=u.dtype, device=u.device)
    dy = offsets.repeat_interleave(2 * radius + 1)[None, :, None]
    dx = offsets.repeat(2 * radius + 1)[None, :, None]
    px = u0[:, None] + dx
    py = v0[:, None] + dy
    du = px - u[:, None]
    dv = py - v[:, None]
    d2 = du * du + dv * dv
    e = (1.0 - d2 / rho2).clamp(min=0.0)
    k = e * e
    zk = z[:, None].expand_as(k)
    inside = (px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1) & (zk > 1e-6)
    weight = torch.where(inside, alpha[:, None] * k, torch.zeros_like(k)).reshape(b, -1)
    index = torch.where(inside, py * w + px, torch.zeros_like(px)).to(torch.int64).reshape(b, -1)
    depth = torch.where(inside, zk, torch.zeros_like(zk)).reshape(b, -1)
    total = torch.zeros(b, h * w, dtype=depth.dtype, device=depth.device).scatter_add(1, index, weight)
    if cfg.zbuffer == "occlusion":
        blend = _occlusion_blend(index, weight, depth, h * w, cfg)
    else:
        blend = _reference_blend(index, weight, depth, total, cfg.front_tolerance)
    num = torch.zeros_like(total).scatter_add(1, index, blend * depth)
    den = torch.zeros_like(total).scatter_add(1, index, blend)
    raw = num / den.clamp(min=1e-12)
    return raw.reshape(b, 1, h, w), total.reshape(b, 1, h, w)


def _occlusion_blend(index: torch.Tensor, weight: torch.Tensor, depth: torch.Tensor, pixels: int, cfg: DepthInitConfig) -> torch.Tensor:
    """weight * exp(-gain * coverage nearer than each contribution by more than the margin)."""
    b = weight.shape[0]
    bins = int(round(2.0 * cfg.depth_span / cfg.depth_bin)) + 1
    log_z = torch.log(depth.clamp(min=1e-3))
    # Bins centred on the view's weighted mean log depth (one number per view: a scene at any scale).
    centre = (weight * log_z).sum(1, keepdim=True) / weight.sum(1, keepdim=True).clamp(min=1e-12)
    t = ((log_z - centre + cfg.depth_span) / cfg.depth_bin).clamp(0.0, bins - 1.001)
    lower = torch.floor(t)
    frac = t - lower
    # Per pixel, bins + 1 slots: an empty slot 0 (nothing nearer than the nearest bin), then the bins.
    slots = bins + 1
    slot = index * slots + lower.to(torch.int64) + 1
    # One scatter for both bins of every contribution (ONNX Runtime copies the histogram per scatter).
    hist = torch.zeros(b, pixels * slots, dtype=weight.dtype, device=weight.device)
    hist = hist.scatter_add(1, torch.cat([slot, slot + 1], dim=1), torch.cat([weight * (1.0 - frac), weight * frac], dim=1))
    # Coverage at or nearer than each bin, read between slots at the contribution's depth minus the
    # margin (linear between slots, 0 at slot 0: continuous wherever the contribution lies).
    nearer = torch.cumsum(hist.reshape(b, pixels, slots), dim=2).reshape(b, pixels * slots)
    r = (t + 1.0 - cfg.occlusion_margin / cfg.depth_bin).clamp(min=0.0)
    r0 = torch.floor(r)
    rf = r - r0
    base = index * slots + r0.to(torch.int64)
    front = torch.gather(nearer, 1, base) * (1.0 - rf) + torch.gather(nearer, 1, base + 1) * rf
    return weight * torch.exp(-cfg.occlusion_gain * front)


def _reference_blend(index: torch.Tensor, weight: torch.Tensor, depth: torch.Tensor, total: torch.Tensor, tolerance: float) -> torch.Tensor:
    """The "reference" z-buffer: z_ref = (sum w z^-4 / sum w)^(-1/4) leaning to the front; each
    contribution blends with w * exp(-clip(log(z/z_ref) / tolerance, +-FRONT_RANGE))."""
    zc = depth.clamp(min=1e-3)
    inv2 = 1.0 / (zc * zc)
    inv4 = torch.zeros_like(total).scatter_add(1, index, weight * (inv2 * inv2))
    log_ref = -0.25 * torch.log(inv4.clamp(min=1e-30) / total.clamp(min=1e-30))
    pref = ((torch.log(zc) - torch.gather(log_ref, 1, index)) / tolerance).clamp(-FRONT_RANGE, FRONT_RANGE)
    return weight * torch.exp(-pref)


def push_pull_fill(depth: torch.Tensor, coverage: torch.Tensor, levels: int) -> torch.Tensor:
    """Fill pixels with coverage < 1 from coarser averages of the covered ones (push-pull)."""
    a = coverage.clamp(0.0, 1.0)
    nums = [depth * a]
    alphas = [a]
    for _ in range(levels):
        if min(nums[-1].shape[-2:]) < 2:
            break
        nums.append(F.avg_pool2d(nums[-1], 2, ceil_mode=True))
        alphas.append(F.avg_pool2d(alphas[-1], 2, ceil_mode=True))
    filled = nums[-1] / alphas[-1].clamp(min=1e-6)
    for num, alpha in zip(reversed(nums[:-1]), reversed(alphas[:-1])):
        up = F.interpolate(filled, size=num.shape[-2:], mode="bilinear", align_corners=False)
        # num = alpha * (this level's depth): keep it where covered, take the coarser level elsewhere.
        filled = num + (1.0 - alpha) * up
    return filled


class DepthInit(nn.Module):
    def __init__(self, cfg: DepthInitConfig, size: tuple[int, int]):
        super().__init__()
        self.cfg = cfg
        self.size = size

    def forward(self, points_left, points_right, opacity_left, opacity_right, left_to_target, target_K) -> SplatDepth:
        """Point maps (B, 3, H, W) in the left frame, opacities (B, 1, H, W); `target_K` for self.size."""
        b = points_left.shape[0]
        pts = torch.cat([points_left.reshape(b, 3, -1), points_right.reshape(b, 3, -1)], dim=2)
        op = torch.cat([opacity_left.reshape(b, 1, -1), opacity_right.reshape(b, 1, -1)], dim=2)
        scale = self.cfg.scale
        if scale == 1:
            raw, cov = splat_depth(pts, op, left_to_target, target_K, self.size, self.cfg)
            return SplatDepth(push_pull_fill(raw, cov, self.cfg.fill_levels), cov, raw)
        w, h = self.size
        small = (-(-w // scale), -(-h // scale))
        raw, cov = splat_depth(pts, op, left_to_target, resize_intrinsics(target_K, self.size, small), small, self.cfg)
        # log2(scale) fewer push-pull levels: the coarsest one is as large as at the fine size.
        filled = push_pull_fill(raw, cov, max(self.cfg.fill_levels - (scale.bit_length() - 1), 1))
        smooth = {"align_corners": False} if self.cfg.upsample == "bilinear" else {}
        depth = F.interpolate(filled, size=(h, w), mode=self.cfg.upsample, **smooth)
        return SplatDepth(depth, F.interpolate(cov, size=(h, w), mode="nearest"), F.interpolate(raw, size=(h, w), mode="nearest"))
