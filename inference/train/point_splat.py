"""Rendering point maps into any camera, differentiably: stage 1's rendering loss (training only).

Stage 1 of the paper trains the backbone's affine transform self-supervised: the metric point maps
X_t of both source views, each point coloured by its source pixel, are rendered into the supervision
cameras and compared with their images. The renderer must reach any camera (not only the target
grid of the Gaussian plane) and pass gradients to the point positions, so it is a forward splatter:

- each point is projected into the target (pose `to_target`, pinhole `K`) and covers the
  (2r+1)^2 pixels around its projection with the compact kernel k(d) = (1 - d^2/rho^2)^2
  (rho = r + 1/2 by default: its support always lies inside the window, so which window a point
  lands in never matters, and k is smooth in the projection: gradients reach the positions);
- its alpha at a pixel is min(max_alpha, opacity * k(d)); the contributions of a pixel are
  composited front to back in depth order, exactly as 3DGS composites Gaussians:
  C = sum_i alpha_i T_i c_i + (1 - A) background, T_i = prod_{j nearer} (1 - alpha_j),
  A = 1 - prod_i (1 - alpha_i), depth = sum_i alpha_i T_i z_i / A.

Why compositing rather than a normalised soft z-buffer (sum w e^{-z/tau} c / sum w e^{-z/tau}): a
soft z-buffer gives a faint nearer contribution (the rim of a foreground kernel) the whole pixel
once it is a few tau in front, which dilates every silhouette by the kernel's radius; compositing
lets the rim cover the pixel by its alpha only. The order is a hard sort, as in 3DGS: depth reaches
the image through the projection and the depth output, not through the order.

`splat_points`: every (point, window pixel) pair as one flat list, one sort by (pixel, depth),
a float64 cumulative sum of log(1 - alpha) for the transmittances, scatter-adds for the sums.
Cost O(N (2r+1)^2 log) time and memory; a 256x144 target with two 256x144 point maps is ~660 k
pairs. `point_splat_reference`: every pixel against every point, dense, double precision (tiny
sizes only); the tests compare the two, values and gradients.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from inference.model.geometry import project, transform_points


@dataclass
class PointSplatConfig:
    radius: int = 1  # window half-size in target pixels: (2r+1)^2 pixels per point
    footprint: Optional[float] = None  # kernel support rho in pixels, at most radius + 1/2 (None: radius + 1/2)
    max_alpha: float = 0.99  # no single point is fully opaque (3DGS), so gradients reach what lies behind
    near: float = 1e-3  # metres: points nearer to the target camera (or behind it) are dropped
    background: tuple[float, ...] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not isinstance(self.radius, int) or self.radius < 0:
            raise ValueError(f"radius must be an integer >= 0, got {self.radius!r}")
        if self.footprint is not None and not 0 < self.footprint <= self.radius + 0.5:
            raise ValueError(f"footprint must be in (0, radius + 1/2], got {self.footprint}")
        if not 0 < self.max_alpha < 1:
            raise ValueError(f"max_alpha must be in (0, 1), got {self.max_alpha}")

    @property
    def rho(self) -> float:
        return float(self.footprint) if self.footprint is not None else self.radius + 0.5


@dataclass
class PointRender:
    image: torch.Tensor  # (B, C, H, W) composited colour over the background
    depth: torch.Tensor  # (B, 1, H, W) alpha-weighted depth of what covers the pixel (0 where nothing)
    alpha: torch.Tensor  # (B, 1, H, W) accumulated opacity A


def _flatten(points: torch.Tensor, colours: torch.Tensor, opacity: Optional[torch.Tensor]):
    """(B, 3, ...), (B, C, ...), (B, 1, ...) or None -> (B, 3, N), (B, C, N), (B, N)."""
    b = points.shape[0]
    pts = points.reshape(b, 3, -1)
    n = pts.shape[2]
    cols = colours.reshape(b, colours.shape[1], -1)
    if cols.shape[2] != n:
        raise ValueError(f"colours have {cols.shape[2]} points, positions {n}")
    op = torch.ones(b, n, dtype=pts.dtype, device=pts.device) if opacity is None else opacity.reshape(b, -1)
    if op.shape[1] != n:
        raise ValueError(f"opacities have {op.shape[1]} points, positions {n}")
    return pts, cols, op


def _kernel(d2: torch.Tensor, rho: float) -> torch.Tensor:
    e = (1.0 - d2 / (rho * rho)).clamp(min=0.0)
    return e * e


def splat_points(points: torch.Tensor, colours: torch.Tensor, opacity: Optional[torch.Tensor], to_target: torch.Tensor,
                 K: torch.Tensor, size: tuple[int, int], cfg: Optional[PointSplatConfig] = None) -> PointRender:
    """Render points (B, 3, ...) with colours (B, C, ...) and opacities (B, 1, ...) (None: 1) into
    a (W, H) = `size` camera whose pose maps the points' frame into it (`to_target`, (B, 4, 4))
    and whose pinhole intrinsics for that size are K (B, 3, 3). Differentiable in points, colours
    and opacities. Two point maps render together when concatenated along the point axis."""
    cfg = cfg or PointSplatConfig()
    pts, cols, op = _flatten(points, colours, opacity)
    b, c, n = cols.shape
    w, h = size
    dtype, device = pts.dtype, pts.device
    uv, z = project(transform_points(to_target, pts), K)
    u, v, z = uv[:, 0], uv[:, 1], z[:, 0]  # (B, N)
    u0 = torch.floor(u.detach() + 0.5)
    v0 = torch.floor(v.detach() + 0.5)
    r = cfg.radius
    alphas, pixels = [], []
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            px, py = u0 + dx, v0 + dy
            du, dv = px - u, py - v
            alpha = (op * _kernel(du * du + dv * dv, cfg.rho)).clamp(max=cfg.max_alpha)
            inside = (px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1) & (z.detach() > cfg.near)
            alphas.append(torch.where(inside, alpha, torch.zeros_like(alpha)))
            pixels.append(torch.where(inside, py * w + px, torch.zeros_like(px)).to(torch.int64))
    alpha = torch.stack(alphas, 1)  # (B, window, N)
    pixel = torch.stack(pixels, 1)
    batch = torch.arange(b, device=device).reshape(b, 1, 1).expand_as(pixel)
    point = torch.arange(n, device=device).reshape(1, 1, n).expand_as(pixel)
    keep = alpha.detach() > 0  # pairs outside the kernel add nothing, value or gradient
    alpha, pixel, batch, point = alpha[keep], pixel[keep], batch[keep], point[keep]
    # One sort orders the pairs by (image pixel, depth): the depth enters as each point's rank.
    rank = torch.argsort(torch.argsort(z.detach(), dim=1), dim=1)  # (B, N)
    key = (batch * (h * w) + pixel) * n + rank[batch, point]
    order = torch.argsort(key)
    alpha, point, batch = alpha[order], point[order], batch[order]
    target = (batch * (h * w) + pixel[order])  # flat pixel of the whole batch
    # Transmittance in front of each pair: exp of the sum of log(1 - alpha) of the nearer pairs of
    # its pixel, from one running sum (float64: the running sum over the whole image is large).
    log_keep = torch.log1p(-alpha.double())
    before = torch.cumsum(log_keep, 0) - log_keep  # over all pairs sorted before this one
    first = torch.ones_like(target, dtype=torch.bool)
    first[1:] = target[1:] != target[:-1]
    idx = torch.arange(target.numel(), device=device)
    start = torch.cummax(torch.where(first, idx, torch.zeros_like(idx)), 0).values  # first pair of the pixel
    weight = (alpha.double() * torch.exp(before - before[start])).to(dtype)
    flat_cols = cols.transpose(1, 2).reshape(b * n, c)[batch * n + point]
    flat_z = z.reshape(b * n)[batch * n + point]
    npix = b * h * w
    image = torch.zeros(npix, c, dtype=dtype, device=device).index_add(0, target, weight[:, None] * flat_cols)
    acc = torch.zeros(npix, dtype=dtype, device=device).index_add(0, target, weight)
    zsum = torch.zeros(npix, dtype=dtype, device=device).index_add(0, target, weight * flat_z)
    bg = torch.tensor(cfg.background, dtype=dtype, device=device).reshape(1, c)
    image = image + (1.0 - acc)[:, None] * bg
    depth = torch.where(acc > 0, zsum / acc.clamp(min=1e-12), torch.zeros_like(acc))
    return PointRender(image.reshape(b, h, w, c).permute(0, 3, 1, 2), depth.reshape(b, 1, h, w), acc.reshape(b, 1, h, w))


def point_splat_reference(points: torch.Tensor, colours: torch.Tensor, opacity: Optional[torch.Tensor], to_target: torch.Tensor,
                          K: torch.Tensor, size: tuple[int, int], cfg: Optional[PointSplatConfig] = None) -> PointRender:
    """The same function, straightforwardly: every pixel against every point in double precision,
    the kernel evaluated everywhere (no window: its support lies inside the window anyway), the
    transmittance as a product over all nearer points (pixel-independent order, one matrix).
    Memory O(H W N + N^2): tiny sizes only."""
    cfg = cfg or PointSplatConfig()
    pts, cols, op = _flatten(points, colours, opacity)
    b, c, n = cols.shape
    w, h = size
    Kd, Td = K.double(), to_target.double()
    cam = Td[:, :3, :3] @ pts.double() + Td[:, :3, 3:]  # (B, 3, N)
    z = cam[:, 2]
    zs = torch.where(z.abs() < 1e-6, torch.full_like(z, 1e-6), z)
    x, y = cam[:, 0] / zs, cam[:, 1] / zs
    u = Kd[:, 0, 0, None] * x + Kd[:, 0, 1, None] * y + Kd[:, 0, 2, None]
    v = Kd[:, 1, 1, None] * y + Kd[:, 1, 2, None]
    dev = cam.device
    gy, gx = torch.meshgrid(torch.arange(h, dtype=torch.float64, device=dev), torch.arange(w, dtype=torch.float64, device=dev), indexing="ij")
    gx, gy = gx.reshape(-1, 1), gy.reshape(-1, 1)  # (P, 1)
    bg = torch.tensor(cfg.background, dtype=torch.float64, device=dev)
    images, depths, accs = [], [], []
    for i in range(b):
        d2 = (gx - u[i]) ** 2 + (gy - v[i]) ** 2  # (P, N)
        alpha = (op[i].double() * _kernel(d2, cfg.rho)).clamp(max=cfg.max_alpha) * (z[i] > cfg.near)
        nearer = (z[i][:, None] < z[i][None, :]).double()  # nearer[j, k]: point j lies in front of point k
        weight = alpha * torch.exp(torch.log1p(-alpha) @ nearer)  # (P, N)
        acc = weight.sum(1)
        image = weight @ cols[i].double().T + (1.0 - acc)[:, None] * bg
        depth = torch.where(acc > 0, (weight @ z[i]) / acc.clamp(min=1e-12), torch.zeros_like(acc))
        images.append(image.T.reshape(c, h, w))
        depths.append(depth.reshape(1, h, w))
        accs.append(acc.reshape(1, h, w))
    dtype = pts.dtype
    return PointRender(torch.stack(images).to(dtype), torch.stack(depths).to(dtype), torch.stack(accs).to(dtype))
