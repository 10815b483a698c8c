"""Vectorised rotation and projection helpers shared by the solver, the report and the exports."""
from __future__ import annotations

import numpy as np


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3)."""
    r = np.asarray(rvec, dtype=np.float64)
    theta = np.linalg.norm(r, axis=-1)
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    k = r / safe[..., None]
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    zero = np.zeros_like(kx)
    Kx = np.stack([np.stack([zero, -kz, ky], -1), np.stack([kz, zero, -kx], -1), np.stack([-ky, kx, zero], -1)], -2)
    s = np.sin(theta)[..., None, None]
    c = np.cos(theta)[..., None, None]
    eye = np.broadcast_to(np.eye(3), Kx.shape)
    R = eye + s * Kx + (1 - c) * (Kx @ Kx)
    # Below 1e-12 rad the first-order form is exact to double precision.
    Rs = eye + np.stack(
        [np.stack([zero, -r[..., 2], r[..., 1]], -1), np.stack([r[..., 2], zero, -r[..., 0]], -1), np.stack([-r[..., 1], r[..., 0], zero], -1)],
        -2,
    )
    return np.where(small[..., None, None], Rs, R)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of a rotation matrix (3, 3); angle in [0, pi]."""
    import cv2

    rv, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return rv.reshape(3)


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of the rotation that takes Ra to Rb, in degrees.

    From both the sine (the skew part) and the cosine (the trace): arccos of the trace alone cannot
    tell angles below about 1e-6 degrees from 0, which hides how exact a calibration is.
    """
    D = np.asarray(Ra).T @ np.asarray(Rb)
    s = 0.5 * np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])
    c = (np.trace(D) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def average_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (N, 3, 3): the rotation nearest their arithmetic mean."""
    M = np.asarray(Rs).sum(axis=0)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def robust_mean_pose(Rs: np.ndarray, ts: np.ndarray, inlier_deg: float = 2.0) -> tuple[np.ndarray, np.ndarray, int]:
    """Mean of pose samples around their medoid rotation; samples further than `inlier_deg` are ignored.

    Returns (R, t, inliers). Used to initialise relative camera poses from per-view board poses, where a
    few views may be wrong (a mis-detected or flipped board).
    """
    Rs = np.asarray(Rs)
    ts = np.asarray(ts)
    n = len(Rs)
    if n == 1:
        return Rs[0], ts[0], 1
    # Pairwise angles via traces: cos(theta_ij) = (tr(Ri^T Rj) - 1) / 2.
    tr = np.einsum("iab,jab->ij", Rs, Rs)
    ang = np.arccos(np.clip((tr - 1) / 2, -1, 1))
    medoid = int(np.argmin(ang.sum(axis=1)))
    inl = ang[medoid] < np.radians(inlier_deg)
    R = average_rotation(Rs[inl])
    t = np.median(ts[inl], axis=0)
    return R, t, int(inl.sum())


def invert_pose(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return R.T, -R.T @ t


def compose(Ra: np.ndarray, ta: np.ndarray, Rb: np.ndarray, tb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Ra, ta) after (Rb, tb): X -> Ra (Rb X + tb) + ta."""
    return Ra @ Rb, Ra @ tb + ta
