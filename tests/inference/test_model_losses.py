"""Training losses: SSIM against a direct per-window computation, L1 + SSIM weights, 6-D Chamfer."""
from __future__ import annotations

import numpy as np
import torch

from inference.train.losses import chamfer_6d, point_colour_set, rendering_loss, ssim


def ssim_direct(x: np.ndarray, y: np.ndarray, window: int = 11, sigma: float = 1.5) -> float:
    """SSIM computed window by window (zero padding), the formula of Wang et al. written out."""
    c1, c2 = 0.01**2, 0.03**2
    r = window // 2
    g = np.exp(-((np.arange(window) - r) ** 2) / (2 * sigma**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    _, h, wd = x.shape
    xp = np.pad(x, ((0, 0), (r, r), (r, r)))
    yp = np.pad(y, ((0, 0), (r, r), (r, r)))
    vals = []
    for c in range(x.shape[0]):
        for i in range(h):
            for j in range(wd):
                a = xp[c, i : i + window, j : j + window]
                b = yp[c, i : i + window, j : j + window]
                ma, mb = (w * a).sum(), (w * b).sum()
                va = (w * a * a).sum() - ma * ma
                vb = (w * b * b).sum() - mb * mb
                cov = (w * a * b).sum() - ma * mb
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma * ma + mb * mb + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_ssim_matches_the_direct_formula():
    rng = np.random.default_rng(0)
    x = rng.random((3, 16, 20))
    y = np.clip(x + 0.1 * rng.normal(size=x.shape), 0, 1)
    ours = ssim(torch.tensor(x)[None], torch.tensor(y)[None]).item()
    assert abs(ours - ssim_direct(x, y)) < 1e-10
    assert abs(ssim(torch.tensor(x)[None], torch.tensor(x)[None]).item() - 1.0) < 1e-12


def test_rendering_loss_weights_l1_and_ssim():
    rng = np.random.default_rng(1)
    x = torch.tensor(rng.random((1, 3, 24, 24)))
    y = torch.tensor(rng.random((1, 3, 24, 24)))
    expected = 0.8 * (x - y).abs().mean() + 0.2 * (1 - ssim(x, y))
    assert torch.isclose(rendering_loss(x, y), expected)
    assert rendering_loss(x, x).item() < 1e-12


def test_chamfer_6d_of_small_sets_by_hand():
    a = torch.tensor([[[0.0, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0]]])
    b = torch.tensor([[[0.0, 0, 0, 0, 0, 1], [3.0, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0]]])
    # a->b: nearest of (0..) is 1 away (colour), of (1..) is 0 away: mean 0.5.
    # b->a: 1, 2, 0: mean 1.
    assert torch.isclose(chamfer_6d(a, b), torch.tensor(1.5))
    assert chamfer_6d(a, a).item() == 0.0
    # Weights leave points out: without b's far point, b->a is (1 + 0) / 2.
    wb = torch.tensor([[1.0, 0.0, 1.0]])
    assert torch.isclose(chamfer_6d(a, b, weight_b=wb), torch.tensor(1.0))


def test_chamfer_6d_matches_brute_force_and_has_gradients():
    rng = np.random.default_rng(2)
    pts = torch.tensor(rng.normal(size=(1, 3, 6, 7)), requires_grad=True)
    img = torch.tensor(rng.random((1, 3, 6, 7)))
    other = torch.tensor(rng.normal(size=(1, 40, 6)))
    a = point_colour_set(pts, img)
    loss = chamfer_6d(a, other)
    an, on = a[0].detach().numpy(), other[0].numpy()
    d = np.linalg.norm(an[:, None] - on[None], axis=-1)
    assert abs(loss.item() - (d.min(1).mean() + d.min(0).mean())) < 1e-10
    loss.backward()
    assert pts.grad is not None and pts.grad.abs().sum() > 0
