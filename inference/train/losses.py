"""Training losses of the paper (used by the trainer).

- `rendering_loss`: beta_1 L1 + beta_2 (1 - SSIM) with beta = (0.8, 0.2) (Eq. render_loss).
- `chamfer_6d`: the stage-1 regulariser, a symmetric Chamfer distance between the two views'
  6-D point sets (xyz of X_t, rgb of the pixel), mean Euclidean distance to the nearest neighbour
  in each direction (Eq. geo_regular).
- `stage1_loss` / `stage2_loss`: the weighted sums with the paper's gamma = 0.5, lambda = (0.5, 0.5).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from inference.train.chamfer import chamfer_6d  # noqa: F401  (the stage-1 regulariser; exact, see chamfer.py)


def _gaussian_window(size: int, sigma: float, channels: int, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2.0
    g = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, size, size).contiguous()


def ssim_map(x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5, c1: float = 0.01**2, c2: float = 0.03**2) -> torch.Tensor:
    """Per-pixel SSIM (B, C, H, W) of images (B, C, H, W) in [0, 1] (Wang et al. 2004: 11x11 Gaussian
    window, sigma 1.5; borders zero-padded as in the 3DGS implementation)."""
    c = x.shape[1]
    w = _gaussian_window(window, sigma, c, x.dtype, x.device)
    pad = window // 2
    mu_x = F.conv2d(x, w, padding=pad, groups=c)
    mu_y = F.conv2d(y, w, padding=pad, groups=c)
    sxx = F.conv2d(x * x, w, padding=pad, groups=c) - mu_x * mu_x
    syy = F.conv2d(y * y, w, padding=pad, groups=c) - mu_y * mu_y
    sxy = F.conv2d(x * y, w, padding=pad, groups=c) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)
    return num / den


def ssim(x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5, c1: float = 0.01**2, c2: float = 0.03**2) -> torch.Tensor:
    """Mean SSIM of images (B, C, H, W) in [0, 1]."""
    return ssim_map(x, y, window, sigma, c1, c2).mean()


def rendering_loss(pred: torch.Tensor, truth: torch.Tensor, beta_l1: float = 0.8, beta_ssim: float = 0.2) -> torch.Tensor:
    return beta_l1 * (pred - truth).abs().mean() + beta_ssim * (1.0 - ssim(pred, truth))


def masked_rendering_loss(pred: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor, beta_l1: float = 0.8, beta_ssim: float = 0.2) -> torch.Tensor:
    """rendering_loss over the pixels of `mask` (B, H, W) alone: per item over its masked pixels (0
    for an item without any), then over the batch (data-parallel processes step as one)."""
    m = mask.to(pred.dtype).flatten(1)
    per_pixel = beta_l1 * (pred - truth).abs().mean(1) + beta_ssim * (1.0 - ssim_map(pred, truth).mean(1))
    return ((per_pixel.flatten(1) * m).sum(1) / m.sum(1).clamp(min=1.0)).mean()


def point_colour_set(points: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """A point map (B, 3, H, W) and its image (B, 3, H, W) as a 6-D point set (B, H*W, 6)."""
    b = points.shape[0]
    return torch.cat([points.reshape(b, 3, -1), image.reshape(b, 3, -1)], dim=1).transpose(1, 2)


def stage1_loss(render: torch.Tensor, truth: torch.Tensor, chamfer: torch.Tensor, gamma: float = 0.5) -> torch.Tensor:
    return rendering_loss(render, truth) + gamma * chamfer


def stage2_loss(colour_fine: torch.Tensor, truth_fine: torch.Tensor, render: torch.Tensor, truth: torch.Tensor, lambda_fine: float = 0.5, lambda_render: float = 0.5) -> torch.Tensor:
    return lambda_fine * rendering_loss(colour_fine, truth_fine) + lambda_render * rendering_loss(render, truth)
