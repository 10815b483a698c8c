"""One camera's intrinsics from its own board session, with honest quality figures.

`calibrate_camera` runs the single-camera fit (`calibration.solve.calibrate_intrinsics`: views that
do not fit are rejected, one reason each), then measures how well the data pins the focal length
down: the fit is repeated leaving out one view at a time (a jackknife), and the spread of the focal
length over those fits is the uncertainty reported. A covariance from one fit assumes the model is
right and the views independent; a resampling shows what one view more or less does to the answer,
which is what goes wrong with a handful of views or a board in one part of the image.

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
from calibration.result import Rejection
from calibration.solve import MIN_VIEWS_PER_CAMERA, Options, calibrate_intrinsics, natural_key

SPREAD_WARN = 0.01  # a relative focal spread above this makes the camera "weak"
COVERAGE_WEAK = 0.25  # board coverage of the image under this makes it "weak"
RMS_UNUSABLE_PX = 2.0  # single-camera RMS above this: no lens model explains the corners


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

    def to_dict(self) -> dict[str, Any]:
        return {
            "width": self.image_size[0],
            "height": self.image_size[1],
            "fx": round(float(self.K[0, 0]), 3),
            "fy": round(float(self.K[1, 1]), 3),
            "cx": round(float(self.K[0, 2]), 3),
            "cy": round(float(self.K[1, 2]), 3),
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


def focal_spread(name: str, size: tuple[int, int], views: dict[str, Corners], object_points: np.ndarray, opts: Options) -> float | None:
    """Relative jackknife standard deviation of fx over the fits that leave one view out."""
    if len(views) <= MIN_VIEWS_PER_CAMERA:
        return None
    fx = []
    for out in views:
        rest = {v: c for v, c in views.items() if v != out}
        # the views are already vetted: no further rejection inside the resampling
        sub = Options(**{**opts.__dict__, "outlier_px": float("inf")})
        fx.append(float(calibrate_intrinsics(name, size, rest, object_points, sub, []).K[0, 0]))
    fx = np.asarray(fx)
    n = len(fx)
    std = float(np.sqrt((n - 1) / n * np.sum((fx - fx.mean()) ** 2)))
    return std / float(np.mean(fx))


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
    spread = focal_spread(name, size, kept, object_points, opts)
    cov = coverage(size, [views[v].points for v in used])
    reasons: list[str] = []
    verdict = "good"
    if fit.rms > RMS_UNUSABLE_PX:
        verdict = "unusable"
        reasons.append(f"RMS {fit.rms:.2f} px: the corners fit no lens model (wrong board size, or a moving board?)")
    else:
        if spread is None:
            reasons.append(f"{len(used)} views: too few to measure how well the focal length is pinned down (use 10 or more)")
        elif spread > SPREAD_WARN:
            reasons.append(f"focal length moves {100 * spread:.1f} % between subsets of the views (limit {100 * SPREAD_WARN:g} %): "
                           f"show the board tilted and in more parts of the image")
        if cov["fraction"] < COVERAGE_WEAK:
            reasons.append(f"the board covered {100 * cov['fraction']:.0f} % of the image (under {100 * COVERAGE_WEAK:.0f} %): "
                           f"distortion at the edges is guessed")
        if reasons:
            verdict = "weak"
    return CameraResult(name, size, fit.K, fit.dist, fit.rms, found, used, rejected, fit.held, spread, cov, verdict, reasons)
