"""The exportable Gaussian-plane renderer against straightforward references."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from inference.config import SplatConfig
from inference.model.geometry import pixel_rays, resize_intrinsics
from inference.model.splat import PlaneSplatter, quaternion_to_matrix, render_reference
from inference.model.stage2 import GaussianPlaneMaps

PLANE = (12, 8)
OUT = (15, 10)
K_PLANE = torch.tensor([[[10.0, 0.0, 5.5], [0.0, 10.0, 3.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
K_OUT = resize_intrinsics(K_PLANE, PLANE, OUT)


def random_plane(seed: int, depth: torch.Tensor | None = None, max_sigma_px: float = 1.2) -> GaussianPlaneMaps:
    g = torch.Generator().manual_seed(seed)
    w, h = PLANE
    if depth is None:
        depth = 2.0 + 0.5 * torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    means = pixel_rays(K_PLANE, w, h) * depth
    q = torch.randn(1, 4, h, w, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=1, keepdim=True)
    footprint = depth / K_PLANE[0, 0, 0]
    scales = footprint * (0.2 + (max_sigma_px - 0.2) * torch.rand(1, 3, h, w, generator=g, dtype=torch.float64))
    opacity = 0.2 + 0.8 * torch.rand(1, 1, h, w, generator=g, dtype=torch.float64)
    colours = torch.rand(1, 3, h, w, generator=g, dtype=torch.float64)
    return GaussianPlaneMaps(means, q, scales, opacity, colours)


def fast(plane, cfg):
    return PlaneSplatter(cfg, PLANE, OUT).double()(plane, K_OUT)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_windowed_renderer_matches_the_reference_under_the_same_window(seed):
    cfg = SplatConfig(window=1)
    plane = random_plane(seed)
    a = fast(plane, cfg)
    b = render_reference(plane, K_OUT, OUT, cfg, window=1)
    assert torch.allclose(a.image, b.image, atol=1e-9)
    assert torch.allclose(a.alpha, b.alpha, atol=1e-9)
    assert torch.allclose(a.depth, b.depth, atol=1e-9)


def test_window_loses_nothing_when_gaussians_fit_inside_it():
    cfg = SplatConfig(window=2)
    plane = random_plane(3, max_sigma_px=0.35)
    a = fast(plane, cfg)
    b = render_reference(plane, K_OUT, OUT, cfg)  # every Gaussian may reach every pixel
    assert (a.image - b.image).abs().max() < 1e-4


def plain_3dgs(plane: GaussianPlaneMaps, cfg: SplatConfig) -> np.ndarray:
    """Textbook 3DGS: sort by depth, composite front to back, one Gaussian at a time."""
    ow, oh = OUT
    mu = plane.means[0].reshape(3, -1).T.numpy()
    R = quaternion_to_matrix(plane.rotations[0].reshape(4, -1).T).numpy()
    S = plane.scales[0].reshape(3, -1).T.numpy()
    K = K_OUT[0].numpy()
    image = np.zeros((oh, ow, 3))
    trans = np.ones((oh, ow))
    v, u = np.mgrid[0:oh, 0:ow].astype(np.float64)
    for i in np.argsort(mu[:, 2]):
        x, y, z = mu[i]
        J = np.array([[K[0, 0] / z, 0, -K[0, 0] * x / z**2], [0, K[1, 1] / z, -K[1, 1] * y / z**2]])
        M = R[i] * S[i]
        cov = J @ M @ M.T @ J.T + cfg.blur * np.eye(2)
        conic = np.linalg.inv(cov)
        c = K @ mu[i]
        du, dv = u - c[0] / c[2], v - c[1] / c[2]
        power = -0.5 * (conic[0, 0] * du * du + 2 * conic[0, 1] * du * dv + conic[1, 1] * dv * dv)
        alpha = np.minimum(cfg.max_alpha, plane.opacities[0, 0].reshape(-1)[i].item() * np.exp(power))
        image += (alpha * trans)[..., None] * plane.colours[0].reshape(3, -1)[:, i].numpy()
        trans *= 1.0 - alpha
    return image + trans[..., None] * np.array(cfg.background)


def test_separate_surfaces_composite_exactly_as_3dgs():
    """With depths far apart (beyond the soft-order tolerance) the result is textbook 3DGS."""
    w, h = PLANE
    y, x = np.mgrid[0:h, 0:w]
    layer = (x + 5 * y) % 25  # every 5x5 window holds 25 different depths, 20 % apart
    depth = torch.tensor(2.0 * 1.2**layer, dtype=torch.float64)[None, None]
    plane = random_plane(4, depth=depth, max_sigma_px=0.35)
    cfg = SplatConfig(window=2)
    ours = fast(plane, cfg).image[0].permute(1, 2, 0).numpy()
    assert np.abs(ours - plain_3dgs(plane, cfg)).max() < 1e-4


def test_strict_order_is_3dgs_even_on_one_surface():
    cfg = SplatConfig(window=2, depth_tolerance=0.0)
    plane = random_plane(5, max_sigma_px=0.35)
    ours = fast(plane, cfg).image[0].permute(1, 2, 0).numpy()
    assert np.abs(ours - plain_3dgs(plane, cfg)).max() < 1e-4


def test_one_surface_blends_smoothly_instead_of_by_order():
    """Gaussians of one flat surface with a colour ramp: the render follows the ramp, with no
    dependence on which of two nearly equal depths is nearer."""
    w, h = PLANE
    depth = torch.full((1, 1, h, w), 3.0, dtype=torch.float64)
    plane = random_plane(6, depth=depth)
    ramp = torch.linspace(0.0, 1.0, w, dtype=torch.float64).reshape(1, 1, 1, w).expand(1, 3, h, w)
    flat = GaussianPlaneMaps(plane.means, torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).reshape(1, 4, 1, 1).expand(1, 4, h, w),
                             depth.expand(1, 3, h, w) / 10.0 * 0.6, torch.full_like(depth, 0.99), ramp.contiguous())
    cfg = SplatConfig()
    a = fast(flat, cfg).image
    nudged = GaussianPlaneMaps(flat.means * (1 + 1e-7 * torch.rand_like(depth)), flat.rotations, flat.scales, flat.opacities, flat.colours)
    b = fast(nudged, cfg).image
    assert (a - b).abs().max() < 2e-6  # measured 1.9e-7
    row = a[0, 0, 5, 2:-2].numpy()
    assert np.all(np.diff(row) > 0)  # monotonic like the ramp
