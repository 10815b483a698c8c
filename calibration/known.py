"""Intrinsics known beforehand, to hold while the rig is solved: read from `rig calibrate intrinsics`'
file, from a rig calibration file, or from an anipose calibration TOML (`[cam_N]` with name, size,
matrix and distortions, as anipose and sleap-anipose write it)."""
from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.camera import CalibrationError


@dataclass(frozen=True)
class KnownIntrinsics:
    name: str
    size: tuple[int, int]  # (width, height)
    K: np.ndarray
    dist: np.ndarray  # k1 k2 p1 p2 k3

    def check(self, size: tuple[int, int], where: str) -> None:
        if tuple(size) != tuple(self.size):
            raise CalibrationError(f"{where}: camera '{self.name}' is {self.size[0]}x{self.size[1]} there but its images are {size[0]}x{size[1]}")


def _known(name: str, size, K, dist, where: str) -> KnownIntrinsics:
    try:
        size = (int(size[0]), int(size[1]))
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, IndexError) as exc:
        raise CalibrationError(f"{where}: camera '{name}': malformed intrinsics ({exc})") from None
    if len(dist) > 5 and np.any(dist[5:] != 0):
        raise CalibrationError(f"{where}: camera '{name}' has {len(dist)} distortion terms; only k1 k2 p1 p2 k3 can be held")
    dist = np.concatenate([dist[:5], np.zeros(max(0, 5 - len(dist)))])
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and K[0, 0] > 0 and K[1, 1] > 0 and min(size) > 0):
        raise CalibrationError(f"{where}: camera '{name}': intrinsics must be finite with positive focal lengths and size")
    return KnownIntrinsics(name, size, K, dist)


def load_known(path: str | Path) -> dict[str, KnownIntrinsics]:
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no such intrinsics file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read it as text ({exc})") from None
    if path.suffix.lower() == ".toml":
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise CalibrationError(f"{path}: not valid TOML ({exc})") from None
        out = {}
        for key, cam in doc.items():
            if not (isinstance(cam, dict) and {"name", "size", "matrix", "distortions"} <= set(cam)):
                continue  # anipose files carry other tables (metadata) beside the cameras
            out[str(cam["name"])] = _known(str(cam["name"]), cam["size"], cam["matrix"], cam["distortions"], str(path))
        if not out:
            raise CalibrationError(f"{path}: no camera tables with name, size, matrix and distortions (an anipose calibration file?)")
        return out
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    if isinstance(doc, dict) and doc.get("format") == "rig-intrinsics":
        cams = doc.get("cameras")
        if not isinstance(cams, dict) or not cams:
            raise CalibrationError(f"{path}: no cameras in this intrinsics file")
        return {n: _known(n, (c.get("width"), c.get("height")),
                          [[c.get("fx"), 0, c.get("cx")], [0, c.get("fy"), c.get("cy")], [0, 0, 1]], c.get("dist", []), str(path))
                for n, c in cams.items()}
    if isinstance(doc, dict) and isinstance(doc.get("cameras"), list):
        from calibration.camera import RigCalibration

        rig = RigCalibration.from_dict(doc, where=str(path))
        return {c.name: _known(c.name, (c.width, c.height), c.K, c.dist, str(path)) for c in rig.cameras}
    raise CalibrationError(f"{path}: neither an intrinsics file (`rig calibrate intrinsics`), a calibration file nor an anipose TOML")
