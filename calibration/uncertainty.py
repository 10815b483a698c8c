"""One-sigma uncertainty of the parameters of a least-squares fit, from its Gauss-Newton normal matrix
H = J^T W J and its final weighted cost; and, honestly, which parameters it cannot be given for.

The noise variance is estimated as cost / (residuals - unknowns). A parameter's uncertainty is
unknown (NaN), never 0, when there are no more residuals than unknowns, or when the parameter lies
along a direction H does not constrain: a degenerate set of views (e.g. a board only ever seen
squarely, where focal length and board distance trade off exactly). The other parameters keep their
variance from the directions H does constrain.

The bundle adjustment's unknowns end with one 6-parameter pose per board view, and no corner ties two
views, so H's view part is block diagonal: the views are marginalised out (Schur complement) and only
the small block of intrinsics and camera poses is analysed, at a cost linear in the number of views.
"""
from __future__ import annotations

import numpy as np

# A direction of the (Jacobi-scaled) matrix whose eigenvalue is this far below the largest is one the
# observations do not determine: its variance would be round-off amplified, not a measurement.
RCOND = 1e-10
# A parameter with more than this share of its unit vector in such directions is undetermined.
NULL_SHARE = 1e-6
POSE = 6  # parameters of one board view's pose


def parameter_std(H: np.ndarray, cost: float, n_residuals: int, n_front: int | None = None) -> tuple[np.ndarray, str | None]:
    """Uncertainty of the first `n_front` parameters (all by default; the rest must be 6-parameter
    blocks that only couple to themselves and to the front), and why some are unknown (None when all
    are known)."""
    n = len(H)
    nf = n if n_front is None else n_front
    dof = n_residuals - n
    if dof <= 0:
        return np.full(nf, np.nan), f"{n_residuals} residuals for {n} unknowns: nothing is left to estimate the noise with"
    S = _schur_complement(H, nf) if nf < n else H
    if S is None:  # a board pose is undetermined by itself: analyse the whole matrix
        S = H
    std = _std(S, cost / dof)[:nf]
    if np.all(np.isfinite(std)):
        return std, None
    return std, "the views do not determine every parameter (their normal matrix is singular): show the board at more varied tilts"


def _std(H: np.ndarray, sigma2: float) -> np.ndarray:
    std = np.full(len(H), np.nan)
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    seen = d > 0  # a parameter no residual depends on stays unknown
    if not seen.any():
        return std
    Hs = H[np.ix_(seen, seen)] / np.outer(d[seen], d[seen])  # Jacobi scaling: the geometry's conditioning, not the units'
    w, V = np.linalg.eigh(Hs)
    null = w <= RCOND * w.max()
    determined = np.sum(V[:, null] ** 2, axis=1) <= NULL_SHARE
    var = (V[:, ~null] ** 2) @ (1.0 / w[~null])
    std[seen] = np.where(determined, np.sqrt(var * sigma2) / d[seen], np.nan)
    return std


def _schur_complement(H: np.ndarray, nf: int) -> np.ndarray | None:
    """H's front block with the trailing pose blocks marginalised out; None if a pose block is singular."""
    m, rest = divmod(len(H) - nf, POSE)
    if rest:
        raise ValueError(f"{len(H) - nf} trailing parameters are not whole {POSE}-parameter poses")
    idx = np.arange(m)
    D = H[nf:, nf:].reshape(m, POSE, m, POSE)[idx, :, idx, :]  # (m, 6, 6) diagonal blocks
    s = np.sqrt(np.clip(np.einsum("mii->mi", D), 0.0, None))
    if np.any(s <= 0):
        return None
    w = np.linalg.eigvalsh(D / (s[:, :, None] * s[:, None, :]))
    if np.any(w[:, 0] <= RCOND * w[:, -1]):
        return None
    B = H[:nf, nf:]
    BD = (B.reshape(nf, m, POSE).transpose(1, 0, 2) @ np.linalg.inv(D)).transpose(1, 0, 2).reshape(nf, m * POSE)
    return H[:nf, :nf] - BD @ B.T


def front_information(H: np.ndarray, cost: float, n_residuals: int, n_front: int) -> np.ndarray | None:
    """The information (inverse covariance) of the first `n_front` parameters with the trailing pose
    blocks marginalised, in 1 / unit^2 of each parameter: H's Schur complement over the noise
    variance. None when the noise cannot be estimated or a pose block is singular."""
    n = len(H)
    dof = n_residuals - n
    if dof <= 0 or not cost > 0:
        return None
    S = _schur_complement(H, n_front) if n_front < n else H
    if S is None:
        return None
    return S / (cost / dof)
