"""What a rig calibration produces besides the calibration file: the observations it used, the
single-camera fits, the rejections with their reasons and the joint adjustment's solution.

The solver (`calibration.solve`) fills these and the report (`calibration.report`) reads them; they
live apart from both so that the dependency runs one way: solve -> report -> result.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration import bundle
from calibration.camera import RigCalibration


@dataclass
class Rejection:
    camera: str
    view: str
    stage: str  # "intrinsics" | "joint"
    rms_px: float
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return {"camera": self.camera, "view": self.view, "stage": self.stage, "rms_px": round(self.rms_px, 4), "reason": self.reason}


@dataclass
class CameraIntrinsics:
    """One camera's single-camera fit (`cv2.calibrateCamera`, or the fisheye fit) over the views it kept."""

    K: np.ndarray
    dist: np.ndarray
    rms: float
    view_rms: dict[str, float]
    poses: dict[str, tuple[np.ndarray, np.ndarray]]  # view -> board-to-camera (R, t)
    fix_k3: bool
    held: tuple[str, ...] = ()  # distortion terms held at 0 in every fit ("k3", "p1", "p2")
    k3_held_for_views: bool = False  # k3 held because the camera had too few views (not by choice)
    given: bool = False  # the intrinsics were given (calibration.known) and held: only board poses were fitted
    focal_spread: float | None = None  # relative spread of fx over fits on subsets of the views (calibration.quality)
    model: str = "pinhole"  # lens model (calibration.lens)
    prior: dict[str, float] | None = None  # the given intrinsics were priors: term -> sigma (calibration.known.prior_sigmas)
    # this fit as the lens's prior in the joint adjustment (calibration.solve.lens_information): its
    # information matrix over the nine slots, and each fitted term's one-sigma uncertainty from it
    lens_information: np.ndarray | None = None
    lens_sigma: dict[str, float] | None = None
    lens_mean: np.ndarray | None = None  # (9,) the nine slots the prior is centred on (that fit, finished by the adjustment)


@dataclass
class Observations:
    """The corners used in the final adjustment and their residuals, for the report."""

    cameras: list[str]
    views: list[str]
    cam_idx: np.ndarray
    view_idx: np.ndarray
    ids: np.ndarray
    uv: np.ndarray
    residuals: np.ndarray


@dataclass
class CalibrationResult:
    rig: RigCalibration
    left: str
    right: str | None
    observations: Observations
    intrinsics: dict[str, CameraIntrinsics]
    rejected: list[Rejection]
    stereo_init: dict[str, Any] | None
    solution: bundle.Solution
    image_size: dict[str, tuple[int, int]]
    images_seen: dict[str, int] = field(default_factory=dict)
    corners_rejected: dict[str, int] = field(default_factory=dict)  # single corners dropped, per camera
    pairing: list = field(default_factory=list)  # calibration.pairing.PairingCheck per camera but the left
