"""Depth initialisation: forward-splat the transformed point maps of both views into the target view.

Every point is splatted with a fixed radius onto the (2r+1)^2 target pixels around its projection,
with a smooth kernel k(d) = (1 - d^2/rho^2)^2 (rho = r + 1/2, so its support always lies inside the
window) times the point's opacity. A soft z-buffer blends the contributions at each pixel: the
front surface wins, depths a few relative tolerances behind it fade out, points of one surface blend
by their weights (see splat_depth). Unlike a hard z-buffer it is continuous in the inputs (a faint
splat fades out instead of switching a pixel to another surface), so float rounding cannot flip a
pixel and ONNX Runtime agrees with torch. Pixels no point reached are filled by push-pull
interpolation.

Everything is scatter/gather on flat tensors: exportable to ONNX (ScatterElements, GatherElements).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.config import DepthInitConfig
from inference.model.geometry import project, transform_points

FRONT_RANGE = 8.0  # the soft z-buffer prefers a nearer surface by at most e^8 (in units of weight)


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
    radius: int,
    front_tolerance: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Splat points (B, 3, N) with opacities (B, 1, N) into a (W, H) target. Returns raw depth and coverage."""
    b = points.shape[0]
    w, h = size
    uv, z = project(transform_points(to_target, points), target_K)  # (B, 2, N), (B, 1, N)
    u, v, z = uv[:, 0], uv[:, 1], z[:, 0]
    alpha = opacity[:, 0]
    u0 = torch.round(u)
    v0 = torch.round(v)
    rho2 = (radius + 0.5) ** 2
    idx_list, w_list, z_list = [], [], []
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            px = u0 + dx
            py = v0 + dy
            du = px - u
            dv = py - v
            d2 = du * du + dv * dv
            e = (1.0 - d2 / rho2).clamp(min=0.0)
            k = e * e
            inside = (px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1) & (z > 1e-6)
            weight = torch.where(inside, alpha * k, torch.zeros_like(k))
            index = torch.where(inside, py * w + px, torch.zeros_like(px)).to(torch.int64)
            idx_list.append(index)
            w_list.append(weight)
            z_list.append(torch.where(inside, z, torch.zeros_like(z)))
    index = torch.cat(idx_list, dim=1)
    weight = torch.cat(w_list, dim=1)
    depth = torch.cat(z_list, dim=1)
    # Soft z-buffer. Each pixel's reference depth is a weighted power mean leaning to the front,
    # z_ref = (sum w z^-4 / sum w)^(-1/4); each contribution blends with w * exp(-clip(log(z/z_ref)
    # / tolerance, +-range)): nearer surfaces win, surfaces a few tolerances behind fade out, and
    # points of one surface blend by weight. Bounding the preference keeps a faint splat (the rim
    # of a kernel) from overriding a well-covered surface however much nearer it is, and keeps the
    # result smooth in the weights, so float rounding cannot swing a pixel between surfaces.
    zc = depth.clamp(min=1e-3)
    total = torch.zeros(b, h * w, dtype=depth.dtype, device=depth.device).scatter_add(1, index, weight)
    inv2 = 1.0 / (zc * zc)
    inv4 = torch.zeros_like(total).scatter_add(1, index, weight * (inv2 * inv2))
    log_ref = -0.25 * torch.log(inv4.clamp(min=1e-30) / total.clamp(min=1e-30))
    pref = ((torch.log(zc) - torch.gather(log_ref, 1, index)) / front_tolerance).clamp(-FRONT_RANGE, FRONT_RANGE)
    blend = weight * torch.exp(-pref)
    num = torch.zeros_like(total).scatter_add(1, index, blend * depth)
    den = torch.zeros_like(total).scatter_add(1, index, blend)
    cov = total
    raw = num / den.clamp(min=1e-12)
    return raw.reshape(b, 1, h, w), cov.reshape(b, 1, h, w)


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
        raw, cov = splat_depth(pts, op, left_to_target, target_K, self.size, self.cfg.radius, self.cfg.front_tolerance)
        filled = push_pull_fill(raw, cov, self.cfg.fill_levels)
        return SplatDepth(filled, cov, raw)
