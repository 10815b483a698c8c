"""Lens models, on normalised image coordinates (x, y) = (X/Z, Y/Z) of a camera-frame point.

- "pinhole": OpenCV's standard model, radial k1 k2 k3 and tangential p1 p2 (dist = k1 k2 p1 p2 k3).
- "fisheye": OpenCV's fisheye model (Kannala-Brandt, equidistant with an odd polynomial; dist = k1 k2
  k3 k4): with r = |(x, y)| and theta = atan(r), theta_d = theta (1 + k1 theta^2 + k2 theta^4 +
  k3 theta^6 + k4 theta^8) and the distorted point is (theta_d / r) (x, y). With every k at 0 it is
  still the equidistant projection, not the identity: a fisheye camera always distorts.

Pixels follow from the distorted point by K as for any camera (u = fx xd + skew yd + cx, v = fy yd + cy).
Both models are the ones `cv2.projectPoints` and `cv2.fisheye.projectPoints` compute; the tests hold
these functions to them.
"""
from __future__ import annotations

import cv2
import numpy as np

MODELS = ("pinhole", "fisheye")
N_DIST = {"pinhole": 5, "fisheye": 4}
DIST_NAMES = {"pinhole": ("k1", "k2", "p1", "p2", "k3"), "fisheye": ("k1", "k2", "k3", "k4")}
# Below this r (normalised), theta / r and its derivatives take their limits at r = 0.
_R_SMALL = 1e-9


def check_model(model: str, where: str) -> str:
    if model not in MODELS:
        raise ValueError(f"{where}: unknown lens model {model!r} (allowed: {', '.join(MODELS)})")
    return model


def coefficients(model: str, dist: np.ndarray) -> np.ndarray:
    """`dist` padded with zeros (or cut) to the model's number of terms."""
    d = np.zeros(N_DIST[model])
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    d[: min(len(d), dist.size)] = dist[: len(d)]
    return d


def _theta_poly(theta: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """theta_d and d(theta_d)/d(theta) of the fisheye polynomial."""
    t2 = theta * theta
    poly = 1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))
    dpoly = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
    return theta * poly, dpoly


def distort_fisheye(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    k = coefficients("fisheye", dist)
    r = np.hypot(xy[..., 0], xy[..., 1])
    theta = np.arctan(r)
    theta_d, _ = _theta_poly(theta, k)
    small = r < _R_SMALL
    scale = np.where(small, 1.0, theta_d / np.where(small, 1.0, r))
    return xy * scale[..., None]


def distort_pinhole(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    k1, k2, p1, p2, k3 = coefficients("pinhole", dist)
    x = xy[..., 0]
    y = xy[..., 1]
    # A diverging solve's lens (or its undistortion's iterate) can send points beyond float range:
    # they come back inf or NaN, which the callers test for, without a warning on the user's screen.
    with np.errstate(over="ignore", invalid="ignore"):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def distort(model: str, dist: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distorted normalised coordinates (..., 2) of undistorted ones."""
    return distort_fisheye(xy, dist) if model == "fisheye" else distort_pinhole(xy, dist)


def undistort_fisheye(xyd: np.ndarray, dist: np.ndarray, iterations: int = 30) -> np.ndarray:
    """Undistorted normalised coordinates of distorted ones: Newton's method on theta_d(theta).
    Points the model cannot reach (theta at or beyond 90 degrees, or where the polynomial turns
    back) come out NaN."""
    k = coefficients("fisheye", dist)
    xyd = np.asarray(xyd, dtype=np.float64)
    theta_d = np.hypot(xyd[..., 0], xyd[..., 1])
    theta = theta_d.copy()
    for _ in range(iterations):
        f, df = _theta_poly(theta, k)
        step = (f - theta_d) / np.where(df > 0, df, np.nan)
        theta = np.clip(theta - step, 0.0, np.pi / 2)
        if np.all(~np.isfinite(step) | (np.abs(step) < 1e-15)):
            break
    f, df = _theta_poly(theta, k)
    ok = (df > 0) & (np.abs(f - theta_d) < 1e-9) & (theta < np.pi / 2 - 1e-6)
    small = theta_d < _R_SMALL
    scale = np.where(small, 1.0, np.tan(theta) / np.where(small, 1.0, theta_d))
    out = xyd * scale[..., None]
    out[~ok & ~small] = np.nan
    return out


def undistort_pinhole(xyd: np.ndarray, dist: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Fixed-point inverse of the pinhole distortion (as cv2.undistortPoints iterates)."""
    xyd = np.asarray(xyd, dtype=np.float64)
    xu = xyd.copy()
    for _ in range(iterations):
        xu = xu - (distort_pinhole(xu, dist) - xyd)
    return xu


def undistort(model: str, dist: np.ndarray, xyd: np.ndarray, iterations: int = 20) -> np.ndarray:
    if model == "fisheye":
        return undistort_fisheye(xyd, dist, max(iterations, 30))
    return undistort_pinhole(xyd, dist, iterations)


def undistort_rectify_map(model: str, K: np.ndarray, dist: np.ndarray, R: np.ndarray, P: np.ndarray,
                          size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Lookup maps (cv2.remap) from the undistorted, rotated image with intrinsics P to the camera's own."""
    if model == "fisheye":
        return cv2.fisheye.initUndistortRectifyMap(K, coefficients("fisheye", dist), R, P, size, cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(K, dist, R, P, size, cv2.CV_32FC1)


# -- per-point projection and its derivatives, for the bundle adjustment -------------------------------
# Intrinsics per point (N, 9): fx fy cx cy and the distortion terms; a fisheye camera uses the first
# four terms (k1..k4) and leaves the ninth slot unused.

def fisheye_terms(x: np.ndarray, y: np.ndarray, k: np.ndarray):
    """For points (x, y) and coefficients k (N, 4): the distorted point (xd, yd), its derivatives
    d(xd, yd)/d(k1..k4) (N, 2, 4) and d(xd, yd)/d(x, y) (N, 2, 2)."""
    r = np.hypot(x, y)
    small = r < _R_SMALL
    rs = np.where(small, 1.0, r)
    theta = np.arctan(r)
    t2 = theta * theta
    k1, k2, k3, k4 = k.T
    poly = 1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    dpoly = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    theta_d = theta * poly
    s = np.where(small, 1.0, theta_d / rs)  # xd = s x
    # (ds/dr) / r, finite at r = 0 (its limit there: 2 (k1 - 1/3))
    q = np.where(small, 2 * (k1 - 1.0 / 3.0), (dpoly / (1 + r * r) * rs - theta_d) / (rs ** 3))
    xd, yd = s * x, s * y
    powers = np.stack([theta ** 3, theta ** 5, theta ** 7, theta ** 9], axis=-1) / rs[:, None]  # d s / d k
    powers = np.where(small[:, None], 0.0, powers)
    dk = np.stack([powers * x[:, None], powers * y[:, None]], axis=1)
    dxy = np.empty((len(x), 2, 2))
    dxy[:, 0, 0] = s + q * x * x
    dxy[:, 0, 1] = q * x * y
    dxy[:, 1, 0] = q * x * y
    dxy[:, 1, 1] = s + q * y * y
    return xd, yd, dk, dxy


def project_points(intr: np.ndarray, Xc: np.ndarray, fisheye: np.ndarray | None = None) -> np.ndarray:
    """Pixels of camera-frame points (N, 3) with per-point intrinsics (N, 9); `fisheye` (N,) bool marks
    the points of fisheye cameras."""
    z = Xc[:, 2]
    x = Xc[:, 0] / z
    y = Xc[:, 1] / z
    out = np.empty((len(x), 2))
    fe = np.zeros(len(x), dtype=bool) if fisheye is None else np.asarray(fisheye, dtype=bool)
    fx, fy, cx, cy = intr[:, 0], intr[:, 1], intr[:, 2], intr[:, 3]
    if (~fe).any():
        p = ~fe
        k1, k2, p1, p2, k3 = intr[p, 4:9].T
        xp, yp = x[p], y[p]
        r2 = xp * xp + yp * yp
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xp * radial + 2 * p1 * xp * yp + p2 * (r2 + 2 * xp * xp)
        yd = yp * radial + p1 * (r2 + 2 * yp * yp) + 2 * p2 * xp * yp
        out[p, 0] = fx[p] * xd + cx[p]
        out[p, 1] = fy[p] * yd + cy[p]
    if fe.any():
        xd, yd, _, _ = fisheye_terms(x[fe], y[fe], intr[fe, 4:8])
        out[fe, 0] = fx[fe] * xd + cx[fe]
        out[fe, 1] = fy[fe] * yd + cy[fe]
    return out
