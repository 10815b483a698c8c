"""Camera model (OpenCV's pinhole or fisheye lens, calibration.lens) and the rig calibration file.

Conventions (OpenCV): pixel centres at integer coordinates, x right, y down, z forward.
`R`, `t` map world points into the camera: X_cam = R @ X_world + t. Units are metres.
The file schema is shared by the calibrator's output and the simulator's ground truth:

    {"version": 1, "cameras": [{"name", "width", "height", "K", "dist", "R", "t"[, "model"]}], ...}

"model" is "pinhole" (dist = k1 k2 p1 p2 k3; the default, and absent from the file) or "fisheye"
(dist = k1 k2 k3 k4).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from calibration import lens
from common.errors import ReportedError
from common.files import atomic_write_json

SCHEMA_VERSION = 1


class CalibrationError(ReportedError):
    """A calibration input or file is unusable; the message says which and why."""

    exit_code = 2


@dataclass
class CameraModel:
    """One calibrated camera: intrinsics, lens model and its distortion (pinhole: k1 k2 p1 p2 k3;
    fisheye: k1 k2 k3 k4) and world-to-camera pose."""

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    model: str = "pinhole"

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)
        self.width = int(self.width)
        self.height = int(self.height)

    # -- properties -----------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def extrinsic(self) -> np.ndarray:
        """4x4 world-to-camera matrix."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def has_distortion(self) -> bool:
        """False only for a pinhole camera with every term 0 (a fisheye lens always bends rays)."""
        return self.model == "fisheye" or bool(np.any(self.dist != 0))

    # -- geometry -------------------------------------------------------------------------------
    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        pts = np.asarray(points, dtype=np.float64)
        return pts @ self.R.T + self.t

    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply the lens model's distortion to normalised image coordinates (..., 2)."""
        return lens.distort(self.model, self.dist, xy)

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (..., 3) to pixels (..., 2); also returns depth z (...)."""
        pc = self.world_to_camera(points_world)
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = pc[..., :2] / z[..., None]
        xy = self.distort_normalized(xy)
        uv = np.empty_like(xy)
        uv[..., 0] = self.K[0, 0] * xy[..., 0] + self.K[0, 1] * xy[..., 1] + self.K[0, 2]
        uv[..., 1] = self.K[1, 1] * xy[..., 1] + self.K[1, 2]
        return uv, z

    def undistort_normalized(self, uv: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Pixels (..., 2) to undistorted normalised coordinates (..., 2) (calibration.lens.undistort;
        NaN where a fisheye lens sees beyond 90 degrees)."""
        uv = np.asarray(uv, dtype=np.float64)
        y = (uv[..., 1] - self.cy) / self.fy
        x = (uv[..., 0] - self.cx - self.K[0, 1] * y) / self.fx
        xd = np.stack([x, y], axis=-1)
        if not self.has_distortion:
            return xd
        return lens.undistort(self.model, self.dist, xd, iterations)

    def pixel_rays(self, uv: np.ndarray | None = None) -> np.ndarray:
        """Unit-z camera-frame directions (x, y, 1) for pixels uv (..., 2); all pixels when None."""
        if uv is None:
            u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
            uv = np.stack([u, v], axis=-1)
        xy = self.undistort_normalized(uv)
        return np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)

    def scaled(self, width: int, height: int) -> "CameraModel":
        """The same camera resampled to another image size (pixel-centre convention kept)."""
        sx = width / self.width
        sy = height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return CameraModel(self.name, width, height, K, self.dist.copy(), self.R.copy(), self.t.copy(), self.model)

    def with_pose(self, R: np.ndarray, t: np.ndarray) -> "CameraModel":
        return CameraModel(self.name, self.width, self.height, self.K.copy(), self.dist.copy(), R, t, self.model)

    # -- serialisation --------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        d = {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
        }
        if self.model != "pinhole":
            d["model"] = self.model
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "camera") -> "CameraModel":
        for key in ("name", "width", "height", "K"):
            if key not in d:
                raise CalibrationError(f"{where}: missing key '{key}'")
        model = d.get("model", "pinhole")
        if model not in lens.MODELS:
            raise CalibrationError(f"{where}: unknown lens model {model!r} (allowed: {', '.join(lens.MODELS)})")
        try:
            cam = cls(
                model=model,
                name=str(d["name"]),
                width=int(d["width"]),
                height=int(d["height"]),
                K=np.asarray(d["K"], dtype=np.float64),
                dist=np.asarray(d.get("dist", [0.0] * lens.N_DIST[model]), dtype=np.float64),
                R=np.asarray(d.get("R", np.eye(3)), dtype=np.float64),
                t=np.asarray(d.get("t", [0, 0, 0]), dtype=np.float64),
            )
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"{where}: malformed values ({exc})") from None
        if cam.width <= 0 or cam.height <= 0:
            raise CalibrationError(f"{where}: width and height must be positive")
        if not np.all(np.isfinite(cam.K)) or cam.fx <= 0 or cam.fy <= 0:
            raise CalibrationError(f"{where}: K must be finite with positive focal lengths")
        if cam.dist.size > lens.N_DIST[model] and np.any(cam.dist[lens.N_DIST[model]:] != 0):
            raise CalibrationError(f"{where}: a {model} lens has {lens.N_DIST[model]} distortion terms "
                                   f"({' '.join(lens.DIST_NAMES[model])}), got {cam.dist.size}")
        if not np.all(np.isfinite(cam.dist)):
            raise CalibrationError(f"{where}: distortion terms must be finite")
        if not np.allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-6):
            raise CalibrationError(f"{where}: R is not a rotation matrix")
        return cam


def look_at(eye: Iterable[float], target: Iterable[float], up: Iterable[float] = (0.0, 1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) for a camera at `eye` looking at `target`; `up` is world up (y-up scenes).

    The camera's y axis points down in the image, so it is aligned with -up.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)  # right = forward x up, so that y = z x x points along -up (image down)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: view direction parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    t = -R @ eye
    return R, t


def intrinsics_from_fov(width: int, height: int, hfov_deg: float) -> np.ndarray:
    fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[fx, 0.0, (width - 1) / 2.0], [0.0, fx, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass
class RigCalibration:
    """All cameras of a rig in one world frame, plus free-form metadata (board, RMS, date, ...)."""

    cameras: list[CameraModel]
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise CalibrationError(f"duplicate camera names in calibration: {names}")

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def __getitem__(self, name: str) -> CameraModel:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(f"no camera '{name}' in calibration (have: {', '.join(self.names)})")

    def __contains__(self, name: str) -> bool:
        return name in self.names

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"version": SCHEMA_VERSION, "cameras": [c.to_dict() for c in self.cameras]}
        for k, v in self.meta.items():
            if k not in d:
                d[k] = v
        return d

    @classmethod
    def from_dict(cls, d: Any, where: str = "calibration") -> "RigCalibration":
        if not isinstance(d, dict):
            raise CalibrationError(f"{where}: expected a JSON object")
        version = d.get("version")
        if version != SCHEMA_VERSION:
            raise CalibrationError(f"{where}: unsupported schema version {version!r} (this program reads version {SCHEMA_VERSION})")
        cams = d.get("cameras")
        if not isinstance(cams, list) or not cams:
            raise CalibrationError(f"{where}: 'cameras' must be a non-empty list")
        cameras = []
        for i, c in enumerate(cams):
            if not isinstance(c, dict):
                raise CalibrationError(f"{where}: cameras[{i}] must be an object")
            cameras.append(CameraModel.from_dict(c, where=f"{where}: cameras[{i}]"))
        meta = {k: v for k, v in d.items() if k not in ("version", "cameras")}
        return cls(cameras, meta)

    def save(self, path: str | os.PathLike) -> None:
        """Write atomically (temp file + rename), so a crash never leaves a torn calibration."""
        atomic_write_json(path, self.to_dict(), make_parents=True)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "RigCalibration":
        path = Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise CalibrationError(f"{path}: no such calibration file") from None
        except UnicodeDecodeError:
            raise CalibrationError(f"{path}: not a calibration file (not JSON text)") from None
        except OSError as exc:
            raise CalibrationError(f"{path}: cannot read ({exc.strerror})") from None
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
        return cls.from_dict(d, where=str(path))
