"""One camera's intrinsics from its own board session, with honest quality figures.

`calibrate_camera` runs the single-camera fit (`calibration.solve.calibrate_intrinsics`: views that
do not fit are rejected, one reason each), then measures how well the data pins the focal length
down: the spread of the focal length over fits that leave part of the views out
(calibration.quality.focal_spread).

Verdict per camera: "good", "weak" (usable, with the reason: focal spread over 1 %, coverage under
a quarter of the image, few views) or "unusable" (too few views, or an RMS no lens model explains).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.camera import CalibrationError
from calibration.detect import Corners
from calibration.report import coverage
from calibration.quality import COVERAGE_WEAK, RMS_UNUSABLE_PX, spread_reason, verdict
from calibration.result import Rejection
from calibration.images import natural_key
from calibration.solve import MIN_VIEWS_PER_CAMERA, Options, calibrate_intrinsics, resampled_spread


@dataclass
class CameraResult:
    name: str
    image_size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    rms_px: float
    views_found: int
    views_used: list[str]
    rejected: list[Rejection]
    held: tuple[str, ...]
    focal_spread: float | None  # relative jackknife standard deviation of fx; None below 5 views
    coverage: dict[str, Any]
    verdict: str
    reasons: list[str] = field(default_factory=list)
    model: str = "pinhole"  # lens model (calibration.lens): "fisheye" has dist k1 k2 k3 k4

    def to_dict(self) -> dict[str, Any]:
        return {
            "width": self.image_size[0],
            "height": self.image_size[1],
            "fx": round(float(self.K[0, 0]), 3),
            "fy": round(float(self.K[1, 1]), 3),
            "cx": round(float(self.K[0, 2]), 3),
            "cy": round(float(self.K[1, 2]), 3),
            "model": self.model,
            "dist": [round(float(x), 6) for x in self.dist],
            "held": list(self.held),
            "rms_px": round(self.rms_px, 4),
            "views_found": self.views_found,
            "views_used": len(self.views_used),
            "rejected": [r.to_dict() for r in self.rejected],
            "focal_spread_pct": None if self.focal_spread is None else round(100 * self.focal_spread, 3),
            "coverage": self.coverage["fraction"],
            "verdict": self.verdict,
            "reasons": self.reasons,
        }


def calibrate_camera(name: str, size: tuple[int, int], views: dict[str, Corners], object_points: np.ndarray,
                     opts: Options | None = None) -> CameraResult:
    opts = opts or Options()
    found = len(views)
    if found < MIN_VIEWS_PER_CAMERA:
        raise CalibrationError(f"camera '{name}': the board was found in only {found} image(s); at least {MIN_VIEWS_PER_CAMERA} are needed")
    rejected: list[Rejection] = []
    fit = calibrate_intrinsics(name, size, views, object_points, opts, rejected)
    used = sorted(fit.view_rms, key=natural_key)
    kept = {v: views[v] for v in used}
    spread = resampled_spread(name, size, kept, object_points, opts, fit.K, fit.dist)
    cov = coverage(size, [views[v].points for v in used])
    reasons: list[str] = []
    if fit.rms > RMS_UNUSABLE_PX:
        reasons.append(f"RMS {fit.rms:.2f} px: the corners fit no lens model (wrong board size, or a moving board?)")
    else:
        why = spread_reason(spread, len(used))
        if why:
            reasons.append(why)
        if cov["fraction"] < COVERAGE_WEAK:
            reasons.append(f"the board covered {100 * cov['fraction']:.0f} % of the image (under {100 * COVERAGE_WEAK:.0f} %): "
                           f"distortion at the edges is guessed")
    verdict_ = verdict(fit.rms, reasons)
    return CameraResult(name, size, fit.K, fit.dist, fit.rms, found, used, rejected, fit.held, spread, cov, verdict_, reasons, fit.model)
