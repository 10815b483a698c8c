"""Image and depth figures (numpy only)."""
from __future__ import annotations

import math

import numpy as np

from calibration.camera import CameraModel


def psnr(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of images in [0, 1] (H, W, C), over the pixels of `mask` (H, W) when given."""
    err = (np.asarray(pred, np.float64) - np.asarray(truth, np.float64)) ** 2
    if mask is not None:
        err = err[np.asarray(mask, bool)]
    mse = float(err.mean()) if err.size else float("nan")
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def depth_agreement(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, tolerance: float = 0.02) -> float:
    """Fraction of the `mask` pixels whose depth is within `tolerance` (relative) of the truth."""
    m = np.asarray(mask, bool) & (truth > 0)
    if not m.any():
        return float("nan")
    rel = np.abs(pred[m] - truth[m]) / truth[m]
    return float((rel <= tolerance).mean())


def covisibility(target: CameraModel, target_depth: np.ndarray, sources: list[tuple[CameraModel, np.ndarray]], tolerance: float = 0.02) -> np.ndarray:
    """Pixels of a pinhole target whose surface point every source sees (H, W) bool.

    A source sees the point when it projects inside the source image and the source's own
    ground-truth depth there (nearest pixel) agrees with the point's depth within `tolerance`.
    """
    rays = target.pixel_rays()
    pts_cam = rays * target_depth[..., None]
    pts_world = (pts_cam - target.t) @ target.R  # R^T (X - t)
    seen = target_depth > 0
    for cam, depth in sources:
        uv, z = cam.project(pts_world)
        u = np.rint(uv[..., 0])
        v = np.rint(uv[..., 1])
        inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height) & (z > 0)
        ui = np.clip(u, 0, cam.width - 1).astype(np.int64)
        vi = np.clip(v, 0, cam.height - 1).astype(np.int64)
        d = depth[vi, ui]
        seen &= inside & (np.abs(d - z) <= tolerance * np.maximum(z, 1e-6))
    return seen
