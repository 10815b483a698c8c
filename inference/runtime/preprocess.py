"""Frames and calibrated cameras to model inputs (numpy only: the runtime's side, no torch).

The model works on pinhole images at its own sizes. A `Resampler` maps a camera's frames (any size,
OpenCV distortion) onto the undistorted pinhole image of the same camera at the model's size, with
precomputed bilinear tables (and a box prefilter when shrinking by 2x or more, against aliasing).
"""
from __future__ import annotations

import numpy as np

from calibration.camera import CameraModel
from inference.config import Sizes
from inference.errors import InferenceError


def pinhole(camera: CameraModel, size: tuple[int, int]) -> CameraModel:
    """The undistorted pinhole version of `camera` at `size` (W, H)."""
    c = camera.scaled(size[0], size[1])
    return CameraModel(c.name, c.width, c.height, c.K, np.zeros(5), c.R, c.t)


def intrinsics(camera: CameraModel, size: tuple[int, int]) -> np.ndarray:
    """(1, 3, 3) float32 intrinsics of the camera's pinhole image at `size`."""
    return pinhole(camera, size).K.astype(np.float32)[None]


def pose(camera: CameraModel) -> np.ndarray:
    """(1, 4, 4) float32 world-to-camera matrix."""
    return camera.extrinsic.astype(np.float32)[None]


def _box_shrink(image: np.ndarray, factor: int) -> np.ndarray:
    h = image.shape[0] // factor * factor
    w = image.shape[1] // factor * factor
    img = image[:h, :w]
    shape = (h // factor, factor, w // factor, factor) + img.shape[2:]
    return img.reshape(shape).mean(axis=(1, 3))


class Resampler:
    """Precomputed resampling of one camera's frames to its pinhole image at `size`."""

    def __init__(self, camera: CameraModel, size: tuple[int, int]):
        self.camera = camera
        self.size = (int(size[0]), int(size[1]))
        w, h = self.size
        target = pinhole(camera, self.size)
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        # Undistorted normalised coordinates of each output pixel, then where the real camera sees them.
        y = (v - target.cy) / target.fy
        x = (u - target.cx - target.K[0, 1] * y) / target.fx
        xy = camera.distort_normalized(np.stack([x, y], axis=-1))
        src_u = camera.K[0, 0] * xy[..., 0] + camera.K[0, 1] * xy[..., 1] + camera.K[0, 2]
        src_v = camera.K[1, 1] * xy[..., 1] + camera.K[1, 2]
        # Nearest source pixel (depth maps must not be blended across edges).
        self._nearest = (
            np.clip(np.rint(src_v), 0, camera.height - 1).astype(np.int64),
            np.clip(np.rint(src_u), 0, camera.width - 1).astype(np.int64),
        )
        self.prefilter = max(1, int(min(camera.width / w, camera.height / h)))
        if self.prefilter > 1:
            f = self.prefilter
            src_u = (src_u + 0.5) / f - 0.5
            src_v = (src_v + 0.5) / f - 0.5
            sw, sh = camera.width // f, camera.height // f
        else:
            sw, sh = camera.width, camera.height
        su = np.clip(src_u, 0, sw - 1)
        sv = np.clip(src_v, 0, sh - 1)
        x0 = np.minimum(np.floor(su).astype(np.int64), max(sw - 2, 0))
        y0 = np.minimum(np.floor(sv).astype(np.int64), max(sh - 2, 0))
        fx = (su - x0).astype(np.float32)[..., None]
        fy = (sv - y0).astype(np.float32)[..., None]
        x1 = np.minimum(x0 + 1, sw - 1)
        y1 = np.minimum(y0 + 1, sh - 1)
        self._idx = (y0 * sw + x0, y0 * sw + x1, y1 * sw + x0, y1 * sw + x1)
        self._w = ((1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy)
        self._identity = (not camera.has_distortion) and (camera.width, camera.height) == self.size and np.allclose(camera.K, target.K)

    def _check(self, array: np.ndarray, what: str) -> None:
        if array.shape[:2] != (self.camera.height, self.camera.width):
            raise InferenceError(
                f"{what} of camera '{self.camera.name}' is {array.shape[1]}x{array.shape[0]}, "
                f"but its calibration is for {self.camera.width}x{self.camera.height}"
            )

    def image(self, image: np.ndarray) -> np.ndarray:
        """An RGB frame (H, W, 3) uint8 or float in [0, 1] to a float32 (H', W', 3) pinhole image."""
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3:
            raise InferenceError(f"frame of camera '{self.camera.name}' must be H x W x 3 RGB, got shape {image.shape}")
        self._check(image, "frame")
        img = image.astype(np.float32)
        if image.dtype == np.uint8:
            img *= 1.0 / 255.0
        if self._identity:
            return np.ascontiguousarray(img)
        if self.prefilter > 1:
            img = _box_shrink(img, self.prefilter)
        flat = img.reshape(-1, 3)
        out = sum(w * flat[i] for i, w in zip(self._idx, self._w))
        return out.astype(np.float32)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """A depth map (H, W) to the pinhole image by nearest sampling (no blending across edges)."""
        depth = np.asarray(depth, dtype=np.float32)
        if depth.ndim != 2:
            raise InferenceError(f"depth of camera '{self.camera.name}' must be H x W, got shape {depth.shape}")
        self._check(depth, "depth map")
        return depth[self._nearest]


def to_nchw(image: np.ndarray) -> np.ndarray:
    """(H, W, C) or (H, W) float32 to (1, C, H, W)."""
    if image.ndim == 2:
        image = image[..., None]
    return np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32)


class InputPreparer:
    """Builds the model's input arrays from frames and cameras, caching a Resampler per camera."""

    def __init__(self, sizes: Sizes, needs_depth: bool, cache_size: int = 16):
        self.sizes = sizes
        self.needs_depth = needs_depth
        self.cache_size = cache_size
        self._resamplers: dict[tuple, Resampler] = {}

    def resampler(self, camera: CameraModel, size: tuple[int, int]) -> Resampler:
        key = (camera.name, camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(), tuple(size))
        r = self._resamplers.get(key)
        if r is None:
            if len(self._resamplers) >= self.cache_size:
                self._resamplers.clear()
            r = self._resamplers[key] = Resampler(camera, size)
        return r

    def __call__(self, left, right, left_cam: CameraModel, right_cam: CameraModel, target_cam: CameraModel, left_depth=None, right_depth=None) -> dict[str, np.ndarray]:
        fine = self.sizes.fine
        feeds = {
            "left_image": to_nchw(self.resampler(left_cam, fine).image(left)),
            "right_image": to_nchw(self.resampler(right_cam, fine).image(right)),
            "left_K": intrinsics(left_cam, fine),
            "right_K": intrinsics(right_cam, fine),
            "left_pose": pose(left_cam),
            "right_pose": pose(right_cam),
            "target_K": intrinsics(target_cam, self.sizes.output),
            "target_pose": pose(target_cam),
        }
        if self.needs_depth:
            if left_depth is None or right_depth is None:
                raise InferenceError("this model uses the oracle backbone and needs left_depth and right_depth")
            coarse = self.sizes.coarse
            feeds["left_depth"] = to_nchw(self.resampler(left_cam, coarse).depth(left_depth))
            feeds["right_depth"] = to_nchw(self.resampler(right_cam, coarse).depth(right_depth))
        return feeds
