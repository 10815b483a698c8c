"""Rendering a Gaussian plane: an exportable windowed splatter and a straightforward reference.

A Gaussian plane holds one Gaussian per pixel of a (W, H) grid of the target camera (its anchor).
It is rendered into the same camera at another size (Wo, Ho) with intrinsics K_out.

Both renderers compute, per Gaussian, the EWA projection of its 3D covariance (3DGS):
Sigma_2D = J R S S^T R^T J^T + blur I, its alpha at a pixel
    alpha_i = min(max_alpha, o_i exp(-d^T Sigma_2D^{-1} d / 2)),
and composite front to back in depth order, where the order is softened over a small relative
depth tolerance (see `composite`): 3DGS order between surfaces, an alpha-weighted blend within one.

`PlaneSplatter` (exportable, no custom op): each output pixel considers only the (2w+1)^2
Gaussians anchored around its nearest plane pixel (a fixed window, fetched with constant-index
row gathers) and composites them with the pairwise soft order (K^2/2 small tensor ops, no sort).
`render_reference`: every pixel against every Gaussian, straightforward double precision.
Given the same window rule (`window=`) the two agree; for Gaussians whose footprint lies inside the
window the rule changes nothing, and the reference without it agrees too. With depths far apart
(or `depth_tolerance=0`) both reduce to plain sorted 3DGS compositing (the tests check all three).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.config import SplatConfig
from inference.model.geometry import pixel_rays
from inference.model.stage2 import GaussianPlaneMaps


@dataclass
class Rendered:
    image: torch.Tensor  # (B, 3, Ho, Wo)
    depth: torch.Tensor  # (B, 1, Ho, Wo) alpha-weighted depth of the composited Gaussians (0 where empty)
    alpha: torch.Tensor  # (B, 1, Ho, Wo) accumulated opacity


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (..., 4) as (w, x, y, z) to rotation matrices (..., 3, 3)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def project_gaussians(plane: GaussianPlaneMaps, K: torch.Tensor, blur: float) -> torch.Tensor:
    """Per-Gaussian screen-space attribute maps (B, 10, H, W): u, v, conic (a, b, c), opacity, depth, rgb."""
    b, _, h, w = plane.means.shape
    mu = plane.means.reshape(b, 3, -1)
    x, y, z = mu[:, 0], mu[:, 1], mu[:, 2]
    zs = z.clamp(min=1e-6)
    fx = K[:, 0, 0, None]
    fy = K[:, 1, 1, None]
    u = fx * x / zs + K[:, 0, 1, None] * y / zs + K[:, 0, 2, None]
    v = fy * y / zs + K[:, 1, 2, None]
    rot = quaternion_to_matrix(plane.rotations.reshape(b, 4, -1).transpose(1, 2))  # (B, N, 3, 3)
    m = rot * plane.scales.reshape(b, 3, -1).transpose(1, 2)[:, :, None, :]  # R S: columns scaled
    # T = J (R S) with J the Jacobian of the perspective projection at the mean.
    t0 = (fx / zs)[..., None] * m[:, :, 0, :] - (fx * x / (zs * zs))[..., None] * m[:, :, 2, :]
    t1 = (fy / zs)[..., None] * m[:, :, 1, :] - (fy * y / (zs * zs))[..., None] * m[:, :, 2, :]
    sa = (t0 * t0).sum(-1) + blur
    sb = (t0 * t1).sum(-1)
    sc = (t1 * t1).sum(-1) + blur
    det = (sa * sc - sb * sb).clamp(min=1e-12)
    opacity = plane.opacities.reshape(b, -1) * (z > 1e-6).to(z.dtype)
    attrs = torch.stack([u, v, sc / det, -sb / det, sa / det, opacity, z], 1).reshape(b, 7, h, w)
    return torch.cat([attrs, plane.colours], dim=1)


def anchors(plane_len: int, out_len: int) -> torch.Tensor:
    """The plane pixel nearest to each output pixel centre along one axis: floor((o + 1/2) s)."""
    return torch.floor((torch.arange(out_len, dtype=torch.float64) + 0.5) * (plane_len / out_len)).to(torch.int64)


def soft_order(z_i: torch.Tensor, z_j: torch.Tensor, tolerance: float) -> torch.Tensor:
    """How much Gaussian j lies in front of Gaussian i: 1 when z_j < z_i by more than `tolerance`
    (relative to their mean depth), 0 when it lies that much behind, a linear ramp between
    (tolerance 0: the hard 3DGS order). soft_order(i, j) + soft_order(j, i) = 1."""
    if tolerance <= 0:
        return (z_j < z_i).to(z_i.dtype) + 0.5 * (z_j == z_i).to(z_i.dtype)
    return (0.5 + (z_i - z_j) / (tolerance * (z_i + z_j).clamp(min=1e-6))).clamp(0.0, 1.0)


def composite(alpha: list[torch.Tensor], depth: list[torch.Tensor], colour: list[torch.Tensor], background: torch.Tensor, tolerance: float):
    """Front-to-back compositing of K samples in soft depth order.

    alpha[k], depth[k] (B, ...); colour[k] (B, 3, ...). Sample i is attenuated by every sample j in
    front of it: T_i = prod_j (1 - alpha_j)^s_ij with s_ij = soft_order(z_i, z_j). The total
    opacity 1 - prod_j (1 - alpha_j) does not depend on the order, and the colour is the
    T-weighted mean scaled by it. With depths further apart than the tolerance this is exactly 3DGS
    compositing; samples on one surface (nearly equal depths) blend by their alphas instead of by
    whichever float rounding puts first, which keeps the image continuous in its inputs (so ONNX
    Runtime matches torch) and interpolates a surface smoothly. Each pair is visited once
    (s_ji = 1 - s_ij). Returns image (B, 3, ...), depth (B, ...), opacity (B, ...).
    """
    k = len(alpha)
    log_keep = [torch.log(1.0 - a) for a in alpha]
    log_t = [torch.zeros_like(alpha[0]) for _ in range(k)]
    for i in range(k):
        for j in range(i + 1, k):
            s = soft_order(depth[i], depth[j], tolerance)  # j in front of i
            log_t[i] = log_t[i] + s * log_keep[j]
            log_t[j] = log_t[j] + (1.0 - s) * log_keep[i]
    weight = [a * torch.exp(lt) for a, lt in zip(alpha, log_t)]
    wsum = sum(weight).clamp(min=1e-12)
    opacity = 1.0 - torch.exp(sum(log_keep))
    mean_colour = sum(w[:, None] * c for w, c in zip(weight, colour)) / wsum[:, None]
    image = mean_colour * opacity[:, None] + (1.0 - opacity[:, None]) * background
    depth_out = sum(w * z for w, z in zip(weight, depth)) / wsum
    return image, depth_out, opacity


class PlaneSplatter(nn.Module):
    """The exportable renderer of a Gaussian plane of `plane_size` into `out_size`.

    The candidate Gaussians of every output pixel are those anchored within `window` plane pixels
    of its nearest plane pixel. All candidates are fetched at once with two row gathers of
    constant indices (columns on the transposed maps, then rows), which ONNX Runtime runs as block
    copies; zero padding stands for "no Gaussian" beyond the border.
    """

    def __init__(self, cfg: SplatConfig, plane_size: tuple[int, int], out_size: tuple[int, int]):
        super().__init__()
        self.cfg = cfg
        self.plane_size = plane_size
        self.out_size = out_size
        r = cfg.window
        self.n = 2 * r + 1
        self.k = self.n**2
        pw, ph = plane_size
        ow, oh = out_size
        offsets = range(-r, r + 1)
        # Indices into the maps padded by r: the anchor plus each window offset, offset-major.
        self.register_buffer("cols", torch.cat([anchors(pw, ow) + r + d for d in offsets]), persistent=False)
        self.register_buffer("rows", torch.cat([anchors(ph, oh) + r + d for d in offsets]), persistent=False)
        v, u = torch.meshgrid(torch.arange(oh, dtype=torch.float32), torch.arange(ow, dtype=torch.float32), indexing="ij")
        self.register_buffer("pixels", torch.stack([u, v], dim=0)[None], persistent=False)  # (1, 2, Ho, Wo)
        self.register_buffer("background", torch.tensor(cfg.background, dtype=torch.float32).reshape(1, 3, 1, 1), persistent=False)

    def forward(self, plane: GaussianPlaneMaps, K: torch.Tensor) -> Rendered:
        b = plane.means.shape[0]
        ow, oh = self.out_size
        r, n = self.cfg.window, self.n
        attrs = F.pad(project_gaussians(plane, K, self.cfg.blur), (r, r, r, r))  # (B, 10, H + 2r, W + 2r)
        cand = torch.index_select(attrs.transpose(2, 3), 2, self.cols).transpose(2, 3)  # (B, 10, H + 2r, n Wo)
        cand = torch.index_select(cand, 2, self.rows).reshape(b, 10, n, oh, n, ow)
        alpha, depth, colour = [], [], []
        for i in range(n):
            for j in range(n):
                g = cand[:, :, i, :, j, :]  # (B, 10, Ho, Wo): the Gaussians at window offset (i - r, j - r)
                du = self.pixels[:, 0] - g[:, 0]
                dv = self.pixels[:, 1] - g[:, 1]
                power = -0.5 * (g[:, 2] * du * du + g[:, 4] * dv * dv) - g[:, 3] * du * dv
                alpha.append((g[:, 5] * torch.exp(power.clamp(max=0.0))).clamp(max=self.cfg.max_alpha))
                depth.append(g[:, 6])
                colour.append(g[:, 7:10])
        image, depth_out, acc = composite(alpha, depth, colour, self.background.to(attrs.dtype), self.cfg.depth_tolerance)
        return Rendered(image, depth_out[:, None], acc[:, None])


def plane_from_depth(depth: torch.Tensor, colours: torch.Tensor, K: torch.Tensor, sigma: float = 0.6, opacity: float = 0.99) -> GaussianPlaneMaps:
    """A Gaussian plane on a depth map (B, 1, H, W) with colours (B, 3, H, W): Gaussians facing
    the camera, `sigma` pixels wide in the image plane, thin along the ray."""
    b, _, h, w = depth.shape
    means = pixel_rays(K, w, h) * depth
    footprint = depth / K[:, 0, 0].reshape(b, 1, 1, 1)
    scales = torch.cat([sigma * footprint, sigma * footprint, 0.1 * sigma * footprint], dim=1)
    rotations = torch.zeros(b, 4, h, w, dtype=depth.dtype, device=depth.device)
    rotations[:, 0] = 1.0
    opacities = torch.full_like(depth, opacity) * (depth > 0).to(depth.dtype)
    return GaussianPlaneMaps(means, rotations, scales, opacities, colours)


def render_plane(plane: GaussianPlaneMaps, K: torch.Tensor, out_size: tuple[int, int], cfg: SplatConfig | None = None) -> Rendered:
    cfg = cfg or SplatConfig()
    h, w = plane.means.shape[-2:]
    return PlaneSplatter(cfg, (w, h), out_size).to(plane.means.device)(plane, K)


def render_reference(
    plane: GaussianPlaneMaps,
    K: torch.Tensor,
    out_size: tuple[int, int],
    cfg: SplatConfig | None = None,
    window: int | None = None,
) -> Rendered:
    """Every Gaussian at every pixel, in double precision (small sizes only).

    With `window`, a Gaussian only reaches the pixels whose nearest anchor lies within `window`
    plane pixels of its own (the fast renderer's rule); without it, it reaches every pixel.
    """
    cfg = cfg or SplatConfig()
    b = plane.means.shape[0]
    ph, pw = plane.means.shape[-2:]
    ow, oh = out_size
    n = ph * pw
    mu = plane.means.reshape(b, 3, n).transpose(1, 2).double()  # (B, N, 3)
    rot = quaternion_to_matrix(plane.rotations.reshape(b, 4, n).transpose(1, 2).double())
    s = torch.diag_embed(plane.scales.reshape(b, 3, n).transpose(1, 2).double())
    cov3 = rot @ s @ s @ rot.transpose(-1, -2)
    Kd = K.double()
    fx, fy = Kd[:, 0, 0, None], Kd[:, 1, 1, None]
    x, y, z = mu.unbind(-1)
    J = torch.zeros(b, n, 2, 3, dtype=torch.float64, device=mu.device)
    J[..., 0, 0] = fx / z
    J[..., 0, 2] = -fx * x / z**2
    J[..., 1, 1] = fy / z
    J[..., 1, 2] = -fy * y / z**2
    cov2 = J @ cov3 @ J.transpose(-1, -2) + cfg.blur * torch.eye(2, dtype=torch.float64, device=mu.device)
    conic = torch.linalg.inv(cov2)  # (B, N, 2, 2)
    proj = (Kd[:, None] @ mu[..., None])[..., 0]
    mean2d = proj[..., :2] / proj[..., 2:3]
    v, u = torch.meshgrid(torch.arange(oh, dtype=torch.float64, device=mu.device), torch.arange(ow, dtype=torch.float64, device=mu.device), indexing="ij")
    pix = torch.stack([u.reshape(-1), v.reshape(-1)], -1)  # (P, 2)
    if window is not None:
        ax = anchors(pw, ow).to(mu.device).double()[pix[:, 0].long()]
        ay = anchors(ph, oh).to(mu.device).double()[pix[:, 1].long()]
        gy, gx = torch.meshgrid(torch.arange(ph, dtype=torch.float64, device=mu.device), torch.arange(pw, dtype=torch.float64, device=mu.device), indexing="ij")
        reach = ((ax[:, None] - gx.reshape(1, -1)).abs() <= window) & ((ay[:, None] - gy.reshape(1, -1)).abs() <= window)
    opac = plane.opacities.reshape(b, n).double()
    cols = plane.colours.reshape(b, 3, n).transpose(1, 2).double()
    bg = torch.tensor(cfg.background, dtype=torch.float64, device=mu.device)
    images, depths, alphas = [], [], []
    for bi in range(b):
        d = pix[:, None, :] - mean2d[bi][None]  # (P, N, 2)
        power = -0.5 * torch.einsum("pni,nij,pnj->pn", d, conic[bi], d)
        alpha = (opac[bi][None] * torch.exp(power.clamp(max=0.0))).clamp(max=cfg.max_alpha)
        if window is not None:
            alpha = alpha * reach
        zi = z[bi]
        # order[i, j]: how much Gaussian j is in front of Gaussian i (independent of the pixel).
        order = soft_order(zi[:, None], zi[None, :], cfg.depth_tolerance)
        order.fill_diagonal_(0.0)
        log_keep = torch.log1p(-alpha)  # (P, N)
        weight = alpha * torch.exp(log_keep @ order.T)
        opacity = 1.0 - torch.exp(log_keep.sum(-1))
        wsum = weight.sum(-1).clamp(min=1e-12)
        colour = (weight @ cols[bi]) / wsum[:, None] * opacity[:, None] + (1.0 - opacity[:, None]) * bg
        images.append(colour.T.reshape(3, oh, ow))
        depths.append(((weight @ zi) / wsum).reshape(1, oh, ow))
        alphas.append(opacity.reshape(1, oh, ow))
    dtype = plane.means.dtype
    return Rendered(torch.stack(images).to(dtype), torch.stack(depths).to(dtype), torch.stack(alphas).to(dtype))
