"""Sparse bundle adjustment of a camera rig observing a planar board.

Unknowns: intrinsics per camera (fx fy cx cy and the lens's distortion terms: k1 k2 p1 p2 k3 for a
pinhole lens, k1 k2 k3 k4 for a fisheye one, whose ninth slot is unused and held), the pose of every
camera in the world (world-to-camera rotation and translation; the reference camera is held at the
origin to fix the gauge) and the pose of the board in every view (board-to-world). The board's known geometry fixes the scale.

Each corner depends on one block of each kind (its camera's intrinsics, its camera's pose, its view's
pose), so the Jacobian is block-sparse: we evaluate each corner's 2x21 block analytically, sum the
21x21 normal-equation blocks per camera view, scatter them into the (small, dense) normal matrix and
solve with Levenberg-Marquardt and Marquardt's diagonal scaling. Rotations are updated on the manifold
(R <- exp([d]x) R), which keeps every step well-conditioned whatever the rotation.
`numeric_jacobian` is the plain finite-difference reference the analytic one is tested against.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.geometry import rodrigues, rotation_vector
from calibration.lens import fisheye_terms, project_points
from calibration.uncertainty import parameter_std

N_INTR = 9
N_LOCAL = N_INTR + 6 + 6
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
FISHEYE_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "")


def intrinsic_names(model: str) -> tuple[str, ...]:
    """The nine intrinsic slots' names for a lens model ("" marks an unused slot)."""
    return FISHEYE_NAMES if model == "fisheye" else INTRINSIC_NAMES


@dataclass
class Problem:
    """Observations: one row per detected corner."""

    cam_idx: np.ndarray  # (M,) camera index of each corner
    view_idx: np.ndarray  # (M,) view index
    board_xyz: np.ndarray  # (M, 3) corner on the board (board frame, metres)
    uv: np.ndarray  # (M, 2) detected pixel position
    n_cameras: int
    n_views: int
    fisheye: np.ndarray | None = None  # (C,) bool: the cameras with a fisheye lens

    def point_fisheye(self) -> np.ndarray | None:
        return None if self.fisheye is None or not np.any(self.fisheye) else np.asarray(self.fisheye, dtype=bool)[self.cam_idx]


@dataclass
class State:
    intr: np.ndarray  # (C, 9)
    Rc: np.ndarray  # (C, 3, 3) world-to-camera
    tc: np.ndarray  # (C, 3)
    Rv: np.ndarray  # (V, 3, 3) board-to-world
    tv: np.ndarray  # (V, 3)

    @classmethod
    def from_vectors(cls, intr, cams, views) -> "State":
        cams = np.asarray(cams, dtype=np.float64)
        views = np.asarray(views, dtype=np.float64)
        return cls(np.array(intr, dtype=np.float64), rodrigues(cams[:, :3]), cams[:, 3:].copy(), rodrigues(views[:, :3]), views[:, 3:].copy())

    def vectors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cams = np.concatenate([np.array([rotation_vector(R) for R in self.Rc]).reshape(-1, 3), self.tc], axis=1)
        views = np.concatenate([np.array([rotation_vector(R) for R in self.Rv]).reshape(-1, 3), self.tv], axis=1)
        return self.intr.copy(), cams, views

    def updated(self, d_intr: np.ndarray, d_cam: np.ndarray, d_view: np.ndarray) -> "State":
        """The state moved by a step: intrinsics and translations add, rotations compose on the left."""
        return State(self.intr + d_intr, rodrigues(d_cam[:, :3]) @ self.Rc, self.tc + d_cam[:, 3:],
                     rodrigues(d_view[:, :3]) @ self.Rv, self.tv + d_view[:, 3:])


@dataclass
class Solution:
    intrinsics: np.ndarray  # (C, 9)
    cameras: np.ndarray  # (C, 6) world-to-camera rvec, t
    views: np.ndarray  # (V, 6) board-to-world rvec, t
    residuals: np.ndarray  # (M, 2) pixels, in the problem's corner order
    iterations: int
    converged: bool
    # (C, 9) one-sigma uncertainty; NaN where it is not known: a slot held fixed (not estimated), or one
    # the covariance could not be computed for (`std_unknown_reason` says why). Never a stand-in 0.
    intrinsics_std: np.ndarray
    std_unknown_reason: str | None = None
    # (C, 9, 9) what the corners say about each camera's intrinsics with every other unknown (board
    # poses, camera poses, other cameras' intrinsics) marginalised: the inverse of its covariance
    # block, in 1 / (unit of the slot)^2. Zero rows and columns for held slots. None when the noise
    # could not be estimated. A single-camera fit's is that lens's prior in a joint solve.
    intrinsics_information: np.ndarray | None = None

    def rms(self, mask: np.ndarray | None = None) -> float:
        r = self.residuals if mask is None else self.residuals[mask]
        return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else float("nan")


def _camera_points(problem: Problem, s: State):
    ci, vi = problem.cam_idx, problem.view_idx
    Xb = np.einsum("mij,mj->mi", s.Rv[vi], problem.board_xyz)  # board point rotated into the world
    Xw = Xb + s.tv[vi]
    Xr = np.einsum("mij,mj->mi", s.Rc[ci], Xw)  # world point rotated into the camera
    return Xb, Xr, Xr + s.tc[ci]


def residuals(problem: Problem, s: State) -> np.ndarray:
    _, _, Xc = _camera_points(problem, s)
    return project_points(s.intr[problem.cam_idx], Xc, problem.point_fisheye()) - problem.uv


def _skew_neg(a: np.ndarray) -> np.ndarray:
    """-[a]x for (M, 3) vectors: d(exp([d]x) a)/dd at d = 0."""
    z = np.zeros(len(a))
    return np.stack([np.stack([z, a[:, 2], -a[:, 1]], -1), np.stack([-a[:, 2], z, a[:, 0]], -1), np.stack([a[:, 1], -a[:, 0], z], -1)], -2)


def jacobian(problem: Problem, s: State) -> np.ndarray:
    """(M, 2, 21): each corner's residual w.r.t. its camera's intrinsics (9), its camera's pose (rotation
    increment, translation) and its view's pose (rotation increment, translation)."""
    ci = problem.cam_idx
    Xb, Xr, Xc = _camera_points(problem, s)
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = s.intr[ci].T
    z = Xc[:, 2]
    x = Xc[:, 0] / z
    y = Xc[:, 1] / z
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    M = len(x)
    J = np.zeros((M, 2, N_LOCAL))
    J[:, 0, 0] = xd
    J[:, 1, 1] = yd
    J[:, 0, 2] = 1.0
    J[:, 1, 3] = 1.0
    J[:, 0, 4] = fx * x * r2
    J[:, 1, 4] = fy * y * r2
    J[:, 0, 5] = fx * x * r2 * r2
    J[:, 1, 5] = fy * y * r2 * r2
    J[:, 0, 6] = fx * 2 * x * y
    J[:, 1, 6] = fy * (r2 + 2 * y * y)
    J[:, 0, 7] = fx * (r2 + 2 * x * x)
    J[:, 1, 7] = fy * 2 * x * y
    J[:, 0, 8] = fx * x * r2 ** 3
    J[:, 1, 8] = fy * y * r2 ** 3
    # Pixel w.r.t. the camera-frame point: focal scaling, distortion, perspective division.
    g = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dxx = radial + 2 * x * x * g + 2 * p1 * y + 6 * p2 * x
    dxy = 2 * x * y * g + 2 * p1 * x + 2 * p2 * y
    dyy = radial + 2 * y * y * g + 6 * p1 * y + 2 * p2 * x
    A = np.empty((M, 2, 2))
    A[:, 0, 0] = fx * dxx
    A[:, 0, 1] = fx * dxy
    A[:, 1, 0] = fy * dxy
    A[:, 1, 1] = fy * dyy
    Pz = np.zeros((M, 2, 3))
    Pz[:, 0, 0] = 1 / z
    Pz[:, 1, 1] = 1 / z
    Pz[:, 0, 2] = -x / z
    Pz[:, 1, 2] = -y / z
    fe = problem.point_fisheye()
    if fe is not None:  # fisheye cameras' corners: their own distortion terms and derivatives
        xd_f, yd_f, dk, dxy = fisheye_terms(x[fe], y[fe], s.intr[ci[fe], 4:8])
        Jf = np.zeros((int(fe.sum()), 2, N_INTR))
        Jf[:, 0, 0] = xd_f
        Jf[:, 1, 1] = yd_f
        Jf[:, 0, 2] = 1.0
        Jf[:, 1, 3] = 1.0
        Jf[:, 0, 4:8] = fx[fe, None] * dk[:, 0]
        Jf[:, 1, 4:8] = fy[fe, None] * dk[:, 1]
        J[fe, :, :N_INTR] = Jf
        A[fe] = np.stack([fx[fe], fy[fe]], -1)[:, :, None] * dxy
    dUV_dXc = A @ Pz  # (M, 2, 3)
    J[:, :, 9:12] = dUV_dXc @ _skew_neg(Xr)
    J[:, :, 12:15] = dUV_dXc
    dUV_dXw = dUV_dXc @ s.Rc[ci]
    J[:, :, 15:18] = dUV_dXw @ _skew_neg(Xb)
    J[:, :, 18:21] = dUV_dXw
    return J


def numeric_jacobian(problem: Problem, s: State, h: float = 1e-6) -> np.ndarray:
    """Central differences of `residuals` in the same local parameters as `jacobian` (the reference)."""
    C, V = len(s.intr), len(s.tv)
    J = np.empty((len(problem.uv), 2, N_LOCAL))
    for k in range(N_LOCAL):
        d = [np.zeros((C, N_INTR)), np.zeros((C, 6)), np.zeros((V, 6))]
        b, slot = (0, k) if k < N_INTR else ((1, k - N_INTR) if k < N_INTR + 6 else (2, k - N_INTR - 6))
        step = h * (max(1.0, float(np.abs(s.intr[:, slot]).max())) if b == 0 and slot < 4 else 1.0)
        d[b][:, slot] = step
        plus = residuals(problem, s.updated(*d))
        d[b][:, slot] = -step
        minus = residuals(problem, s.updated(*d))
        J[:, :, k] = (plus - minus) / (2 * step)
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
    weights: np.ndarray | None = None,
    square_pixels: np.ndarray | None = None,
    prior_std: np.ndarray | None = None,
    prior_mean: np.ndarray | None = None,
    prior_information: np.ndarray | None = None,
) -> Solution:
    """Minimise the squared reprojection error over all free parameters.

    `cams0` (C, 6) and `views0` (V, 6) are rotation vectors and translations. `fixed_intrinsics` (C, 9)
    bool marks intrinsic slots held at their start value (e.g. k3 when a camera has too few views to pin
    it down); the poses of `fixed_cameras` are held (the gauge). `weights` (M,) scales each corner's
    squared error (1 / its noise variance); the returned residuals are unweighted. `square_pixels` (C,)
    bool ties a camera's fy to its fx (one unknown; they must start equal). `prior_std` (C, 9) makes
    intrinsic slots priors: a free slot with a finite value may move from `prior_mean` (default: its
    start value) at a cost of ((value - mean) / prior_std)^2, in the units of the weighted squared
    errors (a weight of 1 is a corner whose noise is 1 px). A fixed slot's prior is moot.
    `prior_information` (C, 9, 9), in the same units, is the general form: camera c's intrinsics x
    cost (x - mean)^T A_c (x - mean), so correlated terms (fx with fy, k1 with k2) move together as
    the fit that measured them allows; it adds to `prior_std`'s terms.
    """
    C, V = problem.n_cameras, problem.n_views
    fisheye = np.zeros(C, dtype=bool) if problem.fisheye is None else np.asarray(problem.fisheye, dtype=bool)
    state = State.from_vectors(np.asarray(intr0).reshape(C, N_INTR), np.asarray(cams0).reshape(C, 6), np.asarray(views0).reshape(V, 6))
    P = C * N_INTR + C * 6 + V * 6
    free, ties, reduced = _unknowns(problem, fisheye, fixed_cameras, fixed_intrinsics, square_pixels)
    Pr = int(free.sum())
    prior_centre_all = np.asarray(intr0 if prior_mean is None else prior_mean, dtype=np.float64).reshape(-1)
    blocks = _prior_blocks(C, reduced, prior_std, prior_information)
    prior_slots = np.concatenate([b[0] for b in blocks]) if blocks else np.zeros(0, dtype=int)

    # Work on corners grouped by camera view, so the normal equations can be summed per view first.
    key = problem.cam_idx.astype(np.int64) * V + problem.view_idx
    order = np.argsort(key, kind="stable")
    prob = Problem(problem.cam_idx[order], problem.view_idx[order], problem.board_xyz[order], problem.uv[order], C, V, problem.fisheye)
    starts = np.flatnonzero(np.r_[True, np.diff(key[order]) != 0])
    ends = np.r_[starts[1:], len(order)]
    gidx = reduced[_global_index(prob)[starts]]
    gidx = np.where(gidx < 0, Pr, gidx)  # fixed columns go to a dummy slot that is dropped
    w = np.ones(len(prob.uv)) if weights is None else np.asarray(weights, dtype=np.float64)[order]
    sw = np.sqrt(w)[:, None]

    def weighted_residuals(s: State) -> np.ndarray:
        return residuals(prob, s) * sw

    def prior_terms(s: State):
        """Each block's offset from its mean and the block's share of the gradient (A d)."""
        flat = s.intr.reshape(-1)
        return [(flat[sl] - prior_centre_all[sl], A) for sl, _, A in blocks]

    def total_cost(r: np.ndarray, s: State) -> float:
        return float(np.sum(r * r) + sum(d @ A @ d for d, A in prior_terms(s)))

    def normal_equations(s: State, r: np.ndarray):
        J = jacobian(prob, s) * sw[:, :, None]
        # One dense product per camera view (tens of corners): far cheaper than a 21x21 block per corner.
        A = np.empty((len(starts), N_LOCAL, N_LOCAL))
        g = np.empty((len(starts), N_LOCAL))
        for k, (a, b) in enumerate(zip(starts, ends)):
            Jo = J[a:b].reshape(-1, N_LOCAL)
            A[k] = Jo.T @ Jo
            g[k] = Jo.T @ r[a:b].reshape(-1)
        n = Pr + 1
        flat = (gidx[:, :, None] * n + gidx[:, None, :]).ravel()
        H = np.bincount(flat, weights=A.ravel(), minlength=n * n).reshape(n, n)[:Pr, :Pr]
        grad = np.bincount(gidx.ravel(), weights=g.ravel(), minlength=n)[:Pr]
        for (_, cols, A), (d, _) in zip(blocks, prior_terms(s)):  # each prior is quadratic in its slots
            np.add.at(H, (cols[:, None], cols[None, :]), A)
            np.add.at(grad, cols, A @ d)
        return H, grad

    def step(s: State, dx: np.ndarray) -> State:
        full = np.zeros(P)
        full[free] = dx
        for dst, src in ties:
            full[dst] = full[src]
        a = C * N_INTR
        b = a + C * 6
        return s.updated(full[:a].reshape(C, N_INTR), full[a:b].reshape(C, 6), full[b:].reshape(V, 6))

    r = weighted_residuals(state)
    cost = total_cost(r, state)
    state, r, cost, it, converged = _levenberg_marquardt(state, r, cost, normal_equations, weighted_residuals, total_cost, step,
                                                         max_iterations, tolerance)

    H, _ = normal_equations(state, r)  # at the solution, not at the last iterate before it
    front = C * N_INTR + C * 6  # intrinsics and camera poses; the board poses after them are marginalised
    n_res = 2 * len(r) + len(prior_slots)
    std_front, why = parameter_std(H, cost, n_res, n_front=int(free[:front].sum()))
    information = _intrinsics_information(H, cost, n_res, free, reduced, C, front)
    std = np.full(front, np.nan)
    std[free[:front]] = std_front
    for dst, src in ties:
        std[dst] = std[src]
    unweighted = np.empty_like(r)
    unweighted[order] = r / sw
    intr, cams, views = state.vectors()
    return Solution(intr, cams, views, unweighted, it, converged, std[: C * N_INTR].reshape(C, N_INTR), why, information)


def _unknowns(problem: Problem, fisheye: np.ndarray, fixed_cameras: tuple[int, ...], fixed_intrinsics: np.ndarray | None,
              square_pixels: np.ndarray | None) -> tuple[np.ndarray, list[tuple[int, int]], np.ndarray]:
    """Which of the flat parameters (intrinsics, camera poses, board poses) are solved for: (free (P,)
    bool, ties (fy slot, fx slot) of square pixels, reduced (P,) each parameter's unknown, -1 held;
    a tied fy shares its fx's)."""
    C, V = problem.n_cameras, problem.n_views
    P = C * N_INTR + C * 6 + V * 6
    free = np.ones(P, dtype=bool)
    if fixed_intrinsics is not None:
        free[: C * N_INTR] = ~np.asarray(fixed_intrinsics, dtype=bool).reshape(-1)
    for c in np.flatnonzero(fisheye):  # the slot a fisheye lens does not use
        free[c * N_INTR + FISHEYE_NAMES.index("")] = False
    for c in fixed_cameras:
        free[C * N_INTR + c * 6 : C * N_INTR + c * 6 + 6] = False
    seen_views = np.zeros(V, dtype=bool)
    seen_views[problem.view_idx] = True
    for v in np.flatnonzero(~seen_views):  # a view with no corners has nothing to solve
        free[C * N_INTR + C * 6 + v * 6 : C * N_INTR + C * 6 + v * 6 + 6] = False
    ties = []  # (fy slot, fx slot): fy moves with fx
    if square_pixels is not None:
        for c in np.flatnonzero(np.asarray(square_pixels, dtype=bool)):
            fx, fy = c * N_INTR + INTRINSIC_NAMES.index("fx"), c * N_INTR + INTRINSIC_NAMES.index("fy")
            if free[fx] and free[fy]:
                free[fy] = False
                ties.append((fy, fx))
    reduced = np.full(P, -1)
    reduced[free] = np.arange(int(free.sum()))
    for dst, src in ties:  # its Jacobian columns add into the fx unknown's
        reduced[dst] = reduced[src]
    return free, ties, reduced


def _prior_blocks(C: int, reduced: np.ndarray, prior_std: np.ndarray | None,
                  prior_information: np.ndarray | None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The priors, per camera an information matrix over its intrinsic slots: those a free (or tied)
    unknown carries, as (slots in the flat intrinsics, their reduced columns, information among them)."""
    info = np.zeros((C, N_INTR, N_INTR))
    if prior_std is not None:
        ps = np.asarray(prior_std, dtype=np.float64).reshape(C, N_INTR)
        ok = np.isfinite(ps) & (ps > 0)
        info[:, np.arange(N_INTR), np.arange(N_INTR)] += np.where(ok, (1.0 / np.where(ok, ps, 1.0)) ** 2, 0.0)  # 1/sigma first: sigma = 1e300 is no weight, not an overflow
    if prior_information is not None:
        info += np.nan_to_num(np.asarray(prior_information, dtype=np.float64).reshape(C, N_INTR, N_INTR))
    blocks = []  # (slots in the flat intrinsics, their reduced columns, information among them)
    for c in range(C):
        slots = c * N_INTR + np.arange(N_INTR)
        has = (reduced[slots] >= 0) & (np.abs(info[c]).sum(axis=1) > 0)
        if has.any():
            blocks.append((slots[has], reduced[slots[has]], info[c][np.ix_(has, has)]))
    return blocks


def _levenberg_marquardt(state: State, r: np.ndarray, cost: float, normal_equations, weighted_residuals, total_cost, step,
                         max_iterations: int, tolerance: float) -> tuple[State, np.ndarray, float, int, bool]:
    """Damped Gauss-Newton steps from `state` (its weighted residuals `r` and cost) until a step no
    longer lowers the cost by `tolerance` of it: (state, r, cost, iterations, converged)."""
    lam = 1e-3
    converged = False
    it = 0
    rel = 0.0
    for it in range(1, max_iterations + 1):
        H, grad = normal_equations(state, r)
        diag = np.diag(H).copy()
        diag[diag <= 0] = 1.0
        improved = False
        for _ in range(12):
            try:
                dx = np.linalg.solve(H + lam * np.diag(diag), -grad)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            candidate = step(state, dx)
            r_new = weighted_residuals(candidate)
            cost_new = total_cost(r_new, candidate)
            if np.isfinite(cost_new) and cost_new < cost:
                rel = (cost - cost_new) / max(cost, 1e-300)
                state, r, cost = candidate, r_new, cost_new
                lam = max(lam / 3.0, 1e-12)
                improved = True
                break
            lam *= 4.0
        if not improved or rel < tolerance:
            converged = True
            break
    return state, r, cost, it, converged


def _intrinsics_information(H: np.ndarray, cost: float, n_residuals: int, free: np.ndarray, reduced: np.ndarray, C: int,
                            front: int) -> np.ndarray | None:
    """(C, 9, 9): each camera's intrinsics' information, everything else marginalised (see Solution)."""
    from calibration.uncertainty import front_information

    nf = int(free[:front].sum())
    S = front_information(H, cost, n_residuals, nf)
    if S is None:
        return None
    out = np.zeros((C, N_INTR, N_INTR))
    for c in range(C):
        slots = c * N_INTR + np.arange(N_INTR)
        own = free[slots]
        if not own.any():
            continue
        cols = reduced[slots[own]]
        rest = np.setdiff1d(np.arange(nf), cols)
        # marginalise the other front unknowns: a pseudo-inverse, as a direction they leave open is
        # one the corners do not determine, not one they pin down
        block = S[np.ix_(cols, cols)] - S[np.ix_(cols, rest)] @ np.linalg.pinv(S[np.ix_(rest, rest)]) @ S[np.ix_(rest, cols)] \
            if len(rest) else S[np.ix_(cols, cols)]
        out[c][np.ix_(own, own)] = 0.5 * (block + block.T)
    return out

