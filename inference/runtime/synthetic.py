"""Deterministic stand-in inputs for exporting and checking a model (numpy only).

Export traces the model on example inputs and `rig model check` compares torch with ONNX Runtime on
the same inputs; neither needs a real scene, only inputs of the right kind: a binocular rig 60
degrees apart looking at a point 3 m away, a target camera between them, smooth random colour
images and (for the oracle backbone) the depth of a slanted plane through the look-at point.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import CameraModel, intrinsics_from_fov, look_at
from inference.config import Sizes
from inference.runtime.preprocess import intrinsics, pose


@dataclass
class ExampleInputs:
    left: CameraModel
    right: CameraModel
    target: CameraModel
    arrays: dict[str, np.ndarray]  # model input name -> array


def rig_camera(name: str, angle_deg: float, size: tuple[int, int], distance: float = 3.0, hfov: float = 60.0) -> CameraModel:
    a = np.radians(angle_deg)
    eye = np.array([distance * np.sin(a), 1.6, -distance * np.cos(a)])
    R, t = look_at(eye, (0.0, 1.2, 0.0))
    return CameraModel(name, size[0], size[1], intrinsics_from_fov(size[0], size[1], hfov), np.zeros(5), R, t)


def smooth_image(rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray:
    """Random colour blobs at several scales, (H, W, 3) float32 in [0, 1]."""
    w, h = size
    img = np.zeros((h, w, 3), dtype=np.float64)
    for cells in (4, 8, 16, 32):
        coarse = rng.random((cells * h // w + 2, cells + 2, 3))
        ys = np.linspace(0, coarse.shape[0] - 2, h)
        xs = np.linspace(0, coarse.shape[1] - 2, w)
        y0 = ys.astype(int)
        x0 = xs.astype(int)
        fy = (ys - y0)[:, None, None]
        fx = (xs - x0)[None, :, None]
        c = coarse
        img += (
            c[y0][:, x0] * (1 - fy) * (1 - fx)
            + c[y0][:, x0 + 1] * (1 - fy) * fx
            + c[y0 + 1][:, x0] * fy * (1 - fx)
            + c[y0 + 1][:, x0 + 1] * fy * fx
        ) / cells**0.5
    img -= img.min()
    img /= img.max()
    return img.astype(np.float32)


def plane_depth(camera: CameraModel, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Depth (z) of a plane seen by a pinhole camera, (H, W) float32, 0 where the plane is behind."""
    n_cam = camera.R @ normal
    p_cam = camera.world_to_camera(point)
    rays = camera.pixel_rays()  # (H, W, 3), z = 1
    denom = rays @ n_cam
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (p_cam @ n_cam) / denom
    z = np.where(np.isfinite(z) & (z > 0), z, 0.0)
    return z.astype(np.float32)


def example_inputs(sizes: Sizes, with_depth: bool, seed: int = 0) -> ExampleInputs:
    rng = np.random.default_rng(seed)
    left = rig_camera("left", -30.0, sizes.fine)
    right = rig_camera("right", 30.0, sizes.fine)
    target = rig_camera("target", 8.0, sizes.output)
    arrays = {
        "left_image": smooth_image(rng, sizes.fine).transpose(2, 0, 1)[None].copy(),
        "right_image": smooth_image(rng, sizes.fine).transpose(2, 0, 1)[None].copy(),
        "left_K": intrinsics(left, sizes.fine),
        "right_K": intrinsics(right, sizes.fine),
        "left_pose": pose(left),
        "right_pose": pose(right),
        "target_K": intrinsics(target, sizes.output),
        "target_pose": pose(target),
    }
    if with_depth:
        normal = np.array([0.2, 0.1, -1.0])
        normal /= np.linalg.norm(normal)
        centre = np.array([0.0, 1.2, 0.0])
        for name, cam in (("left_depth", left), ("right_depth", right)):
            coarse = cam.scaled(*sizes.coarse)
            arrays[name] = plane_depth(coarse, centre, normal)[None, None]
    return ExampleInputs(left, right, target, arrays)
