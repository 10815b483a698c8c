"""Camera rays of the renderer: each pixel's exactly undistorted ray, cached per camera.

The ray of a pixel is (x, y, 1) in the camera frame, found by inverting the lens distortion exactly,
so a hit's ray parameter is its depth and distortion costs nothing per frame. Per camera the cache
also keeps the ranges of the rays by column and row, from which the renderer finds the rectangle of
pixels a bounding sphere can reach under any distortion.
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np

from calibration.camera import CameraModel
from simulator.errors import SimulatorError

NEAR = 0.01  # metres: nothing closer to the camera is drawn


def check_camera(camera: CameraModel) -> None:
    """Raise SimulatorError for a camera the renderer cannot use."""
    if not isinstance(camera, CameraModel):
        raise SimulatorError(f"expected a CameraModel, got {type(camera).__name__}")
    if camera.width <= 0 or camera.height <= 0:
        raise SimulatorError(f"camera {camera.name}: image size must be positive, got {camera.width}x{camera.height}")
    if not np.all(np.isfinite(camera.K)) or camera.fx <= 0 or camera.fy <= 0:
        raise SimulatorError(f"camera {camera.name}: focal lengths must be positive and finite, got fx={camera.fx} fy={camera.fy}")
    if not (np.all(np.isfinite(camera.dist)) and np.all(np.isfinite(camera.R)) and np.all(np.isfinite(camera.t))):
        raise SimulatorError(f"camera {camera.name}: distortion and pose must be finite")
    if not np.allclose(camera.R @ camera.R.T, np.eye(3), atol=1e-6) or np.linalg.det(camera.R) < 0:
        raise SimulatorError(f"camera {camera.name}: R is not a rotation matrix")


def _distortion_jacobian(cam: CameraModel, x: np.ndarray, y: np.ndarray):
    d = np.zeros(5)
    d[: min(5, cam.dist.size)] = cam.dist[:5]
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    g = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d(rad)/d(r2)
    a = rad + 2 * x * x * g + 2 * p1 * y + 6 * p2 * x
    b = 2 * x * y * g + 2 * p1 * x + 2 * p2 * y
    d_ = rad + 2 * y * y * g + 6 * p1 * y + 2 * p2 * x
    return a, b, b, d_


class CameraRays:
    """Undistorted ray directions of every pixel centre of one camera, and their ranges."""

    def __init__(self, cam: CameraModel):
        H, W = cam.height, cam.width
        u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
        yd = (v - cam.cy) / cam.fy
        xd = (u - cam.cx - cam.K[0, 1] * yd) / cam.fx
        xy = np.stack([xd, yd], axis=-1)
        if cam.model == "fisheye":
            xy = cam.undistort_normalized(np.stack([u, v], axis=-1))
            if not np.all(np.isfinite(xy)):
                raise SimulatorError(f"camera {cam.name}: its fisheye lens sees 90 degrees or more off its axis inside "
                                     f"the image, which this renderer's rays (x, y, 1) cannot represent")
        elif cam.has_distortion:
            # Newton's method on the distortion polynomial: every ray exact to ~1e-12.
            for it in range(30):
                dxy = cam.distort_normalized(xy)
                ex, ey = dxy[..., 0] - xd, dxy[..., 1] - yd
                if it >= 3 and max(np.abs(ex).max(), np.abs(ey).max()) < 1e-13:
                    break
                a, b, c, d = _distortion_jacobian(cam, xy[..., 0], xy[..., 1])
                det = a * d - b * c
                xy[..., 0] -= (d * ex - b * ey) / det
                xy[..., 1] -= (a * ey - c * ex) / det
            res = np.abs(cam.distort_normalized(xy) - np.stack([xd, yd], axis=-1)).max()
            if not np.isfinite(res) or res * max(cam.fx, cam.fy) > 1e-6:
                raise SimulatorError(f"camera {cam.name}: the distortion cannot be inverted over the image "
                                     f"(residual {res * max(cam.fx, cam.fy):.2g} px); it folds over inside the frame")
        self.width, self.height = W, H
        self.X = np.ascontiguousarray(xy[..., 0], dtype=np.float32)
        self.Y = np.ascontiguousarray(xy[..., 1], dtype=np.float32)
        self.Xf, self.Yf = self.X.ravel(), self.Y.ravel()
        self.col_min = self.X.min(axis=0).astype(np.float64)
        self.col_max = self.X.max(axis=0).astype(np.float64)
        self.row_min = self.Y.min(axis=1).astype(np.float64)
        self.row_max = self.Y.max(axis=1).astype(np.float64)
        self.monotonic = all(np.all(np.diff(a) >= 0) for a in (self.col_min, self.col_max, self.row_min, self.row_max))
        self.f = math.sqrt(cam.fx * cam.fy)

    def _span(self, lo, hi, a0, a1):
        """Index ranges [i0, i1) of the entries whose [a0, a1] range meets [lo, hi]."""
        if self.monotonic:
            return np.searchsorted(a1, lo, "left"), np.searchsorted(a0, hi, "right")
        i0 = np.zeros(lo.shape, np.int64)
        i1 = np.zeros(lo.shape, np.int64)
        for n in range(lo.size):
            hit = np.flatnonzero((a1 >= lo[n]) & (a0 <= hi[n]))
            if hit.size:
                i0[n], i1[n] = hit[0], hit[-1] + 1
        return i0, i1

    def boxes(self, batch) -> np.ndarray:
        """Pixel rectangles (n, 4): v0, v1, u0, u1 (ends exclusive) holding every pixel whose ray can
        meet each primitive of the batch; empty rectangles (v0 >= v1) where none can."""
        return self.sphere_boxes(batch.sphere_c, batch.sphere_r, batch.sphere_j, len(batch.ks))

    def sphere_boxes(self, c, r, j, n) -> np.ndarray:
        """As `boxes`, for n objects each enclosed by the camera-frame spheres (c[i], r[i]) with j[i]
        naming the object."""
        c = np.asarray(c, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(r, dtype=np.float64).ravel()
        cx, cy, cz = c[:, 0], c[:, 1], c[:, 2]
        den = np.maximum(cz * cz - r * r, 1e-12)
        sx = r * np.sqrt(np.maximum(cx * cx + den, 0.0))
        sy = r * np.sqrt(np.maximum(cy * cy + den, 0.0))
        x0 = (cx * cz - sx) / den
        x1 = (cx * cz + sx) / den
        y0 = (cy * cz - sy) / den
        y1 = (cy * cz + sy) / den
        behind = cz + r <= NEAR
        crossing = ~behind & (cz - r <= NEAR)
        x0[behind] = y0[behind] = np.inf
        x1[behind] = y1[behind] = -np.inf
        x0[crossing] = y0[crossing] = -np.inf
        x1[crossing] = y1[crossing] = np.inf
        lo_x = np.full(n, np.inf)
        hi_x = np.full(n, -np.inf)
        lo_y = np.full(n, np.inf)
        hi_y = np.full(n, -np.inf)
        np.minimum.at(lo_x, j, x0)
        np.maximum.at(hi_x, j, x1)
        np.minimum.at(lo_y, j, y0)
        np.maximum.at(hi_y, j, y1)
        u0, u1 = self._span(lo_x, hi_x, self.col_min, self.col_max)
        v0, v1 = self._span(lo_y, hi_y, self.row_min, self.row_max)
        out = np.stack([v0, v1, u0, u1], axis=1).astype(np.int64)
        empty = (u0 >= u1) | (v0 >= v1)
        out[empty] = 0
        return out


_RAYS: OrderedDict = OrderedDict()
_RAYS_LOCK = threading.Lock()


def camera_rays(cam: CameraModel) -> CameraRays:
    """The cached rays of a camera (keyed by its intrinsics and size, not its pose)."""
    key = (cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes(), cam.model)
    with _RAYS_LOCK:
        rays = _RAYS.get(key)
        if rays is not None:
            _RAYS.move_to_end(key)
            return rays
    rays = CameraRays(cam)
    with _RAYS_LOCK:
        _RAYS[key] = rays
        while len(_RAYS) > 16:
            _RAYS.popitem(last=False)
    return rays
