"""The virtual rig: N cameras on an arc facing the actors, as exact ground-truth calibration.

Cameras stand on a horizontal arc of `radius` metres around the origin on the +z side, at `height`,
all looking at `target`. The outermost two are the `left` and `right` sources, `span_deg` apart
(60 degrees by default, the paper's setting); the others are supervision cameras `sup1`, `sup2`, ...
in arc order from left to right (as seen from behind the rig). Each camera gets a slightly different
lens (focal length, principal point, radial and tangential distortion), deterministic for a seed.
"""
from __future__ import annotations

import math

import numpy as np

from calibration.camera import CameraModel, RigCalibration, intrinsics_from_fov, look_at
from simulator.errors import SimulatorError


def camera_names(n_cameras: int) -> list[str]:
    """'left', 'sup1', ..., 'right' in arc order."""
    if n_cameras < 1:
        raise SimulatorError(f"a rig needs at least one camera, got {n_cameras}")
    if n_cameras == 1:
        return ["left"]
    return ["left"] + [f"sup{i}" for i in range(1, n_cameras - 1)] + ["right"]


def virtual_rig(n_cameras: int = 6, width: int = 1280, height: int = 720, **kwargs) -> RigCalibration:
    """Ground-truth calibration of an N-camera arc rig (world frame of simulator.scene): cameras
    'left', 'sup1', ..., 'right' of width x height. Keyword arguments as for `arc_rig`."""
    for name, v in (("n_cameras", n_cameras), ("width", width), ("height", height)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool):
            raise SimulatorError(f"{name} must be an integer, got {v!r}")
    if n_cameras < 1 or n_cameras > 64:
        raise SimulatorError(f"n_cameras must be between 1 and 64, got {n_cameras}")
    return arc_rig([(name, width, height) for name in camera_names(n_cameras)], **kwargs)


def arc_rig(cameras, *, span_deg: float = 60.0, radius: float = 3.6, camera_height: float = 1.5,
            target=(0.0, 1.0, 0.0), hfov_deg: float = 62.0, distortion: bool = True, seed: int = 0) -> RigCalibration:
    """Cameras [(name, width, height)] placed in that order from left to right on the arc."""
    n = len(cameras)
    if n < 1:
        raise SimulatorError("a rig needs at least one camera")
    if not 0 < hfov_deg < 170:
        raise SimulatorError(f"hfov_deg must be between 0 and 170, got {hfov_deg}")
    if not radius > 0:
        raise SimulatorError(f"radius must be positive, got {radius}")
    cams = []
    for i, (name, width, height) in enumerate(cameras):
        if not isinstance(width, (int, np.integer)) or not isinstance(height, (int, np.integer)) or width <= 0 or height <= 0:
            raise SimulatorError(f"camera {name}: image size must be positive integers, got {width}x{height}")
        # Lens of camera i depends on (seed, i) only, so a camera keeps its lens at any resolution.
        rng = np.random.default_rng([int(seed), 7, i])
        # left is on the viewer's left: world -x for cameras looking towards -z
        a = 0.0 if n == 1 else math.radians(-span_deg / 2 + span_deg * i / (n - 1))
        eye = np.array([radius * math.sin(a), camera_height, radius * math.cos(a)])
        R, t = look_at(eye, target)
        K = intrinsics_from_fov(width, height, hfov_deg * rng.uniform(0.97, 1.03))
        K[1, 1] = K[0, 0] * rng.uniform(0.998, 1.002)
        K[0, 2] += rng.uniform(-0.01, 0.01) * width
        K[1, 2] += rng.uniform(-0.01, 0.01) * height
        dist = np.zeros(5)
        if distortion:
            dist = np.array([rng.uniform(-0.12, 0.05), rng.uniform(-0.03, 0.06), rng.uniform(-1e-3, 1e-3),
                             rng.uniform(-1e-3, 1e-3), 0.0])
        cams.append(CameraModel(name, width, height, K, dist, R, t))
    return RigCalibration(cams, {"source": "simulator", "span_deg": span_deg, "radius": radius})
