"""Sparse bundle adjustment of a camera rig observing a planar board.

Unknowns: intrinsics per camera (fx fy cx cy k1 k2 p1 p2 k3), the pose of every camera in the world
(world-to-camera rotation vector and translation; the reference camera is held at the origin to fix the
gauge) and the pose of the board in every view (board-to-world). The board's known geometry fixes the
scale. Each corner observation depends on one block of each kind, so the Jacobian is block-sparse: we
evaluate it per observation (21 columns, central differences applied to all blocks at once) and
accumulate the normal equations by scattering each observation's 21x21 block; Levenberg-Marquardt with
Marquardt's diagonal scaling solves them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.geometry import project_rad_tan, rodrigues

N_INTR = 9
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")

# Central-difference steps per parameter slot: pixels for fx..cy, unitless for distortion,
# radians for rotations, metres for translations.
_STEPS = np.array([1e-4, 1e-4, 1e-4, 1e-4, 1e-7, 1e-7, 1e-8, 1e-8, 1e-7] + [1e-7] * 3 + [1e-7] * 3 + [1e-7] * 3 + [1e-7] * 3)


@dataclass
class Problem:
    """Observations: one row per detected corner."""

    cam_idx: np.ndarray  # (M,) camera index of each corner
    view_idx: np.ndarray  # (M,) view index
    board_xyz: np.ndarray  # (M, 3) corner on the board (board frame, metres)
    uv: np.ndarray  # (M, 2) detected pixel position
    n_cameras: int
    n_views: int


@dataclass
class Solution:
    intrinsics: np.ndarray  # (C, 9)
    cameras: np.ndarray  # (C, 6) world-to-camera rvec, t
    views: np.ndarray  # (V, 6) board-to-world rvec, t
    residuals: np.ndarray  # (M, 2) pixels
    iterations: int
    converged: bool
    intrinsics_std: np.ndarray  # (C, 9) one-sigma uncertainty (0 where held fixed)

    def rms(self, mask: np.ndarray | None = None) -> float:
        r = self.residuals if mask is None else self.residuals[mask]
        return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else float("nan")


def residuals(problem: Problem, intr: np.ndarray, cams: np.ndarray, views: np.ndarray) -> np.ndarray:
    Rc = rodrigues(cams[:, :3])
    Rv = rodrigues(views[:, :3])
    ci, vi = problem.cam_idx, problem.view_idx
    Xw = np.einsum("mij,mj->mi", Rv[vi], problem.board_xyz) + views[vi, 3:]
    Xc = np.einsum("mij,mj->mi", Rc[ci], Xw) + cams[ci, 3:]
    return project_rad_tan(intr[ci], Xc) - problem.uv


def _jacobian(problem: Problem, intr: np.ndarray, cams: np.ndarray, views: np.ndarray) -> np.ndarray:
    """(M, 2, 21): derivative of each corner's residual w.r.t. its camera's intrinsics, pose and its view's pose."""
    M = len(problem.uv)
    J = np.empty((M, 2, 21))
    blocks = (intr, cams, views)
    offsets = (0, N_INTR, N_INTR + 6)
    for b, block in enumerate(blocks):
        for k in range(block.shape[1]):
            slot = offsets[b] + k
            h = _STEPS[slot] * (max(1.0, float(np.abs(block[:, k]).max())) if b == 0 and k < 4 else 1.0)
            plus = [x.copy() for x in blocks]
            minus = [x.copy() for x in blocks]
            plus[b][:, k] += h
            minus[b][:, k] -= h
            J[:, :, slot] = (residuals(problem, *plus) - residuals(problem, *minus)) / (2 * h)
    return J


def _global_index(problem: Problem) -> np.ndarray:
    """(M, 21) index of each local Jacobian column in the full parameter vector."""
    C = problem.n_cameras
    ci = problem.cam_idx[:, None]
    vi = problem.view_idx[:, None]
    intr = ci * N_INTR + np.arange(N_INTR)[None, :]
    cam = C * N_INTR + ci * 6 + np.arange(6)[None, :]
    view = C * N_INTR + C * 6 + vi * 6 + np.arange(6)[None, :]
    return np.concatenate([intr, cam, view], axis=1)


def solve(
    problem: Problem,
    intr0: np.ndarray,
    cams0: np.ndarray,
    views0: np.ndarray,
    fixed_cameras: tuple[int, ...] = (0,),
    fixed_intrinsics: np.ndarray | None = None,
    max_iterations: int = 60,
    tolerance: float = 1e-10,
) -> Solution:
    """Minimise the squared reprojection error over all free parameters.

    `fixed_intrinsics` (C, 9) bool marks intrinsic slots held at their start value (e.g. k3 when a camera
    has too few views to pin it down); the poses of `fixed_cameras` are held (the gauge).
    """
    C, V = problem.n_cameras, problem.n_views
    intr = np.array(intr0, dtype=np.float64).reshape(C, N_INTR)
    cams = np.array(cams0, dtype=np.float64).reshape(C, 6)
    views = np.array(views0, dtype=np.float64).reshape(V, 6)
    P = C * N_INTR + C * 6 + V * 6
    free = np.ones(P, dtype=bool)
    if fixed_intrinsics is not None:
        free[: C * N_INTR] = ~np.asarray(fixed_intrinsics, dtype=bool).reshape(-1)
    for c in fixed_cameras:
        free[C * N_INTR + c * 6 : C * N_INTR + c * 6 + 6] = False
    seen_views = np.zeros(V, dtype=bool)
    seen_views[problem.view_idx] = True
    for v in np.flatnonzero(~seen_views):  # a view with no corners has nothing to solve
        free[C * N_INTR + C * 6 + v * 6 : C * N_INTR + C * 6 + v * 6 + 6] = False
    reduced = np.full(P, -1)
    reduced[free] = np.arange(int(free.sum()))
    Pr = int(free.sum())
    gidx = reduced[_global_index(problem)]
    gidx = np.where(gidx < 0, Pr, gidx)  # fixed columns go to a dummy slot that is dropped

    def pack() -> np.ndarray:
        return np.concatenate([intr.ravel(), cams.ravel(), views.ravel()])

    def unpack(p: np.ndarray):
        a = C * N_INTR
        b = a + C * 6
        return p[:a].reshape(C, N_INTR), p[a:b].reshape(C, 6), p[b:].reshape(V, 6)

    def normal_equations(J: np.ndarray, r: np.ndarray):
        n = Pr + 1
        A = np.einsum("mri,mrj->mij", J, J)
        g = np.einsum("mri,mr->mi", J, r)
        flat = (gidx[:, :, None] * n + gidx[:, None, :]).ravel()
        H = np.bincount(flat, weights=A.ravel(), minlength=n * n).reshape(n, n)[:Pr, :Pr]
        grad = np.bincount(gidx.ravel(), weights=g.ravel(), minlength=n)[:Pr]
        return H, grad

    p = pack()
    r = residuals(problem, intr, cams, views)
    cost = float(np.sum(r * r))
    lam = 1e-3
    converged = False
    it = 0
    H = None
    for it in range(1, max_iterations + 1):
        J = _jacobian(problem, *unpack(p))
        H, grad = normal_equations(J, r)
        diag = np.diag(H).copy()
        diag[diag <= 0] = 1.0
        improved = False
        for _ in range(12):
            A = H + lam * np.diag(diag)
            try:
                dx = np.linalg.solve(A, -grad)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            p_new = p.copy()
            p_new[free] += dx
            r_new = residuals(problem, *unpack(p_new))
            cost_new = float(np.sum(r_new * r_new))
            if np.isfinite(cost_new) and cost_new < cost:
                rel = (cost - cost_new) / max(cost, 1e-300)
                p, r, cost = p_new, r_new, cost_new
                lam = max(lam / 3.0, 1e-12)
                improved = True
                break
            lam *= 4.0
        if not improved or rel < tolerance:
            converged = True
            break

    intr, cams, views = unpack(p)
    std = np.zeros(C * N_INTR)
    if H is not None and len(r) * 2 > Pr:
        sigma2 = cost / (2 * len(r) - Pr)
        try:
            cov_diag = np.diag(np.linalg.inv(H)) * sigma2
            full = np.zeros(P)
            full[free] = np.sqrt(np.clip(cov_diag, 0, None))
            std = full[: C * N_INTR]
        except np.linalg.LinAlgError:
            pass
    return Solution(intr.copy(), cams.copy(), views.copy(), r, it, converged, std.reshape(C, N_INTR))
