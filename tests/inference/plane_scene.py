"""A textured plane seen by pinhole cameras, with exact images and depth (test helper)."""
from __future__ import annotations

import numpy as np

from calibration.camera import CameraModel, intrinsics_from_fov, look_at


def camera(name: str, eye, size=(64, 48), target=(0.0, 1.0, 0.0), hfov=60.0) -> CameraModel:
    R, t = look_at(eye, target)
    return CameraModel(name, size[0], size[1], intrinsics_from_fov(size[0], size[1], hfov), np.zeros(5), R, t)


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.stack([0.5 + 0.4 * np.sin(3 * x), 0.5 + 0.4 * np.cos(2 * y), 0.5 + 0.3 * np.sin(x + y)], -1)


def view_of_plane(cam: CameraModel, z_world: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Image (H, W, 3) in [0, 1] and depth (H, W) of the textured plane z = z_world."""
    rays = cam.pixel_rays()
    d_world = rays @ cam.R
    c = cam.center
    s = (z_world - c[2]) / d_world[..., 2]
    hit = c + d_world * s[..., None]
    return texture(hit[..., 0], hit[..., 1]).astype(np.float32), (rays * s[..., None])[..., 2].astype(np.float32)
