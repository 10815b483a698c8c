"""Calibrating a rig from board detections.

1. intrinsics of every camera alone (`cv2.calibrateCamera`; a fisheye lens: `cv2.fisheye.calibrate`
   to start, then the bundle adjustment below on the one camera), views that do not fit rejected;
2. each camera's pairing with the left camera's instants checked at offsets -2..+2 (calibration.pairing):
   a camera out of step stops the solve unless its offset is given or `auto_offset` applies it;
3. the stereo pair's extrinsics (`cv2.stereoCalibrate`, intrinsics held; on undistorted coordinates
   when a camera of the pair has a fisheye lens);
4. every camera in the left camera's frame, started from the relative poses the board views imply and
   refined jointly with the intrinsics and every board pose by bundle adjustment over all views
   (a board seen by two or more cameras ties them together), each lens held to its own fit of step 1
   by a prior weighted by what that fit measured (`lens_information`; off with `lens_priors=False`,
   when the report still says which lens moved beyond what its own views allow);
   observations that do not fit are rejected with the reason and the adjustment is run again.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import cv2
import numpy as np

from calibration import bundle, lens
from calibration.boards import BoardSpec
from calibration.camera import CalibrationError, CameraModel, RigCalibration
from calibration.detect import Corners
from calibration.geometry import (
    compose,
    invert_pose,
    robust_mean_pose,
    rodrigues,
    rotation_vector,
)
from calibration.images import DetectionSet, natural_key
from calibration.known import prior_sigmas
from calibration.quality import focal_spread
from calibration.report import summary_meta
from calibration.result import CalibrationResult, CameraIntrinsics, Observations, Rejection

MIN_VIEWS_PER_CAMERA = 4
# Below this many views k3 is not observable enough to estimate; it stays 0.
MIN_VIEWS_FOR_K3 = 10


@dataclass
class Options:
    left: str | None = None  # camera at the origin; default "left", else the first camera
    right: str | None = None  # the other camera of the stereo pair; default "right", else the second
    outlier_px: float = 1.0  # an observation is an outlier above max(outlier_px, outlier_factor * median RMS)
    outlier_factor: float = 5.0
    fix_k3: bool | None = None  # None: fix k3 for cameras with fewer than MIN_VIEWS_FOR_K3 views
    fix_tangential: bool | None = None  # hold p1 p2 at 0; None: hold them for cameras with fewer than MIN_VIEWS_FOR_K3 views
    max_rounds: int = 5  # bundle adjustment + rejection rounds
    reweight: bool = True  # weight each camera view by its measured corner noise
    known: dict = field(default_factory=dict)  # camera -> calibration.known.KnownIntrinsics, held fixed throughout
    square_pixels: bool = False  # fy = fx (aspect ratio held at 1)
    centred: bool = False  # principal point held at the image centre
    fisheye: Any = ()  # cameras with a fisheye lens (names), or True for every camera
    # the `known` intrinsics as priors instead of held: term -> (sigma, percent of f) (calibration.known.parse_prior)
    prior: dict = field(default_factory=dict)
    # each camera's single-camera fit as a prior in the joint adjustment, weighted by what that fit
    # measured (False: every fitted term free, the joint corners alone decide; `--free-intrinsics`)
    lens_priors: bool = True
    offsets: dict = field(default_factory=dict)  # camera -> instants its images are re-paired by (calibration.pairing)
    auto_offset: bool = False  # apply an offset the pairing check finds, instead of stopping

    def model_of(self, camera: str) -> str:
        """The lens model to fit for `camera`: given intrinsics carry their own."""
        known = self.known.get(camera)
        if known is not None:
            return known.model
        return "fisheye" if (self.fisheye is True or camera in (self.fisheye or ())) else "pinhole"


def camera_order(names: list[str], left: str | None, right: str | None) -> tuple[list[str], str, str | None]:
    """Left first, right last, the others between in natural order."""
    names = sorted(names, key=natural_key)
    if left is None:
        left = "left" if "left" in names else names[0]
    if left not in names:
        raise CalibrationError(f"no images of camera '{left}' (cameras: {', '.join(names)})")
    rest = [n for n in names if n != left]
    if right is None and rest:
        right = "right" if "right" in rest else rest[-1]
    if right is not None and right not in rest:
        raise CalibrationError(f"no images of camera '{right}' (cameras: {', '.join(names)})")
    middle = [n for n in rest if n != right]
    return [left] + middle + ([right] if right else []), left, right


def _planar(points: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """One view's board points as OpenCV's planar calibration wants them (z = 0), with the frame
    they were moved into: (local points, R, c), local = R^T (p - c); (points, None, None) when they
    already lie on z = 0. The back face of a double-sided board lies on z = thickness, mirrored."""
    if not np.any(points[:, 2]):
        return points, None, None
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c)
    R = vt.T.copy()
    if np.linalg.det(R) < 0:
        R[:, 2] *= -1
    local = (points - c) @ R
    local[:, 2] = 0.0
    return local, R, c


def _board_pose(R_local: np.ndarray, t_local: np.ndarray, R: np.ndarray | None, c: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """A board-to-camera pose found on `_planar`'s local points, in the board's own frame."""
    if R is None:
        return R_local, t_local
    Rb = R_local @ R.T
    return Rb, t_local - Rb @ c


def _view_rms(uv_hat: np.ndarray, uv: np.ndarray) -> float:
    d = uv_hat.reshape(-1, 2) - uv.reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _threshold(values: list[float], opts: Options) -> float:
    return max(opts.outlier_px, opts.outlier_factor * float(np.median(values)))


def _view_limits(view_rms: dict[str, float], opts: Options) -> dict[str, float]:
    """Each view's rejection limit, from the median of the other views: with few views, one bad view
    raises the median of all of them enough to hide itself (six photos, one at 2.08 px, median 0.42)."""
    limits = {}
    for v in view_rms:
        others = [e for w, e in view_rms.items() if w != v]
        limits[v] = _threshold(others or [view_rms[v]], opts)
    return limits


def _holds(camera: str, n_views: int, opts: Options) -> tuple[bool, bool, bool]:
    """(fix_k3, fix_tangential, k3 held for too few views): the higher terms from a handful of views
    are poorly observed and free to absorb a bad view. For a fisheye lens `fix_k3` holds k3 and k4."""
    fix_k3 = opts.fix_k3 if opts.fix_k3 is not None else n_views < MIN_VIEWS_FOR_K3
    fix_tangential = opts.fix_tangential if opts.fix_tangential is not None else n_views < MIN_VIEWS_FOR_K3
    return fix_k3, fix_tangential, fix_k3 and opts.fix_k3 is None and camera not in opts.known


@dataclass
class _Fit:
    rms: float
    K: np.ndarray
    dist: np.ndarray
    view_rms: dict[str, float]
    poses: dict[str, tuple[np.ndarray, np.ndarray]]  # view -> board-to-camera, in the board's own frame
    model: str = "pinhole"


def _pinhole_fit(camera, size, views, names, object_points, opts, fix_k3, fix_tangential, known, guess=None) -> _Fit:
    flags = (cv2.CALIB_FIX_K3 if fix_k3 else 0) | (cv2.CALIB_ZERO_TANGENT_DIST if fix_tangential else 0)
    flags |= (cv2.CALIB_FIX_ASPECT_RATIO if opts.square_pixels else 0) | (cv2.CALIB_FIX_PRINCIPAL_POINT if opts.centred else 0)
    # without an intrinsic guess OpenCV takes only the ratio fx/fy from K (1 here) and puts a held
    # principal point at the image centre
    K0 = np.eye(3) if (opts.square_pixels or opts.centred) else None
    dist0 = None
    if guess is not None:
        K0, dist0 = guess[0].copy(), guess[1].copy()
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    if known is not None:  # only the board poses are solved
        K0, dist0 = known.K.copy(), known.dist.copy()
        flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_FOCAL_LENGTH | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_K1
                 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_TANGENT_DIST)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100 if guess is None else 50, 1e-12 if guess is None else 1e-10)
    planar = [_planar(object_points[views[v].ids]) for v in names]
    obj = [p[0].astype(np.float32) for p in planar]
    img = [views[v].points.astype(np.float32).reshape(-1, 1, 2) for v in names]
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, K0, dist0, flags=flags, criteria=crit)
    except cv2.error as exc:
        raise CalibrationError(f"camera '{camera}': OpenCV could not calibrate it from these views ({exc.err})") from None
    view_rms, poses = {}, {}
    for v, o, i, rv, tv, p in zip(names, obj, img, rvecs, tvecs, planar):
        proj, _ = cv2.projectPoints(o, rv, tv, K, dist)
        view_rms[v] = _view_rms(proj, i)
        poses[v] = _board_pose(cv2.Rodrigues(rv)[0], tv.reshape(3), p[1], p[2])
    return _Fit(float(rms), K, dist.reshape(-1)[:5], view_rms, poses)


def _poses_through(camera: str, K: np.ndarray, D: np.ndarray, obj: list[np.ndarray], img: list[np.ndarray]):
    """Each view's board pose through a fisheye lens: its corners undistorted, then `cv2.solvePnP`."""
    rvecs, tvecs = [], []
    for o, i in zip(obj, img):
        xy = lens.undistort_fisheye((i.reshape(-1, 2) - K[:2, 2]) / [K[0, 0], K[1, 1]], D)
        ok = np.all(np.isfinite(xy), axis=1)
        if ok.sum() < 4:
            raise CalibrationError(f"camera '{camera}': its corners lie outside what these fisheye intrinsics can see")
        _, rv, tv = cv2.solvePnP(o.reshape(-1, 3)[ok], xy[ok].reshape(-1, 1, 2), np.eye(3), None)
        rvecs.append(rv)
        tvecs.append(tv)
    return rvecs, tvecs


def _equidistant_start(camera: str, size: tuple[int, int], obj: list[np.ndarray], img: list[np.ndarray]):
    """A fisheye start without OpenCV's: the equidistant lens (every k 0, principal point at the image
    centre) whose focal length makes the views' corners fit best, among 24 from 60 to 240 degrees
    across the image's diagonal."""
    w, h = size
    half_diagonal = 0.5 * float(np.hypot(w, h))
    best = None
    for fov in np.linspace(60.0, 240.0, 24):
        f = half_diagonal / np.radians(fov / 2)
        K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
        try:
            rvecs, tvecs = _poses_through(camera, K, np.zeros(4), obj, img)
        except (CalibrationError, cv2.error):
            continue
        err = sum(float(np.sum((lens.project_points(np.tile([f, f, K[0, 2], K[1, 2], 0, 0, 0, 0, 0], (o.shape[1], 1)),
                                                    o.reshape(-1, 3) @ cv2.Rodrigues(rv)[0].T + tv.reshape(3), np.ones(o.shape[1], bool))
                                 - i.reshape(-1, 2)) ** 2)) for o, i, rv, tv in zip(obj, img, rvecs, tvecs))
        if np.isfinite(err) and (best is None or err < best[0]):
            best = (err, K, rvecs, tvecs)
    if best is None:
        raise CalibrationError(f"camera '{camera}': no fisheye lens fits these views (is the board size right?)")
    return best[1], np.zeros(4), best[2], best[3]


def _fisheye_fit(camera, size, views, names, object_points, opts, fix_k3, known, guess=None) -> _Fit:
    """A fisheye lens: `cv2.fisheye.calibrate` (or the given intrinsics and a pose per view from its
    undistorted corners) to start, then the bundle adjustment on this one camera, which holds what
    the options hold (k3 k4, the principal point, fy = fx) as it does in the joint rig fit."""
    planar = [_planar(object_points[views[v].ids]) for v in names]
    obj = [p[0].reshape(1, -1, 3).astype(np.float64) for p in planar]  # (1, N, 3): cv2.fisheye takes no other shape
    img = [views[v].points.reshape(1, -1, 2).astype(np.float64) for v in names]
    w, h = size
    if known is not None or guess is not None:
        K, D = (known.K, known.dist) if known is not None else guess
        K, D = K.copy(), lens.coefficients("fisheye", D)
        rvecs, tvecs = _poses_through(camera, K, D, obj, img)
    else:
        flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | (cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4 if fix_k3 else 0)
        K0, D0 = np.zeros((3, 3)), np.zeros(4)
        if opts.centred:
            K0 = np.array([[1.0, 0, (w - 1) / 2], [0, 1.0, (h - 1) / 2], [0, 0, 1]])
            flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
        try:
            _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(obj, img, size, K0, D0, flags=flags,
                                                          criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12))
            D = D.reshape(-1)
        except cv2.error:
            # OpenCV's start fails outright on some views (an assertion on a near-degenerate one);
            # the equidistant lens that fits the views best is a start as good.
            K, D, rvecs, tvecs = _equidistant_start(camera, size, obj, img)
        if opts.square_pixels:
            K[0, 0] = K[1, 1] = 0.5 * (K[0, 0] + K[1, 1])
    # The adjustment: the camera is the world; each view's board pose is free.
    ids = [np.full(o.shape[1], k) for k, o in enumerate(obj)]
    problem = bundle.Problem(np.zeros(sum(o.shape[1] for o in obj), dtype=int), np.concatenate(ids), np.concatenate([o.reshape(-1, 3) for o in obj]),
                             np.concatenate([i.reshape(-1, 2) for i in img]), 1, len(obj), np.array([True]))
    fixed = np.zeros((1, bundle.N_INTR), dtype=bool)
    names9 = bundle.FISHEYE_NAMES
    if known is not None:
        fixed[:] = True
    else:
        if fix_k3:
            fixed[0, [names9.index("k3"), names9.index("k4")]] = True
        if opts.centred:
            fixed[0, [names9.index("cx"), names9.index("cy")]] = True
    intr0 = np.array([[K[0, 0], K[1, 1], K[0, 2], K[1, 2], *D, 0.0]])
    views0 = np.array([np.concatenate([np.reshape(rv, 3), np.reshape(tv, 3)]) for rv, tv in zip(rvecs, tvecs)])
    sol = bundle.solve(problem, intr0, np.zeros((1, 6)), views0, fixed_cameras=(0,), fixed_intrinsics=fixed,
                       square_pixels=np.array([opts.square_pixels and known is None]))
    fx, fy, cx, cy, *d = sol.intrinsics[0]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    sq = np.sum(sol.residuals ** 2, axis=1)
    view_rms = {v: float(np.sqrt(np.mean(sq[problem.view_idx == k]))) for k, v in enumerate(names)}
    poses = {v: _board_pose(rodrigues(sol.views[k, :3]), sol.views[k, 3:].copy(), p[1], p[2]) for k, (v, p) in enumerate(zip(names, planar))}
    return _Fit(sol.rms(), K, np.array(d[:4]), view_rms, poses, "fisheye")


def _fit(camera, size, views, names, object_points, opts, fix_k3, fix_tangential, guess=None) -> _Fit:
    known = opts.known.get(camera)
    if known is not None:
        known.check(size)
    if opts.model_of(camera) == "fisheye":
        return _fisheye_fit(camera, size, views, names, object_points, opts, fix_k3, known, guess)
    return _pinhole_fit(camera, size, views, names, object_points, opts, fix_k3, fix_tangential, known, guess)


def calibrate_intrinsics(
    camera: str,
    size: tuple[int, int],
    views: dict[str, Corners],
    object_points: np.ndarray,
    opts: Options,
    rejected: list[Rejection],
) -> CameraIntrinsics:
    """One camera's K and distortion from its board views; views that do not fit are rejected and logged."""
    keep = dict(sorted(views.items(), key=lambda kv: natural_key(kv[0])))
    if len(keep) < MIN_VIEWS_PER_CAMERA:
        raise CalibrationError(
            f"camera '{camera}': the board was found in only {len(keep)} image(s); at least {MIN_VIEWS_PER_CAMERA} are needed"
        )
    known = opts.known.get(camera)
    model = opts.model_of(camera)
    fix_k3, fix_tangential, k3_held_for_views = _holds(camera, len(keep), opts)
    rounds = max(opts.max_rounds, len(keep) // 2)  # one view rejected per round; the last round only fits
    for round_ in range(rounds + 1):
        fit = _fit(camera, size, keep, list(keep), object_points, opts, fix_k3, fix_tangential)
        limits = _view_limits(fit.view_rms, opts)
        bad = sorted((v for v, e in fit.view_rms.items() if e > limits[v]), key=lambda v: -fit.view_rms[v] / limits[v])
        if not bad or len(keep) - 1 < MIN_VIEWS_PER_CAMERA or round_ == rounds:
            break
        v = bad[0]  # the worst view only: the refit without it may clear the others
        med = float(np.median([e for w, e in fit.view_rms.items() if w != v]))
        rejected.append(
            Rejection(camera, v, "intrinsics", fit.view_rms[v],
                      f"reprojection RMS {fit.view_rms[v]:.2f} px in the single-camera fit, above the limit {limits[v]:.2f} px "
                      f"(median of the other views {med:.2f} px)")
        )
        del keep[v]
    if known is not None:
        return CameraIntrinsics(known.K.copy(), known.dist.copy(), fit.rms, fit.view_rms, fit.poses, True, (), False, given=True, model=model)
    if model == "fisheye":
        held = ("k3", "k4") if fix_k3 else ()
    else:
        held = (("k3",) if fix_k3 else ()) + (("p1", "p2") if fix_tangential else ())
    return CameraIntrinsics(fit.K, fit.dist, fit.rms, fit.view_rms, fit.poses, fix_k3, held, k3_held_for_views, model=model)


def resampled_spread(camera: str, size: tuple[int, int], views: dict[str, Corners], object_points: np.ndarray, opts: Options,
                     K: np.ndarray, dist: np.ndarray) -> float | None:
    """The focal length's relative spread over single-camera fits on subsets of these (vetted)
    views (calibration.quality.focal_spread); each fit starts from the full fit's K and distortion."""
    if opts.known.get(camera) is not None:
        return None
    fix_k3, fix_tangential, _ = _holds(camera, len(views), opts)

    def fit_fx(subset: list[str]) -> float:
        return float(_fit(camera, size, views, subset, object_points, opts, fix_k3, fix_tangential, guess=(K, dist)).K[0, 0])

    try:
        return focal_spread(sorted(views, key=natural_key), fit_fx)
    except (cv2.error, CalibrationError):
        return None


def _common(a: Corners, b: Corners) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ids, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    return ids, a.points[ia], b.points[ib]


def stereo_pair(
    left: str, right: str, corners: dict[str, dict[str, Corners]], intr: dict[str, CameraIntrinsics],
    object_points: np.ndarray, size: tuple[int, int],
) -> dict[str, Any] | None:
    """cv2.stereoCalibrate with both intrinsics held: right-from-left (R, T) and its RMS in pixels.
    A fisheye lens in the pair: on both cameras' undistorted normalised coordinates (OpenCV's stereo
    calibration takes one lens model for both), the RMS then from reprojecting with each lens."""
    views = [v for v in intr[left].poses if v in intr[right].poses]
    obj, pl, pr, used = [], [], [], []
    for v in views:
        ids, a, b = _common(corners[left][v], corners[right][v])
        if len(ids) < 6:
            continue
        obj.append(object_points[ids].astype(np.float32))
        pl.append(a.astype(np.float32).reshape(-1, 1, 2))
        pr.append(b.astype(np.float32).reshape(-1, 1, 2))
        used.append(v)
    if not obj:
        return None
    L, Rr = intr[left], intr[right]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if L.model == "pinhole" and Rr.model == "pinhole":
        out = cv2.stereoCalibrate(obj, pl, pr, L.K, L.dist, Rr.K, Rr.dist, size, flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
        rms, R, T = out[0], out[5], out[6]
        return {"rms_px": float(rms), "R": np.asarray(R), "T": np.asarray(T).reshape(3), "views": len(obj)}
    cams = [CameraModel(n, size[0], size[1], c.K, c.dist, model=c.model) for n, c in ((left, L), (right, Rr))]
    norm = [[cam.undistort_normalized(p.reshape(-1, 2)) for p in pts] for cam, pts in zip(cams, (pl, pr))]
    keep = [k for k in range(len(obj)) if np.all(np.isfinite(norm[0][k])) and np.all(np.isfinite(norm[1][k]))]
    if not keep:
        return None
    out = cv2.stereoCalibrate([obj[k] for k in keep], *([n[k].reshape(-1, 1, 2).astype(np.float32) for k in keep] for n in norm),
                              np.eye(3), np.zeros(5), np.eye(3), np.zeros(5), size, flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    R, T = np.asarray(out[5]), np.asarray(out[6]).reshape(3)
    d = []
    for k in keep:  # each view's board pose as the left camera's fit found it, carried to the right camera
        Rb, tb = L.poses[used[k]]
        Xl = object_points[_common(corners[left][used[k]], corners[right][used[k]])[0]] @ Rb.T + tb
        d.append(cams[0].project(Xl)[0] - pl[k].reshape(-1, 2))
        d.append(cams[1].project(Xl @ R.T + T)[0] - pr[k].reshape(-1, 2))
    d = np.concatenate(d)
    return {"rms_px": float(np.sqrt(np.mean(np.sum(d * d, axis=1)))), "R": R, "T": T, "views": len(keep)}


def _initial_camera_poses(order: list[str], intr: dict[str, CameraIntrinsics], stereo: dict | None, right: str | None):
    """World(=left camera)-to-camera poses from the relative poses implied by shared board views.

    A spanning tree grows from the left camera, always adding the camera that shares the most views with
    one already placed; each edge is the robust mean of the per-view relative poses.
    """
    placed: dict[str, tuple[np.ndarray, np.ndarray]] = {order[0]: (np.eye(3), np.zeros(3))}
    if stereo is not None and right is not None:
        placed[right] = (stereo["R"], stereo["T"])
    while len(placed) < len(order):
        best = None
        for a in placed:
            for b in order:
                if b in placed:
                    continue
                shared = [v for v in intr[a].poses if v in intr[b].poses]
                if shared and (best is None or len(shared) > len(best[2])):
                    best = (a, b, shared)
        if best is None:
            missing = [n for n in order if n not in placed]
            raise CalibrationError(
                f"camera(s) {', '.join(repr(m) for m in missing)} never see the board at the same time as the others; "
                "capture views where the board is visible to them and a calibrated neighbour together"
            )
        a, b, shared = best
        Rs, ts = [], []
        for v in shared:
            Ra, ta = intr[a].poses[v]
            Rb, tb = intr[b].poses[v]
            R_ab, t_ab = compose(Rb, tb, *invert_pose(Ra, ta))  # camera a -> camera b
            Rs.append(R_ab)
            ts.append(t_ab)
        R_ab, t_ab, _ = robust_mean_pose(np.array(Rs), np.array(ts))
        placed[b] = compose(R_ab, t_ab, *placed[a])
    return placed


def lens_information(fit: CameraIntrinsics, views: dict[str, Corners], object_points: np.ndarray,
                     opts: Options) -> tuple[np.ndarray, np.ndarray] | None:
    """The lens a camera's own views give and what they say about it: (9,) its nine slots, as the
    bundle adjustment on this camera alone finishes the single-camera fit, and (9, 9) their
    information there (bundle.Solution.intrinsics_information, every board pose marginalised) in
    1 / unit^2 of each slot, zero for held terms. None where the fit leaves the noise unknown."""
    names = list(fit.poses)
    planar = [_planar(object_points[views[v].ids]) for v in names]
    obj = [p[0] for p in planar]
    problem = bundle.Problem(np.zeros(sum(len(o) for o in obj), dtype=int), np.concatenate([np.full(len(o), k) for k, o in enumerate(obj)]),
                             np.concatenate(obj), np.concatenate([views[v].points for v in names]), 1, len(obj),
                             np.array([fit.model == "fisheye"]))
    views0 = []
    for v, (_, R, c) in zip(names, planar):  # each view's pose in `_planar`'s local frame, where the points are
        Rb, tb = fit.poses[v]
        views0.append(np.r_[rotation_vector(Rb if R is None else Rb @ R), tb if R is None else tb + Rb @ c])
    names9 = bundle.intrinsic_names(fit.model)
    fixed = np.zeros((1, bundle.N_INTR), dtype=bool)
    for term in fit.held:
        fixed[0, names9.index(term)] = True
    if opts.centred:
        fixed[0, [names9.index("cx"), names9.index("cy")]] = True
    intr0 = np.array([[fit.K[0, 0], fit.K[1, 1], fit.K[0, 2], fit.K[1, 2], *lens.coefficients("pinhole", fit.dist)]])
    sol = bundle.solve(problem, intr0, np.zeros((1, 6)), np.array(views0), fixed_cameras=(0,), fixed_intrinsics=fixed,
                       square_pixels=np.array([opts.square_pixels]), max_iterations=20)
    # the adjustment's own optimum, not OpenCV's stopping point: a prior centred a little off it would
    # pull exact data off the truth
    return None if sol.intrinsics_information is None else (sol.intrinsics[0], sol.intrinsics_information[0])


def lens_sigmas(info: np.ndarray, model: str) -> dict[str, float]:
    """The one-sigma uncertainty of each term `info` constrains (its marginal, from the inverse)."""
    names9 = bundle.intrinsic_names(model)
    on = np.flatnonzero(np.abs(info).sum(axis=1) > 0)
    if not len(on):
        return {}
    cov = np.linalg.pinv(info[np.ix_(on, on)])
    return {names9[i]: float(np.sqrt(max(cov[k, k], 0.0))) for k, i in enumerate(on) if names9[i]}


def _pair_instants(detections: DetectionSet, intr: dict[str, CameraIntrinsics], order: list[str], left: str,
                   object_points: np.ndarray, opts: Options, say: Callable[[str], None]):
    """The offsets given applied, then every other camera's pairing checked against `left`
    (calibration.pairing); an offset found is applied with `opts.auto_offset`, else the solve stops:
    poses solved from mispaired views are wrong. Returns (detections, fits, checks) re-paired."""
    import dataclasses

    from calibration import pairing

    corners = dict(detections.corners)
    intr = dict(intr)
    if opts.offsets:
        pairing.check_offsets(opts.offsets, corners)
        inst = pairing.instant_order(corners)
        for c, k in opts.offsets.items():
            corners[c] = pairing.shift(corners[c], k, inst)
            intr[c] = pairing.shift_fit(intr[c], k, inst)
    say("checking that every camera's images are paired with the same instants")
    checks = pairing.check_pairing(left, order, corners, intr, object_points, opts.offsets)
    lost = [ch for ch in checks if ch.lost]
    if lost:  # whatever --auto-offset says: the best offset tried is another wrong pairing
        raise CalibrationError(
            "; ".join(ch.lost_line() for ch in lost) + ": these images are not of the same instants as "
            f"{left}'s (taken at different times, or out of step by more than {pairing.SEARCH[-1]} instants); "
            "a rig cannot be solved from them. Give the offset if you know it: "
            + " ".join(f"--offset {ch.camera}=N" for ch in lost))
    found = [ch for ch in checks if ch.clear]
    if found and not opts.auto_offset:
        raise CalibrationError(
            "; ".join(ch.line() for ch in found) + ": a rig solved from views paired with the wrong instants is wrong; "
            + "apply it with " + " ".join(f"--offset {ch.camera}={ch.best:+d}" for ch in found) + " or --auto-offset"
            + _reference_hint(left, checks, found))
    if found:
        inst = pairing.instant_order(corners)
        for ch in found:
            corners[ch.camera] = pairing.shift(corners[ch.camera], ch.best, inst)
            intr[ch.camera] = pairing.shift_fit(intr[ch.camera], ch.best, inst)
            ch.applied = ch.best
            say(ch.line() + f": applied ({ch.best:+d})")
    return dataclasses.replace(detections, corners=corners), intr, checks


def _reference_hint(left: str, checks: list, found: list) -> str:
    """When every other camera is out of step by the same offset, the left camera is the likelier
    one: a shorter fix that says so (or "" when that is not the case)."""
    searched = [ch for ch in checks if not ch.given]
    offsets = {ch.best for ch in found}
    if len(found) < 2 or len(found) != len(searched) or len(offsets) != 1:
        return ""
    k = offsets.pop()
    return (f" (every other camera fits best at {k:+d}: more likely {left}'s own images are out of step; "
            f"then --offset {left}={-k:+d} alone)")


def calibrate_rig(
    detections: DetectionSet,
    board: BoardSpec,
    opts: Options | None = None,
    progress: Callable[[str], None] | None = None,
) -> CalibrationResult:
    opts = opts or Options()
    say = progress or (lambda s: None)
    order, left, right = _cameras_to_solve(detections, opts)
    _, object_points = board.object_points()
    rejected: list[Rejection] = []

    intr: dict[str, CameraIntrinsics] = {}
    for c in order:
        say(f"intrinsics of {c}")
        intr[c] = calibrate_intrinsics(c, detections.image_size[c], detections.corners[c], object_points, opts, rejected)

    # A lens does not depend on which instant its images belong to; the rig does: the pairing is
    # checked (and the solve stopped) before the slower measures of each lens below.
    detections, intr, checks = _pair_instants(detections, intr, order, left, object_points, opts, say)
    _measure_lenses(detections, intr, order, object_points, opts)

    stereo = None
    if right is not None:
        say(f"stereo pair {left}-{right}")
        stereo = stereo_pair(left, right, detections.corners, intr, object_points, detections.image_size[left])

    say("initial rig geometry")
    poses = _initial_camera_poses(order, intr, stereo, right)
    joint = _joint_start(detections, intr, order, poses, opts.lens_priors)
    terms = _joint_terms(intr, order, opts)
    sol, active, corners_rejected = _adjust_rejecting_outliers(joint, terms, intr, order, object_points, opts, rejected, say)

    cameras = []
    for ci, c in enumerate(order):
        fx, fy, cx, cy, *d = sol.intrinsics[ci]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        R = rodrigues(sol.cameras[ci, :3])
        w, h = detections.image_size[c]
        model = intr[c].model
        cameras.append(CameraModel(c, w, h, K, np.array(d[: lens.N_DIST[model]]), R, sol.cameras[ci, 3:].copy(), model))
    rig = RigCalibration(cameras, {})
    obs = Observations(order, joint.views, joint.cam_idx[active], joint.view_idx[active], joint.ids[active], joint.uv[active], sol.residuals)
    result = CalibrationResult(rig, left, right, obs, intr, rejected, stereo, sol, dict(detections.image_size), dict(detections.images_seen),
                               {c: int(n) for c, n in zip(order, corners_rejected)}, checks)
    rig.meta.update(summary_meta(result, board))
    return result


def _cameras_to_solve(detections: DetectionSet, opts: Options) -> tuple[list[str], str, str | None]:
    """The cameras in solving order (calibrate_rig's `camera_order`); a camera that never saw the
    board stops the solve, named."""
    cams_with_views = [c for c in detections.cameras if detections.corners.get(c)]
    for c in detections.cameras:
        if not detections.corners.get(c):
            raise CalibrationError(f"camera '{c}': the board was not found in any of its {detections.images_seen.get(c, 0)} images")
    return camera_order(cams_with_views, opts.left, opts.right)


def _measure_lenses(detections: DetectionSet, intr: dict[str, CameraIntrinsics], order: list[str], object_points: np.ndarray,
                    opts: Options) -> None:
    """Each fitted lens's focal spread over subsets of its kept views and what its own views measured
    of it (with `opts.lens_priors` the prior the joint adjustment holds it to; either way what the
    report measures the joint solve's lens against), set on `intr`."""
    for c in order:
        kept = {v: detections.corners[c][v] for v in intr[c].view_rms}
        intr[c].focal_spread = resampled_spread(c, detections.image_size[c], kept, object_points, opts, intr[c].K, intr[c].dist)
        if not intr[c].given:
            measured = lens_information(intr[c], kept, object_points, opts)
            if measured is not None:
                intr[c].lens_mean, intr[c].lens_information = measured
                intr[c].lens_sigma = lens_sigmas(intr[c].lens_information, intr[c].model)


@dataclass
class _JointStart:
    """The joint adjustment's observations, every corner of every (camera, view) that survived the
    single-camera fit (one row each), and where its unknowns start."""
    views: list[str]
    cam_idx: np.ndarray
    view_idx: np.ndarray
    ids: np.ndarray
    uv: np.ndarray
    view_pose: np.ndarray  # (views, 6) board-to-world
    intr0: np.ndarray  # (cameras, 9) each lens: its own adjustment's where it has one, else its fit's
    cams0: np.ndarray  # (cameras, 6) world-to-camera
    fisheye: np.ndarray


def _joint_start(detections: DetectionSet, intr: dict[str, CameraIntrinsics], order: list[str],
                 poses: dict[str, tuple[np.ndarray, np.ndarray]], lens_priors: bool = True) -> _JointStart:
    views = sorted({v for c in order for v in intr[c].poses}, key=natural_key)
    vindex = {v: i for i, v in enumerate(views)}
    obs_cam, obs_view, obs_ids, obs_uv = [], [], [], []
    for ci, c in enumerate(order):
        for v in intr[c].poses:
            cr = detections.corners[c][v]
            obs_cam.append(np.full(len(cr), ci))
            obs_view.append(np.full(len(cr), vindex[v]))
            obs_ids.append(cr.ids)
            obs_uv.append(cr.points)

    # Board pose per view in the world: from the camera that sees the most of it.
    view_pose = np.zeros((len(views), 6))
    for v, vi in vindex.items():
        best = max((c for c in order if v in intr[c].poses), key=lambda c: len(detections.corners[c][v]))
        Rcw, tcw = poses[best]
        Rcb, tcb = intr[best].poses[v]
        Rwb, twb = compose(*invert_pose(Rcw, tcw), Rcb, tcb)
        view_pose[vi, :3] = rotation_vector(Rwb)
        view_pose[vi, 3:] = twb
    # five distortion slots whatever the lens (a fisheye's four terms leave the last at 0)
    intr0 = np.array([[K[0, 0], K[1, 1], K[0, 2], K[1, 2], *lens.coefficients("pinhole", d)]
                      for K, d in ((intr[c].K, intr[c].dist) for c in order)])
    for ci, c in enumerate(order):  # a lens prior is centred on its camera's own adjustment, which starts it too
        if lens_priors and intr[c].lens_mean is not None:
            intr0[ci] = intr[c].lens_mean
    fisheye = np.array([intr[c].model == "fisheye" for c in order])
    cams0 = np.array([np.concatenate([rotation_vector(poses[c][0]), poses[c][1]]) for c in order])
    return _JointStart(views, np.concatenate(obs_cam), np.concatenate(obs_view), np.concatenate(obs_ids), np.concatenate(obs_uv),
                       view_pose, intr0, cams0, fisheye)


@dataclass
class _JointTerms:
    """What the joint adjustment holds and what it pulls each lens towards."""
    fixed: np.ndarray  # (cameras, 9) terms held
    square: np.ndarray  # (cameras,) fy = fx
    prior_px: np.ndarray  # (cameras, 9) each given term's prior sigma, for a corner noise of 1 px; inf: none
    lens_info: np.ndarray  # (cameras, 9, 9) each lens's own fit as its prior, per unit of chi-square
    priors: dict[str, dict[str, float]]  # camera -> term -> sigma, of the given intrinsics used as priors


def _joint_terms(intr: dict[str, CameraIntrinsics], order: list[str], opts: Options) -> _JointTerms:
    """Terms held (each lens's held terms; given intrinsics whole, or but for the terms `opts.prior`
    lets move; the principal point with `opts.centred`) and the priors; records each given camera's
    prior on its `intr`."""
    fixed_intr = np.zeros((len(order), bundle.N_INTR), dtype=bool)
    for ci, c in enumerate(order):
        names9 = bundle.intrinsic_names(intr[c].model)
        for term in intr[c].held:
            fixed_intr[ci, names9.index(term)] = True
        if intr[c].given:
            fixed_intr[ci, :] = True
        elif opts.centred:
            fixed_intr[ci, names9.index("cx")] = fixed_intr[ci, names9.index("cy")] = True
    square = np.array([opts.square_pixels and not intr[c].given for c in order])
    prior_px = np.full((len(order), bundle.N_INTR), np.inf)
    # each lens's own fit as its prior (information per unit of chi-square, scaled to the corners' noise in the adjustment)
    lens_info = np.zeros((len(order), bundle.N_INTR, bundle.N_INTR))
    for ci, c in enumerate(order):
        if opts.lens_priors and intr[c].lens_information is not None:
            lens_info[ci] = intr[c].lens_information
    priors: dict[str, dict[str, float]] = {}
    for ci, c in enumerate(order):
        if intr[c].given and opts.prior:
            priors[c] = prior_sigmas(opts.known[c], opts.prior)
            names9 = bundle.intrinsic_names(intr[c].model)
            intr[c].prior = priors[c]
            for term, sigma in priors[c].items():
                fixed_intr[ci, names9.index(term)] = False
                prior_px[ci, names9.index(term)] = sigma
    return _JointTerms(fixed_intr, square, prior_px, lens_info, priors)


def _adjust_rejecting_outliers(joint: _JointStart, terms: _JointTerms, intr: dict[str, CameraIntrinsics], order: list[str],
                               object_points: np.ndarray, opts: Options, rejected: list[Rejection], say: Callable[[str], None]):
    """The joint bundle adjustment, run again after each round's rejections (up to `opts.max_rounds`)
    and with each corner weighted by its view's measured noise (`opts.reweight`): (the last solution,
    which observations it kept, single corners rejected per camera). Rejected views go on `rejected`."""
    cam_idx, view_idx, ids, uv, views = joint.cam_idx, joint.view_idx, joint.ids, joint.uv, joint.views
    intr0, cams0, view_pose = joint.intr0, joint.cams0, joint.view_pose
    # The priors weigh against the corners in their noise's units: their measured noise, first from
    # the single-camera fits, then from the joint fit's views.
    noise_px = float(np.median([e for c in order for e in intr[c].view_rms.values()])) / np.sqrt(2.0)
    prior_mean = intr0.copy()  # the given values and own fits: the priors' centres whatever the rounds move
    active = np.ones(len(uv), dtype=bool)
    corners_rejected = np.zeros(len(order), dtype=int)
    sigma = None  # per-corner noise estimate (its camera view's RMS), once a first fit gives one
    sol = None
    for round_ in range(opts.max_rounds):
        say(f"bundle adjustment, round {round_ + 1}")
        problem = bundle.Problem(cam_idx[active], view_idx[active], object_points[ids[active]], uv[active], len(order), len(views), joint.fisheye)
        w = None if sigma is None else 1.0 / sigma[active] ** 2
        sol = bundle.solve(problem, intr0, cams0, view_pose, fixed_cameras=(0,), fixed_intrinsics=terms.fixed, weights=w,
                           square_pixels=terms.square, prior_std=terms.prior_px / max(noise_px, 1e-3) if terms.priors else None,
                           prior_mean=prior_mean, prior_information=terms.lens_info * noise_px ** 2 if terms.lens_info.any() else None)
        intr0, cams0, view_pose = sol.intrinsics, sol.cameras, sol.views
        if round_ == opts.max_rounds - 1:
            break
        # Single corners far off (a refinement caught by a nearby edge) go; so does a whole camera view
        # whose corners fit badly or are largely off (a mis-detected board, a moved board).
        norm = np.linalg.norm(sol.residuals, axis=1)
        corner_limit = max(0.5 * opts.outlier_px, 5.0 * float(np.median(norm)))
        off = norm > corner_limit
        key = problem.cam_idx * len(views) + problem.view_idx
        uniq, inv = np.unique(key, return_inverse=True)
        n_obs = np.bincount(inv)
        good = ~off
        rms = np.sqrt(np.bincount(inv, weights=np.where(good, norm ** 2, 0.0)) / np.maximum(np.bincount(inv, weights=good.astype(float)), 1))
        rms_all = np.sqrt(np.bincount(inv, weights=norm ** 2) / n_obs)  # what a rejection reports: every corner of the view
        off_frac = np.bincount(inv, weights=off.astype(float)) / n_obs
        limit = _threshold(list(rms), opts)
        bad_obs = (rms > limit) | (off_frac > 0.25)
        if not bad_obs.any() and not off.any() and (sigma is not None or not opts.reweight):
            break
        if opts.reweight:
            # Corners are weighted by their view's noise: a board seen at a grazing angle is measured
            # less precisely than one seen face-on and should count for less. The floor keeps a
            # lucky, nearly noise-free view from dominating.
            view_sigma = np.maximum(rms, 0.5 * float(np.median(rms))) / np.sqrt(2.0)
            all_key = cam_idx * len(views) + view_idx
            lookup = dict(zip(uniq.tolist(), view_sigma.tolist()))
            med_sigma = float(np.median(view_sigma))
            sigma = np.array([lookup.get(k, med_sigma) for k in all_key.tolist()]) / med_sigma
            noise_px = med_sigma
        rejected.extend(_joint_rejections(order, views, uniq, rms, rms_all, off_frac, bad_obs, corner_limit, limit))
        active_idx = np.flatnonzero(active)
        drop = bad_obs[inv] | off
        single = off & ~bad_obs[inv]
        np.add.at(corners_rejected, problem.cam_idx[single], 1)
        active[active_idx[drop]] = False
        for ci, c in enumerate(order):
            if not np.any(active & (cam_idx == ci)):
                if intr[c].given and not intr[c].prior:  # the lens held is the likelier fault than every image
                    raise CalibrationError(
                        f"camera '{c}': every view was rejected as an outlier; its intrinsics were given and held "
                        f"(--intrinsics{': ' + opts.known[c].source if c in opts.known and opts.known[c].source else ''}) "
                        f"and its views fit them at {intr[c].rms:.2f} px: check that they are this camera's lens")
                if c in opts.offsets:  # paired as the user said: that pairing is the first thing to doubt
                    raise CalibrationError(
                        f"camera '{c}': every view was rejected as an outlier with its images paired as --offset {c}={opts.offsets[c]:+d} "
                        "gives: check that offset (without it the pairing check tries -2..+2 for this camera)")
                raise CalibrationError(f"camera '{c}': every view was rejected as an outlier; check the images of this camera")
    assert sol is not None
    return sol, active, corners_rejected


def _joint_rejections(order: list[str], views: list[str], keys: np.ndarray, rms: np.ndarray, rms_all: np.ndarray, off_frac: np.ndarray,
                      bad: np.ndarray, corner_limit: float, limit: float) -> list[Rejection]:
    """Each camera view a joint round rejects (`bad`, by key camera * len(views) + view), with its reason."""
    med = float(np.median(rms))
    out = []
    for k, e, e_all, f, b in zip(keys, rms, rms_all, off_frac, bad):
        if not b:
            continue
        c, v = order[k // len(views)], views[k % len(views)]
        # one reason per view: most corners off (the board mis-detected or moved) before a poor fit
        if f > 0.25:
            why = (f"{f * 100:.0f}% of its corners are more than {corner_limit:.2f} px off in the joint rig fit "
                   f"(RMS of all its corners {e_all:.2f} px)")
        else:
            why = f"reprojection RMS {e:.2f} px in the joint rig fit, above the limit {limit:.2f} px (median {med:.2f} px)"
        out.append(Rejection(c, v, "joint", float(e_all if f > 0.25 else e), why))
    return out
