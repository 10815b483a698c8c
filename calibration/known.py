"""Intrinsics known beforehand, to hold while the rig is solved: read from `rig calibrate intrinsics`'
file, from a rig calibration file, or from an anipose calibration TOML (`[cam_N]` with name, size,
matrix and distortions, and `fisheye = true` for a fisheye lens, as anipose and sleap-anipose write
it). Each camera keeps its lens model (calibration.lens)."""
from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration import lens
from calibration.camera import CalibrationError


@dataclass(frozen=True)
class KnownIntrinsics:
    name: str
    size: tuple[int, int]  # (width, height)
    K: np.ndarray
    dist: np.ndarray  # pinhole: k1 k2 p1 p2 k3; fisheye: k1 k2 k3 k4
    model: str = "pinhole"
    source: str = ""  # the file the intrinsics were read from

    def check(self, size: tuple[int, int], where: str = "") -> None:
        if tuple(size) != tuple(self.size):
            raise CalibrationError(f"{where or self.source or 'intrinsics given'}: camera '{self.name}' is {self.size[0]}x{self.size[1]} "
                                   f"there but its images are {size[0]}x{size[1]}")


def _known(name: str, size, K, dist, where: str, model: str = "pinhole") -> KnownIntrinsics:
    try:
        size = (int(size[0]), int(size[1]))
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, IndexError) as exc:
        raise CalibrationError(f"{where}: camera '{name}': malformed intrinsics ({exc})") from None
    if model not in lens.MODELS:
        raise CalibrationError(f"{where}: camera '{name}': unknown lens model {model!r} (allowed: {', '.join(lens.MODELS)})")
    n = lens.N_DIST[model]
    if len(dist) > n and np.any(dist[n:] != 0):
        raise CalibrationError(f"{where}: camera '{name}' has {len(dist)} distortion terms; a {model} lens has {n} "
                               f"({' '.join(lens.DIST_NAMES[model])})")
    dist = lens.coefficients(model, dist)
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and K[0, 0] > 0 and K[1, 1] > 0 and min(size) > 0):
        raise CalibrationError(f"{where}: camera '{name}': intrinsics must be finite with positive focal lengths and size")
    return KnownIntrinsics(name, size, K, dist, model, where)


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
            model = "fisheye" if cam.get("fisheye") is True else "pinhole"
            out[str(cam["name"])] = _known(str(cam["name"]), cam["size"], cam["matrix"], cam["distortions"], str(path), model)
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
                          [[c.get("fx"), 0, c.get("cx")], [0, c.get("fy"), c.get("cy")], [0, 0, 1]], c.get("dist", []), str(path),
                          c.get("model", "pinhole"))
                for n, c in cams.items()}
    if isinstance(doc, dict) and isinstance(doc.get("cameras"), list):
        from calibration.camera import RigCalibration

        rig = RigCalibration.from_dict(doc, where=str(path))
        return {c.name: _known(c.name, (c.width, c.height), c.K, c.dist, str(path), c.model) for c in rig.cameras}
    raise CalibrationError(f"{path}: neither an intrinsics file (`rig calibrate intrinsics`), a calibration file nor an anipose TOML")


# -- given intrinsics as priors ----------------------------------------------------------------------
PIXEL_TERMS = {"f": ("fx", "fy"), "c": ("cx", "cy"), "fx": ("fx",), "fy": ("fy",), "cx": ("cx",), "cy": ("cy",)}
DIST_TERMS = ("k1", "k2", "k3", "k4", "p1", "p2")


def parse_prior(spec: str) -> dict[str, tuple[float, bool]]:
    """`f=1%,c=8,dist=0.02` -> {term: (sigma, in percent of the focal length)}: the one-sigma freedom
    each given term has in the rig solve. f and c (or fx fy cx cy) in pixels, or with % in percent of
    the focal length; distortion terms (k1 k2 k3 k4 p1 p2, or dist for all) as plain numbers."""
    out: dict[str, tuple[float, bool]] = {}
    for part in (p.strip() for p in str(spec).split(",")):
        if not part:
            continue
        term, eq, value = part.partition("=")
        term, value = term.strip(), value.strip()
        if not eq or term not in (*PIXEL_TERMS, *DIST_TERMS, "dist"):
            raise CalibrationError(f"prior {part!r}: expected TERM=SIGMA with TERM one of f c fx fy cx cy k1 k2 k3 k4 p1 p2 dist")
        percent = value.endswith("%")
        if percent and term not in PIXEL_TERMS:
            raise CalibrationError(f"prior {part!r}: only f and c (fx fy cx cy) take a percentage")
        try:
            sigma = float(value[:-1] if percent else value)
        except ValueError:
            raise CalibrationError(f"prior {part!r}: {value!r} is not a number") from None
        if not (np.isfinite(sigma) and sigma > 0):
            raise CalibrationError(f"prior {part!r}: the sigma must be a positive number")
        if term in out:
            raise CalibrationError(f"prior {part!r}: {term} is given a sigma twice")
        out[term] = (sigma, percent)
    if not out:
        raise CalibrationError("the prior names no term (e.g. f=1%,c=8,dist=0.02)")
    return out


def prior_sigmas(known: KnownIntrinsics, prior: dict[str, tuple[float, bool]]) -> dict[str, float]:
    """Each term's sigma for this camera, by the names of its lens model's slots (calibration.bundle)."""
    names = lens.DIST_NAMES[known.model]
    sigmas: dict[str, float] = {}
    for term, (sigma, percent) in prior.items():
        value = sigma * float(known.K[0, 0]) / 100.0 if percent else sigma
        for t in PIXEL_TERMS.get(term) or (names if term == "dist" else (term,)):
            if t not in PIXEL_TERMS and t not in names:
                raise CalibrationError(f"prior {term}: camera '{known.name}' has a {known.model} lens, whose terms are {' '.join(names)}")
            sigmas[t] = value
    return sigmas
