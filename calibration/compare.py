"""How far a calibration is from the true rig: the one measure the tests, the benchmarks and `rig demo`
use against a known rig (synthetic, or the simulator's exact cameras).

A calibration's world frame is a choice (the solver puts its left camera at the origin; a simulator
puts the scene centre there), so both rigs are first re-expressed in the frame of one reference
camera; poses are then compared camera by camera. Figures, per camera:

- `focal_pct`: the larger of |fx / fx_true - 1| and |fy / fy_true - 1|, in percent;
- `principal_px`: distance between the principal points, in pixels;
- `rotation_deg`: angle of the rotation between the two orientations, in degrees;
- `position_mm`: distance between the camera centres, in millimetres (rigs in metres);

and for the rig, `baseline_pct`: the stereo pair's baseline (distance between its two centres)
against the true one, in percent. `worst` holds the largest of each figure over the cameras.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import CalibrationError, CameraModel, RigCalibration
from calibration.geometry import rotation_angle_deg

FIGURES = ("focal_pct", "principal_px", "rotation_deg", "position_mm")


@dataclass
class TruthErrors:
    reference: str  # camera at the origin of the frame both rigs were compared in
    pair: tuple[str, str]  # the stereo pair whose baseline was compared
    cameras: dict[str, dict[str, float]]  # camera -> {figure: value}
    baseline_pct: float | None  # None for a one-camera rig

    @property
    def worst(self) -> dict[str, float]:
        """The largest of each figure over the cameras, and the baseline error."""
        out = {k: max(e[k] for e in self.cameras.values()) for k in FIGURES}
        if self.baseline_pct is not None:
            out["baseline_pct"] = self.baseline_pct
        return out


def in_frame_of(rig: RigCalibration, ref: str) -> RigCalibration:
    """The rig re-expressed with camera `ref` at the origin (X_ref = R_ref X + t_ref)."""
    r = rig[ref]
    out = []
    for c in rig.cameras:
        R = c.R @ r.R.T
        t = c.t - R @ r.t
        out.append(c.with_pose(R, t))
    return RigCalibration(out, dict(rig.meta))


def camera_errors(estimate: CameraModel, truth: CameraModel) -> dict[str, float]:
    """One camera against the true one; both poses must already be in the same frame."""
    return {
        "focal_pct": 100 * max(abs(estimate.fx / truth.fx - 1), abs(estimate.fy / truth.fy - 1)),
        "principal_px": float(np.hypot(estimate.cx - truth.cx, estimate.cy - truth.cy)),
        "rotation_deg": rotation_angle_deg(estimate.R, truth.R),
        "position_mm": 1000 * float(np.linalg.norm(estimate.center - truth.center)),
    }


def errors_against_truth(
    estimate: RigCalibration, truth: RigCalibration, reference: str | None = None, pair: tuple[str, str] | None = None
) -> TruthErrors:
    """Every camera of `estimate` against the camera of the same name in `truth`.

    `reference` is the camera whose frame both rigs are compared in (default: the estimate's first
    camera, the solver's left camera). `pair` is the stereo pair whose baseline is compared (default:
    the file's `stereo_pair` metadata, else the estimate's first and last cameras).
    """
    missing = [n for n in estimate.names if n not in truth]
    if missing:
        raise CalibrationError(f"the true rig has no camera {', '.join(repr(m) for m in missing)} (it has: {', '.join(truth.names)})")
    reference = reference or estimate.names[0]
    if pair is None:
        sp = estimate.meta.get("stereo_pair") or {}
        pair = (sp["left"], sp["right"]) if sp.get("left") and sp.get("right") else (estimate.names[0], estimate.names[-1])
    est = in_frame_of(estimate, reference)
    gt = in_frame_of(truth, reference)
    cameras = {c.name: camera_errors(c, gt[c.name]) for c in est.cameras}
    a, b = pair
    baseline_pct = None
    if a != b:
        true_baseline = float(np.linalg.norm(gt[b].center - gt[a].center))
        baseline = float(np.linalg.norm(est[b].center - est[a].center))
        baseline_pct = 100 * abs(baseline / true_baseline - 1)
    return TruthErrors(reference, (a, b), cameras, baseline_pct)


def describe(figures: dict[str, float]) -> str:
    """One line of the figures (a camera's or the worst), with the precision they are measured to."""
    text = (f"focal {figures['focal_pct']:.4f}%, principal point {figures['principal_px']:.3f} px, "
            f"rotation {figures['rotation_deg']:.4f} deg, position {figures['position_mm']:.3f} mm")
    if "baseline_pct" in figures:
        text += f", baseline {figures['baseline_pct']:.4f}%"
    return text
