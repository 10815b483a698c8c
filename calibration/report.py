"""Calibration quality report: reprojection error per camera and per view, board coverage of each image,
the stereo pair's epipolar error after rectification, the intrinsics' uncertainty, and warnings when
the result should not be trusted.

`build_report` measures a fresh calibration (it needs the corners); `summary_meta` stores it, with the
headline figures, in the calibration file's metadata, and `format_report` prints it again from the file
alone. An uncertainty the adjustment could not compute is null in the report and 'unknown' in print,
never 0.
"""
from __future__ import annotations

import datetime as _dt
from typing import Any

import cv2
import numpy as np

from calibration.boards import BoardSpec
from calibration.bundle import intrinsic_names
from calibration.camera import CalibrationError, CameraModel, RigCalibration
from calibration.quality import MIN_JOINT_VIEWS, SPREAD_WARN, spread_reason, verdict
from calibration.result import CalibrationResult

COVERAGE_GRID = (8, 6)  # cells across, down
MIN_GOOD_VIEWS = 10
MIN_COVERAGE = 0.6
MAX_GOOD_RMS_PX = 1.0
MAX_GOOD_EPIPOLAR_PX = 0.5
MIN_STEREO_VIEWS = 5
MAX_FOCAL_STD_PCT = 1.0  # a focal length whose one-sigma uncertainty is above this share of it is not trusted
# A lens term the joint solve moved more than this many of its single-camera fit's sigmas from that fit
# left its prior: by chance alone a term moves that far about once in 370.
LENS_PRIOR_SIGMAS = 3.0
_REGIONS = (("top-left", "top", "top-right"), ("left", "centre", "right"), ("bottom-left", "bottom", "bottom-right"))


def coverage(size: tuple[int, int], views: list[np.ndarray], grid: tuple[int, int] = COVERAGE_GRID) -> dict[str, Any]:
    """Which parts of the image the board covered in at least one view (each view's corner hull).

    A grid cell counts as seen when half of it was inside some view's board outline. `never_seen` names
    the ninths of the image (top-left ... bottom-right) that less than a quarter of was ever covered.
    """
    w, h = size
    scale = 8
    mw, mh = max(1, w // scale), max(1, h // scale)
    mask = np.zeros((mh, mw), np.uint8)
    for pts in views:
        if len(pts) < 3:
            continue
        hull = cv2.convexHull((np.asarray(pts, dtype=np.float64) / scale).astype(np.float32))
        cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
    gx, gy = grid
    cells = []
    seen = 0
    for j in range(gy):
        row = ""
        for i in range(gx):
            block = mask[j * mh // gy : (j + 1) * mh // gy, i * mw // gx : (i + 1) * mw // gx]
            hit = block.size > 0 and block.mean() >= 0.5
            seen += hit
            row += "#" if hit else "."
        cells.append(row)
    never = []
    for j in range(3):
        for i in range(3):
            block = mask[j * mh // 3 : (j + 1) * mh // 3, i * mw // 3 : (i + 1) * mw // 3]
            if block.size == 0 or block.mean() < 0.25:
                never.append(_REGIONS[j][i])
    return {"fraction": round(seen / (gx * gy), 3), "grid": cells, "never_seen": never}


def rectification(left: CameraModel, right: CameraModel, alpha: float | None = None) -> dict[str, np.ndarray]:
    """cv2.stereoRectify for the pair: R1 R2 P1 P2 Q, plus R T (right-from-left).

    A near-parallel pair (optical axes within 15 degrees) gets OpenCV's usual rectification: equal
    principal points (zero disparity at infinity) and alpha = 0 (only valid pixels). A strongly verged
    pair cannot share a principal point without pushing the scene out of both images, and OpenCV's
    alpha scaling degenerates for it; it keeps separate principal points and the cameras' focal length
    (alpha = -1).
    """
    R = right.R @ left.R.T
    T = right.t - R @ left.t
    verge = np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0)))
    parallel = verge < 15.0
    flags = cv2.CALIB_ZERO_DISPARITY if parallel else 0
    if alpha is None:
        alpha = 0.0 if parallel else -1.0
    # OpenCV's rectification reads the distortion only to find the valid pixels for alpha; it knows
    # one lens model for both cameras. A fisheye camera enters it without distortion: the rotations
    # are exact, and the crop is that of the undistorted image's central part.
    dl = left.dist if left.model == "pinhole" else np.zeros(5)
    dr = right.dist if right.model == "pinhole" else np.zeros(5)
    R1, R2, P1, P2, Q, roi1, roi2 = cv2.stereoRectify(
        left.K, dl, right.K, dr, (left.width, left.height), R, T.reshape(3, 1), flags=flags, alpha=alpha
    )
    return {"R": R, "T": T, "R1": R1, "R2": R2, "P1": P1, "P2": P2, "Q": Q, "roi1": np.array(roi1), "roi2": np.array(roi2),
            "verge_deg": verge}


def epipolar_error(left: CameraModel, right: CameraModel, pairs: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, Any] | None:
    """Residual of matched corners across the epipolar lines after rectification (0 for a perfect
    calibration): the row difference for a side-by-side pair, the column difference for a pair one
    above the other (OpenCV rectifies a pair whose baseline is mostly vertical along columns; its
    row difference is then the disparity, not an error).

    Measured in pixels of the left camera's focal length: the rectified images' own focal length
    depends on how far they are zoomed (strongly verged pairs zoom a lot) and would inflate the figure.
    """
    if not pairs:
        return None
    rect = rectification(left, right)
    vertical = abs(rect["P2"][1, 3]) > abs(rect["P2"][0, 3])  # the baseline along the rectified y axis
    axis = 0 if vertical else 1
    f = left.fx if vertical else left.fy
    d = []
    for pl, pr in pairs:
        d.append(f * (_rectified(left, rect["R1"], pl)[:, axis] - _rectified(right, rect["R2"], pr)[:, axis]))
    d = np.concatenate(d)
    return {"rms_px": float(np.sqrt(np.mean(d * d))), "max_px": float(np.abs(d).max()), "points": int(d.size), "views": len(pairs),
            "measured_along": "x (a vertical pair)" if vertical else "y"}


def _rectified(cam: CameraModel, R_rect: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Normalised (x, y) of pixels after undistortion and the rectifying rotation."""
    xy = cam.undistort_normalized(uv, iterations=50)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ R_rect.T
    return rays[:, :2] / rays[:, 2:3]


def _r(x: float | None, n: int = 4):
    return None if x is None or not np.isfinite(x) else round(float(x), n)


def _significant(x: float, digits: int = 3):
    """Rounded to significant digits, not decimals: a small but known uncertainty must not print as 0."""
    return None if x is None or not np.isfinite(x) else float(f"{float(x):.{digits}g}")


def _prior(fit, cam: CameraModel) -> dict[str, Any] | None:
    """Given intrinsics used as priors: per term its sigma, its given value and how far the solve moved it."""
    if not fit.prior:
        return None
    names = intrinsic_names(cam.model)
    given = np.r_[fit.K[0, 0], fit.K[1, 1], fit.K[0, 2], fit.K[1, 2], np.asarray(fit.dist).reshape(-1)]
    now = np.r_[cam.fx, cam.fy, cam.cx, cam.cy, cam.dist]
    out = {}
    for term, sigma in fit.prior.items():
        i = names.index(term)
        moved = float(now[i] - given[i])
        out[term] = {"sigma": _significant(sigma), "given": _significant(given[i], 8), "moved": _significant(moved),
                     "moved_sigma": round(moved / sigma, 3)}
    return out


def _lens_prior(fit, cam: CameraModel) -> dict[str, Any] | None:
    """The camera's own lens fit as the joint solve's prior: per fitted term the fit's value, its
    sigma there and how far the joint solve moved it; `kept` when no term moved beyond
    LENS_PRIOR_SIGMAS of them."""
    if not fit.lens_sigma:
        return None
    names = intrinsic_names(cam.model)
    single = np.asarray(fit.lens_mean, dtype=np.float64)
    now = np.r_[cam.fx, cam.fy, cam.cx, cam.cy, cam.dist]
    terms = {}
    for term, sigma in fit.lens_sigma.items():
        i = names.index(term)
        moved = float(now[i] - single[i])
        terms[term] = {"single": _significant(single[i], 8), "sigma": _significant(sigma), "moved": _significant(moved),
                       "moved_sigma": round(moved / sigma, 3) if sigma > 0 else None}
    beyond = [t for t, p in terms.items() if p["moved_sigma"] is not None and abs(p["moved_sigma"]) > LENS_PRIOR_SIGMAS]
    return {"kept": not beyond, "beyond": beyond, "terms": terms}


def _lens_moved_reason(lp: dict[str, Any], shared_views: int) -> str:
    moves = ", ".join(f"{t} {lp['terms'][t]['moved']:+.4g} ({lp['terms'][t]['moved_sigma']:+.1f} sigma of its own fit)" for t in lp["beyond"])
    few = f"too few views shared with the other cameras ({shared_views}), " if shared_views < MIN_GOOD_VIEWS else ""
    return (f"the joint solve moved its lens beyond what its own views allow: {moves}; likely causes: {few}"
            "its images out of step with the others' (timing), a board that is not flat, or a lens its views measured poorly")


def build_report(result: CalibrationResult) -> dict[str, Any]:
    obs = result.observations
    names = obs.cameras
    sq = np.sum(obs.residuals ** 2, axis=1)
    V = len(obs.views)
    per_view = _per_view_rms(obs, sq)
    per_camera: dict[str, Any] = {}
    warnings: list[str] = []
    for ci, name in enumerate(names):
        per_camera[name] = _camera_entry(result, ci, sq)
        reasons = _camera_warnings(result, ci, per_camera[name])
        joint_rejected = sum(1 for r in result.rejected if r.camera == name and r.stage == "joint")
        too_few = joint_rejected > 0 and per_camera[name]["views_used"] < MIN_JOINT_VIEWS
        if too_few:
            reasons.insert(0, f"the joint rig fit kept only {per_camera[name]['views_used']} of its views ({joint_rejected} rejected as "
                              f"outliers; {MIN_JOINT_VIEWS} are needed): its views do not fit the others' (images paired with the "
                              "wrong instants, or a lens that is not its own)")
        warnings += [f"camera '{name}': {r}" for r in reasons]
        per_camera[name]["verdict"] = verdict(per_camera[name]["rms_px"], reasons, too_few)
        per_camera[name]["reasons"] = reasons

    shared_views = [v for v, cams in per_view.items() if len(cams) >= 2]
    report: dict[str, Any] = {
        "cameras": per_camera,
        "rms_px": {n: c["rms_px"] for n, c in per_camera.items()},
        "views_used": {n: c["views_used"] for n, c in per_camera.items()},
        "views_total": V,
        "views_multi_camera": len(shared_views),
        "per_view": {v: per_view[v] for v in obs.views if v in per_view},
        "rejected": [r.to_dict() for r in result.rejected],
        # each camera's images tried at other instants against the reference camera (calibration.pairing)
        "pairing": [{**ch.to_dict(), "line": ch.line() if ch.residuals and ch.best != 0 else None} for ch in result.pairing],
        "converged": bool(result.solution.converged),
        "iterations": int(result.solution.iterations),
        "stereo_rms_px": None,
        "baseline_m": None,
        "stereo": None,
    }
    if not result.solution.converged:
        warnings.append("the joint adjustment did not converge within its iteration limit")
    if result.right is not None:
        report["stereo"] = _stereo_entry(result, sq, warnings)
        report["stereo_rms_px"] = report["stereo"]["rms_px"]
        report["baseline_m"] = report["stereo"]["baseline_m"]
    report["warnings"] = warnings
    return report


def _per_view_rms(obs, sq: np.ndarray) -> dict[str, dict[str, float]]:
    """view -> camera -> reprojection RMS of that camera's corners in that view."""
    V = len(obs.views)
    per_view: dict[str, dict[str, float]] = {}
    key = obs.cam_idx * V + obs.view_idx
    uniq, inv = np.unique(key, return_inverse=True)
    obs_rms = np.sqrt(np.bincount(inv, weights=sq) / np.bincount(inv))
    for k, e in zip(uniq, obs_rms):
        per_view.setdefault(obs.views[k % V], {})[obs.cameras[k // V]] = _r(e)
    return per_view


def _camera_entry(result: CalibrationResult, ci: int, sq: np.ndarray) -> dict[str, Any]:
    """One camera's figures: its lens and uncertainty, RMS, views, coverage and priors."""
    obs = result.observations
    name = obs.cameras[ci]
    cam = result.rig[name]
    m = obs.cam_idx == ci
    used_views = sorted(set(obs.view_idx[m].tolist()))
    hulls = [obs.uv[m & (obs.view_idx == v)] for v in used_views]
    std = result.solution.intrinsics_std[ci]
    intr = result.intrinsics[name]
    return {
        "width": cam.width,
        "height": cam.height,
        "fx": _r(cam.fx, 3),
        "fy": _r(cam.fy, 3),
        "cx": _r(cam.cx, 3),
        "cy": _r(cam.cy, 3),
        "model": cam.model,
        "dist": [round(float(x), 6) for x in cam.dist],
        "std": {k: _significant(std[i]) for i, k in enumerate(("fx", "fy", "cx", "cy"))},
        "center_m": [round(float(x), 5) for x in cam.center],
        "rms_px": _r(np.sqrt(np.mean(sq[m]))),
        "rms_single_camera_px": _r(intr.rms),
        "views_used": len(used_views),
        "views_found": len(intr.view_rms) + sum(1 for r in result.rejected if r.camera == name and r.stage == "intrinsics"),
        "images": result.images_seen.get(name),
        "rejected": sum(1 for r in result.rejected if r.camera == name),
        "corners_rejected": result.corners_rejected.get(name, 0),
        "coverage": coverage(result.image_size[name], hulls),
        "held": list(intr.held),  # distortion terms held at 0
        "intrinsics_given": intr.given,  # held at values given beforehand (--intrinsics)
        "prior": _prior(intr, cam),
        "lens_prior": _lens_prior(intr, cam),
        "focal_spread_pct": None if intr.focal_spread is None else round(100 * intr.focal_spread, 3),
    }


def _camera_warnings(result: CalibrationResult, ci: int, entry: dict[str, Any]) -> list[str]:
    """What makes camera `ci`'s calibration doubtful, one reason each (the report's warnings name the camera)."""
    obs = result.observations
    name = obs.cameras[ci]
    intr = result.intrinsics[name]
    views_used, rms, cov = entry["views_used"], entry["rms_px"], entry["coverage"]
    reasons: list[str] = []
    # Intrinsics given and held were not fitted here: what would make a fit of them doubtful (few
    # views, a small part of the image, no covariance for them) says nothing of them. Their RMS does.
    held_given = intr.given and not intr.prior
    if views_used < MIN_GOOD_VIEWS and not held_given:
        reasons.append(f"only {views_used} views used; {MIN_GOOD_VIEWS} or more are needed to trust its intrinsics")
    if cov["fraction"] < MIN_COVERAGE and not held_given:
        where = f" (never seen: {', '.join(cov['never_seen'])})" if cov["never_seen"] else ""
        reasons.append(
            f"the board covered only {cov['fraction'] * 100:.0f}% of the image{where}; "
            "distortion there is extrapolated, show the board in those regions"
        )
    if rms is not None and rms > MAX_GOOD_RMS_PX:
        reasons.append(f"reprojection RMS {rms:.2f} px is high (above {MAX_GOOD_RMS_PX} px)")
    if intr.k3_held_for_views and not held_given:
        reasons.append("too few views to estimate k3; it was held at 0")
    std_of = entry["std"]
    unknown = [k for k, v in std_of.items() if v is None]
    if unknown and not held_given:
        why = result.solution.std_unknown_reason or "the adjustment's covariance is not defined for them"
        reasons.append(f"the uncertainty of {', '.join(unknown)} is unknown ({why})")
    loose = [k for k in ("fx", "fy") if std_of[k] is not None and std_of[k] > MAX_FOCAL_STD_PCT / 100 * entry[k]]
    if loose:
        reasons.append(
            "its focal length is poorly determined ("
            + ", ".join(f"{k} {entry[k]:.1f} +- {std_of[k]:.3g} px" for k in loose)
            + "); show the board at more varied tilts and distances"
        )
    lp = entry["lens_prior"]
    if lp is not None and not lp["kept"]:
        m = obs.cam_idx == ci
        used_views = sorted(set(obs.view_idx[m].tolist()))
        shared = int(sum(1 for v in used_views if np.any((obs.view_idx == v) & (obs.cam_idx != ci))))
        reasons.append(_lens_moved_reason(lp, shared))
    spread = intr.focal_spread
    if spread is not None and spread > SPREAD_WARN:
        reasons.append(spread_reason(spread, views_used))
    return reasons


def _stereo_entry(result: CalibrationResult, sq: np.ndarray, warnings: list[str]) -> dict[str, Any]:
    """The stereo pair's figures (RMS over their shared views, baseline, epipolar error after
    rectification); what makes them doubtful is appended to `warnings`."""
    obs = result.observations
    names = obs.cameras
    li, ri = names.index(result.left), names.index(result.right)
    left, right = result.rig[result.left], result.rig[result.right]
    common = sorted(set(obs.view_idx[obs.cam_idx == li].tolist()) & set(obs.view_idx[obs.cam_idx == ri].tolist()))
    mask = np.isin(obs.view_idx, common) & ((obs.cam_idx == li) | (obs.cam_idx == ri))
    stereo_rms = float(np.sqrt(np.mean(sq[mask]))) if mask.any() else None
    pairs = []
    for v in common:
        ml = (obs.cam_idx == li) & (obs.view_idx == v)
        mr = (obs.cam_idx == ri) & (obs.view_idx == v)
        _, a, b = np.intersect1d(obs.ids[ml], obs.ids[mr], return_indices=True)
        if len(a):
            pairs.append((obs.uv[ml][a], obs.uv[mr][b]))
    epi = epipolar_error(left, right, pairs)
    baseline = float(np.linalg.norm(right.center - left.center))
    if len(common) < MIN_STEREO_VIEWS:
        warnings.append(
            f"stereo pair: '{result.left}' and '{result.right}' saw the board together in only {len(common)} views; "
            f"their relative pose rests on the other cameras ({MIN_STEREO_VIEWS} or more shared views are advised)"
        )
    if epi and epi["rms_px"] > MAX_GOOD_EPIPOLAR_PX:
        warnings.append(f"stereo pair: epipolar error after rectification is {epi['rms_px']:.2f} px RMS (above {MAX_GOOD_EPIPOLAR_PX} px)")
    return {
        "left": result.left,
        "right": result.right,
        "common_views": len(common),
        "rms_px": _r(stereo_rms),
        "rms_fixed_intrinsics_px": _r(result.stereo_init["rms_px"]) if result.stereo_init else None,
        "baseline_m": _r(baseline, 6),
        "epipolar_rms_px": _r(epi["rms_px"]) if epi else None,
        "epipolar_max_px": _r(epi["max_px"]) if epi else None,
        "epipolar_along": epi["measured_along"] if epi else None,
    }


def summary_meta(result: CalibrationResult, board: BoardSpec) -> dict[str, Any]:
    """The file's metadata: board, date, per-camera RMS and views, stereo RMS, baseline, rejections, report."""
    report = build_report(result)
    return {
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "board": board.to_dict(),
        "stereo_pair": {"left": result.left, "right": result.right},
        "rms_px": report["rms_px"],
        "stereo_rms_px": report["stereo_rms_px"],
        "baseline_m": report["baseline_m"],
        "views_used": report["views_used"],
        "views": len(result.observations.views),
        "rejected": [r.to_dict() for r in result.rejected],
        "report": report,
    }


def format_report(calib: RigCalibration) -> str:
    """Human-readable report of a calibration file (measurements when the file carries them); a
    `report` section that is not as `rig calibrate run` writes it (edited by hand, another tool) is
    CalibrationError (one line), not a traceback."""
    try:
        return _format_report(calib)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        raise CalibrationError(f"the calibration's measurements (its 'report') are malformed ({type(exc).__name__}: {exc}): "
                               "the file was edited, or written by another tool; `rig calibrate run` writes them again") from None


def _format_report(calib: RigCalibration) -> str:
    rep = calib.meta.get("report")
    lines = _header_lines(calib.meta) + [""] + _camera_table(calib, rep)
    if rep is None:
        if len(calib.cameras) >= 2:
            a, b = calib.cameras[0], calib.cameras[-1]
            lines.append("")
            lines.append(f"baseline {a.name}-{b.name}: {np.linalg.norm(b.center - a.center) * 1000:.2f} mm")
        lines.append("(this file carries no measurements: reprojection errors and coverage come from `rig calibrate run`)")
        return "\n".join(lines)
    lines += [""] + _lens_lines(rep) + _stereo_lines(rep) + [""] + _coverage_lines(rep) + _fault_lines(rep)
    return "\n".join(lines)


def _header_lines(meta: dict[str, Any]) -> list[str]:
    """When, and with which board."""
    lines = []
    if meta.get("date"):
        lines.append(f"calibrated {meta['date']}")
    if meta.get("board"):
        b = meta["board"]
        desc = ", ".join(f"{k}={v}" for k, v in b.items() if k != "type")
        lines.append(f"board: {b.get('type')} ({desc})")
    return lines


def _camera_table(calib: RigCalibration, rep: dict[str, Any] | None) -> list[str]:
    """A row per camera: size, intrinsics, RMS, views, coverage, centre."""
    lines = [f"{'camera':<10} {'size':>10} {'fx':>9} {'fy':>9} {'cx':>8} {'cy':>8} {'rms px':>7} {'views':>5} {'cover':>6}  centre (m)"]
    for cam in calib.cameras:
        c = (rep or {}).get("cameras", {}).get(cam.name, {})
        rms = c.get("rms_px")
        cov = c.get("coverage", {}).get("fraction")
        lines.append(
            f"{cam.name:<10} {f'{cam.width}x{cam.height}':>10} {cam.fx:9.2f} {cam.fy:9.2f} {cam.cx:8.2f} {cam.cy:8.2f} "
            f"{'-' if rms is None else f'{rms:.3f}':>7} {c.get('views_used', '-'):>5} {'-' if cov is None else f'{cov * 100:.0f}%':>6}  "
            + " ".join(f"{x:+.4f}" for x in cam.center)
        )
    return lines


def _lens_lines(rep: dict[str, Any]) -> list[str]:
    """The intrinsics' uncertainty, the verdicts, what was given or held, each lens against its own
    fit and the pairing applied."""
    lines = ["one-sigma uncertainty of the intrinsics (px; 'unknown' where the adjustment could not compute it):"]
    for name, c in rep["cameras"].items():
        std = c.get("std") or {}
        spread = c.get("focal_spread_pct")
        held = c.get("intrinsics_given") and not c.get("prior")
        lines.append(f"  {name:<10} " + "  ".join(f"{k} {'given' if held else _std(std.get(k))}" for k in ("fx", "fy", "cx", "cy"))
                     + ("" if spread is None else f"   fx spread over subsets of the views {spread:.2f} %"))
    verdicts = {name: c.get("verdict") for name, c in rep["cameras"].items() if c.get("verdict")}
    if verdicts:
        lines.append("verdict: " + ", ".join(f"{n} {v}" for n, v in verdicts.items())
                     + (" (why: the warnings below)" if any(v != "good" for v in verdicts.values()) else ""))
    given = [name for name, c in rep["cameras"].items() if c.get("intrinsics_given") and not c.get("prior")]
    if given:
        lines.append(f"intrinsics given and held (not fitted): {', '.join(given)}")
    for name, c in rep["cameras"].items():
        if c.get("prior"):
            moves = ", ".join(f"{t} {p['moved']:+.4g} ({p['moved_sigma']:+.2f} sigma)" for t, p in c["prior"].items())
            lines.append(f"intrinsics given as priors, {name}: {moves}")
    kept = {name: c["lens_prior"] for name, c in rep["cameras"].items() if c.get("lens_prior")}
    if kept:
        lines.append(f"lens within its own fit ({LENS_PRIOR_SIGMAS:g} sigma of what its views measured): " + ", ".join(_kept(n, lp) for n, lp in kept.items()))
    for ch in rep.get("pairing", []):
        if ch.get("given"):
            k = ch["applied"]
            lines.append(f"pairing: {ch['camera']}'s images " + (f"shifted by {k:+d} instant{'s' if abs(k) != 1 else ''} (given)" if k
                                                                 else "kept as named (given)"))
        elif ch.get("applied"):
            lines.append(f"pairing: {ch['line']}: applied ({ch['applied']:+d})")
    held = {name: c.get("held") for name, c in rep["cameras"].items() if c.get("held")}
    if held:
        terms = sorted({t for h in held.values() for t in h}, key=["k3", "k4", "p1", "p2"].index)
        who = "every camera" if len(held) == len(rep["cameras"]) else ", ".join(held)
        lines.append(f"held at 0 (not fitted): {' '.join(terms)} ({who})")
    return lines


def _stereo_lines(rep: dict[str, Any]) -> list[str]:
    """The stereo pair's figures and the views' count."""
    lines = []
    st = rep.get("stereo")
    if st:
        lines.append("")
        lines.append(
            f"stereo pair {st['left']}-{st['right']}: baseline {st['baseline_m'] * 1000:.2f} mm, RMS {_fmt(st['rms_px'])} px "
            f"over {st['common_views']} shared views, epipolar error after rectification {_fmt(st['epipolar_rms_px'])} px RMS "
            f"(max {_fmt(st['epipolar_max_px'])} px)"
        )
    lines.append(f"views: {rep['views_total']} ({rep['views_multi_camera']} seen by two or more cameras)")
    return lines


def _coverage_lines(rep: dict[str, Any]) -> list[str]:
    """Each camera's board coverage grid, four cameras side by side."""
    lines = ["board coverage (# seen, . never):"]
    cams = list(rep["cameras"].items())
    for start in range(0, len(cams), 4):
        chunk = cams[start : start + 4]
        width = max(len(c["coverage"]["grid"][0]) for _, c in chunk) + 4
        lines.append("  " + "".join(f"{n[: width - 2]:<{width}}" for n, _ in chunk))
        for row in range(len(chunk[0][1]["coverage"]["grid"])):
            lines.append("  " + "".join(f"{c['coverage']['grid'][row]:<{width}}" for _, c in chunk))
    return lines


def _fault_lines(rep: dict[str, Any]) -> list[str]:
    """The worst views, the rejections and the warnings."""
    lines = []
    worst = sorted(
        ((max(v.values()), view, v) for view, v in rep.get("per_view", {}).items() if v), key=lambda x: -x[0]
    )[:5]
    if worst:
        lines.append("")
        lines.append("worst views (RMS px per camera):")
        for _, view, v in worst:
            lines.append(f"  {view}: " + ", ".join(f"{c} {e:.3f}" for c, e in v.items()))
    if rep.get("rejected"):
        lines.append("")
        lines.append(f"rejected ({len(rep['rejected'])}):")
        for r in rep["rejected"]:
            lines.append(f"  view {r['view']}, camera {r['camera']}: {r['reason']}")
    if rep.get("warnings"):
        lines.append("")
        lines.append("warnings:")
        for w in rep["warnings"]:
            lines.append(f"  - {w}")
    return lines


def _kept(name: str, lp: dict[str, Any]) -> str:
    if lp["kept"]:
        return f"{name} yes"
    return f"{name} no (" + ", ".join(f"{t} {lp['terms'][t]['moved_sigma']:+.1f} sigma" for t in lp["beyond"]) + ")"


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def _std(x) -> str:
    return "unknown" if x is None else f"{x:.3g}"
