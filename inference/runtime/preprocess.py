"""Frames and calibrated cameras to model inputs (numpy and OpenCV only: the runtime's side, no torch).

The model works on pinhole images at its own sizes. A `Resampler` maps a camera's frames (any size,
OpenCV distortion) onto the undistorted pinhole image of the same camera at the model's size with
precomputed tables: a box prefilter when shrinking by 2x or more (against aliasing; `cv2.resize`
with INTER_AREA at an integer factor, which is the exact box mean), then one bilinear `cv2.remap`
through fixed-point maps (`cv2.convertMaps` to CV_16SC2: coordinates to 1/32 pixel, OpenCV's own
precision for bilinear remapping, so the conversion costs nothing in accuracy and saves it per
frame). uint8 frames stay uint8 until the small image is converted to float32 (each step rounds
to 1/255: the result is within about 1/255 of the float computation); float frames are resampled in
float32. Depth maps are sampled at the nearest source pixel, never blended across edges.
"""
from __future__ import annotations

import cv2
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


def source_coordinates(camera: CameraModel, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) float64 (H', W') arrays: where, in the camera's own frame, each pixel of its pinhole
    image at `size` (W', H') lies."""
    w, h = int(size[0]), int(size[1])
    target = pinhole(camera, (w, h))
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    # Undistorted normalised coordinates of each output pixel, then where the real camera sees them.
    y = (v - target.cy) / target.fy
    x = (u - target.cx - target.K[0, 1] * y) / target.fx
    xy = camera.distort_normalized(np.stack([x, y], axis=-1))
    src_u = camera.K[0, 0] * xy[..., 0] + camera.K[0, 1] * xy[..., 1] + camera.K[0, 2]
    src_v = camera.K[1, 1] * xy[..., 1] + camera.K[1, 2]
    return src_u, src_v


class Resampler:
    """Precomputed resampling of one camera's frames to its pinhole image at `size`."""

    def __init__(self, camera: CameraModel, size: tuple[int, int]):
        self.camera = camera
        self.size = (int(size[0]), int(size[1]))
        w, h = self.size
        target = pinhole(camera, self.size)
        src_u, src_v = source_coordinates(camera, self.size)
        # Nearest source pixel (depth maps must not be blended across edges), as flat indices.
        iv = np.clip(np.rint(src_v), 0, camera.height - 1).astype(np.int64)
        iu = np.clip(np.rint(src_u), 0, camera.width - 1).astype(np.int64)
        self._nearest = iv * camera.width + iu
        # Box prefilter by the integer factor the image shrinks by (1: none).
        self.prefilter = max(1, int(min(camera.width / w, camera.height / h)))
        f = self.prefilter
        if f > 1:
            src_u = (src_u + 0.5) / f - 0.5
            src_v = (src_v + 0.5) / f - 0.5
        sw, sh = camera.width // f, camera.height // f
        # Clamped coordinates: the border pixels extend outwards (as BORDER_REPLICATE).
        map_x = np.clip(src_u, 0, sw - 1).astype(np.float32)
        map_y = np.clip(src_v, 0, sh - 1).astype(np.float32)
        self._maps = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
        self._shrunk = (sw, sh)
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
        u8 = image.dtype == np.uint8
        img = np.ascontiguousarray(image) if u8 else np.ascontiguousarray(image, dtype=np.float32)
        if self._identity:
            return img.astype(np.float32) * np.float32(1.0 / 255.0) if u8 else np.array(img, dtype=np.float32, order="C")
        f = self.prefilter
        if f > 1:
            sw, sh = self._shrunk
            img = cv2.resize(img[: sh * f, : sw * f], (sw, sh), interpolation=cv2.INTER_AREA)
        out = cv2.remap(img, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if u8:
            return np.multiply(out, np.float32(1.0 / 255.0), dtype=np.float32)
        return out

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """A depth map (H, W) to the pinhole image by nearest sampling (no blending across edges)."""
        depth = np.asarray(depth, dtype=np.float32)
        if depth.ndim != 2:
            raise InferenceError(f"depth of camera '{self.camera.name}' must be H x W, got shape {depth.shape}")
        self._check(depth, "depth map")
        return depth.reshape(-1).take(self._nearest)


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
        key = (camera.name, camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(), camera.model, tuple(size))
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
