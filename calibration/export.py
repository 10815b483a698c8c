"""Exports of a rig calibration to the formats other tools read.

Conventions of the formats differ in where a pixel's centre is: OpenCV, EasyMocap and aniposelib put
pixel (0, 0)'s centre at (0, 0), as our file does; COLMAP and nerfstudio put it at (0.5, 0.5), so their
principal points are shifted by +0.5 px. All translations stay in metres.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from calibration import lens
from calibration.camera import CalibrationError, CameraModel, RigCalibration
from common.files import atomic_path, atomic_write_bytes
from calibration.geometry import rotation_vector
from calibration.report import rectification

FORMATS = ("opencv", "easymocap", "anipose", "nerfstudio", "colmap")
IMAGE_FORMATS = ("nerfstudio", "colmap")  # formats that point at one image per camera (images/NAME.png)


def stereo_pair(rig: RigCalibration) -> tuple[CameraModel, CameraModel]:
    """The stereo pair: as the calibration names it, else cameras 'left' and 'right', else first and last."""
    pair = rig.meta.get("stereo_pair") or {}
    names = rig.names
    left = pair.get("left") if pair.get("left") in names else ("left" if "left" in names else names[0])
    right = pair.get("right") if pair.get("right") in names else ("right" if "right" in names else names[-1])
    if left == right:
        raise CalibrationError("the calibration has a single camera; the OpenCV stereo export needs two")
    return rig[left], rig[right]


def _fs_write(path: Path, entries: list[tuple[str, object]]) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        for key, value in entries:
            if isinstance(value, (int, np.integer)):
                fs.write(key, int(value))  # a plain integer node (EasyMocap reads H_ and W_ as such)
            elif isinstance(value, str):
                fs.write(key, value)
            elif isinstance(value, (list, tuple)) and value and isinstance(value[0], str):
                fs.startWriteStruct(key, cv2.FileNode_SEQ)
                for s in value:
                    fs.write("", s)
                fs.endWriteStruct()
            else:
                fs.write(key, np.asarray(value, dtype=np.float64))
    finally:
        fs.release()


def rectification_maps(left: CameraModel, right: CameraModel, alpha: float | None = None) -> dict[str, np.ndarray]:
    """Per-pixel lookup maps (for cv2.remap) that rectify the pair, plus R1 R2 P1 P2 Q."""
    rect = rectification(left, right, alpha)
    lx, ly = lens.undistort_rectify_map(left.model, left.K, left.dist, rect["R1"], rect["P1"], (left.width, left.height))
    rx, ry = lens.undistort_rectify_map(right.model, right.K, right.dist, rect["R2"], rect["P2"], (left.width, left.height))
    return {"left_map_x": lx, "left_map_y": ly, "right_map_x": rx, "right_map_y": ry, **{k: rect[k] for k in ("R1", "R2", "P1", "P2", "Q")}}


def export_opencv(rig: RigCalibration, out: Path, images=None) -> list[Path]:
    """intrinsics.yml (M1 D1 M2 D2, and lens1 lens2: "pinhole", whose D has k1 k2 p1 p2 k3 for
    cv2.initUndistortRectifyMap, or "fisheye", whose D has k1..k4 for cv2.fisheye's), extrinsics.yml
    (R T R1 R2 P1 P2 Q; right-from-left) and the rectification maps of the stereo pair
    (rectification_maps.npz)."""
    left, right = stereo_pair(rig)
    rect = rectification(left, right)
    intr = out / "intrinsics.yml"
    extr = out / "extrinsics.yml"
    _fs_write(intr, [("M1", left.K), ("D1", left.dist.reshape(1, -1)), ("M2", right.K), ("D2", right.dist.reshape(1, -1)),
                     ("lens1", left.model), ("lens2", right.model)])
    _fs_write(extr, [("R", rect["R"]), ("T", rect["T"].reshape(3, 1)), ("R1", rect["R1"]), ("R2", rect["R2"]),
                     ("P1", rect["P1"]), ("P2", rect["P2"]), ("Q", rect["Q"])])
    maps = out / "rectification_maps.npz"
    np.savez_compressed(maps, **rectification_maps(left, right))
    return [intr, extr, maps]


def export_easymocap(rig: RigCalibration, out: Path, images=None) -> list[Path]:
    """EasyMocap intri.yml (K_NAME, dist_NAME, and the image size H_NAME W_NAME, integers, as
    EasyMocap's read_camera reads them) and extri.yml (R_NAME Rodrigues, Rot_NAME, T_NAME)."""
    fisheye = [c.name for c in rig.cameras if c.model == "fisheye"]
    if fisheye:
        raise CalibrationError(f"EasyMocap reads only OpenCV's pinhole lens model; camera(s) {', '.join(fisheye)} have a fisheye "
                               f"lens (export to colmap, nerfstudio, anipose or opencv instead)")
    intr = out / "intri.yml"
    extr = out / "extri.yml"
    names = rig.names
    _fs_write(intr, [("names", names)] + [e for c in rig.cameras for e in (
        (f"K_{c.name}", c.K), (f"dist_{c.name}", _dist5(c).reshape(1, 5)), (f"H_{c.name}", int(c.height)), (f"W_{c.name}", int(c.width)))])
    _fs_write(extr, [("names", names)] + [e for c in rig.cameras for e in (
        (f"R_{c.name}", rotation_vector(c.R).reshape(3, 1)), (f"Rot_{c.name}", c.R), (f"T_{c.name}", c.t.reshape(3, 1)))])
    return [intr, extr]


def _dist5(cam: CameraModel) -> np.ndarray:
    d = np.zeros(5)
    d[: min(5, cam.dist.size)] = cam.dist[:5]
    return d


def _toml_list(values) -> str:
    return "[" + ", ".join(_toml_list(v) if isinstance(v, (list, tuple, np.ndarray)) else repr(float(v)) for v in values) + "]"


def export_anipose(rig: RigCalibration, out: Path, images=None) -> list[Path]:
    """aniposelib CameraGroup TOML: [cam_N] name size matrix distortions rotation (Rodrigues) translation,
    and `fisheye = true` with the four fisheye terms for a fisheye camera (aniposelib's FisheyeCamera)."""
    path = out / "calibration.toml"
    lines = []
    for i, c in enumerate(rig.cameras):
        lines += [
            f"[cam_{i}]",
            f'name = "{c.name}"',
            f"size = [{c.width}, {c.height}]",
            f"matrix = {_toml_list(c.K)}",
            f"distortions = {_toml_list(lens.coefficients(c.model, c.dist))}",
            f"rotation = {_toml_list(rotation_vector(c.R))}",
            f"translation = {_toml_list(c.t)}",
        ] + (["fisheye = true"] if c.model == "fisheye" else []) + [""]
    rms = rig.meta.get("rms_px") or {}
    err = float(np.mean(list(rms.values()))) if rms else 0.0
    lines += ["[metadata]", "adjusted = true", f"error = {err!r}", ""]
    path.write_text("\n".join(lines))
    return [path]


def write_images(out: Path, rig: RigCalibration, images: dict[str, np.ndarray]) -> list[Path]:
    """out/images/NAME.png for every camera: the image it points at, at the calibrated size."""
    files = []
    for c in rig.cameras:
        img = np.asarray(images[c.name])
        if img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        if img.ndim == 3 and img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        path = out / "images" / f"{c.name}.png"
        with atomic_path(path, make_parents=True) as tmp:
            if not cv2.imwrite(str(tmp), img):
                raise OSError(f"{path}: could not write the image")
        files.append(path)
    return files


def check_images(rig: RigCalibration, images: dict[str, np.ndarray], source: str) -> None:
    """Every calibrated camera has an image at its calibrated size (the intrinsics are per pixel)."""
    for c in rig.cameras:
        if c.name not in images:
            raise CalibrationError(f"{source}: no image of camera '{c.name}'")
        h, w = np.asarray(images[c.name]).shape[:2]
        if (w, h) != (c.width, c.height):
            raise CalibrationError(f"{source}: camera '{c.name}' images are {w}x{h} but it was calibrated at {c.width}x{c.height}")


def images_from_views(rig: RigCalibration, folder: str | Path, view: str | None = None) -> dict[str, np.ndarray]:
    """One calibration view (DIR/CAMNAME/VIEW.png, as `rig calibrate capture` writes): `view`, or the
    first that every calibrated camera has. RGB (or grey) pixels per camera."""
    from calibration.images import find_images

    found = find_images(folder)
    missing = [n for n in rig.names if n not in found.paths]
    if missing:
        raise CalibrationError(f"{folder}: no images of camera {', '.join(repr(m) for m in missing)}")
    common = [v for v in found.views if all(v in found.paths[n] for n in rig.names)]
    if view is not None and view not in common:
        raise CalibrationError(f"{folder}: no view {view!r} that every camera has (views: {', '.join(common[:8]) or 'none'}"
                               f"{' ...' if len(common) > 8 else ''})")
    if not common:
        raise CalibrationError(f"{folder}: no view that every camera ({', '.join(rig.names)}) has")
    chosen = view or common[0]
    out = {}
    for n in rig.names:
        path = found.paths[n][chosen]
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CalibrationError(f"{path}: cannot read this image (corrupt or not an image)")
        out[n] = cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if img.ndim == 3 else img
    return out


def export_nerfstudio(rig: RigCalibration, out: Path, images: dict[str, np.ndarray] | None = None) -> list[Path]:
    """nerfstudio transforms.json, one frame per camera, per-frame OPENCV intrinsics, and the images
    it points at (images/NAME.png), so that `ns-train` can start from the folder.

    transform_matrix is camera-to-world in nerfstudio's (OpenGL) camera axes: x right, y up, z backwards.
    """
    if images is None:
        raise CalibrationError("a nerfstudio export needs one image per camera (a take's set or a calibration view)")
    check_images(rig, images, "nerfstudio export")
    path = out / "transforms.json"
    frames = []
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    models = {c.model for c in rig.cameras}
    if len(models) > 1:
        raise CalibrationError("nerfstudio takes one camera model per folder; this rig mixes pinhole and fisheye lenses")
    camera_model = "OPENCV_FISHEYE" if models == {"fisheye"} else "OPENCV"
    for c in rig.cameras:
        c2w = np.eye(4)
        c2w[:3, :3] = c.R.T
        c2w[:3, 3] = c.center
        d = lens.coefficients(c.model, c.dist)
        terms = dict(zip(lens.DIST_NAMES[c.model], (float(x) for x in d)))
        frames.append({
            "file_path": f"images/{c.name}.png",
            "transform_matrix": (c2w @ flip).tolist(),
            "camera_model": camera_model,
            "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx + 0.5, "cy": c.cy + 0.5, "w": c.width, "h": c.height,
            **terms,
        })
    written = write_images(out, rig, images)
    atomic_write_bytes(path, (json.dumps({"camera_model": camera_model, "frames": frames}, indent=2) + "\n").encode())
    return [path, *written]


def _quaternion(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix, w >= 0."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = np.array([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = np.array([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = np.array([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def export_colmap(rig: RigCalibration, out: Path, images: dict[str, np.ndarray] | None = None) -> list[Path]:
    """COLMAP text model: cameras.txt (FULL_OPENCV, or OPENCV_FISHEYE for a fisheye lens), images.txt
    (world-to-camera quaternion, NAME.png),
    and an empty points3D.txt so COLMAP reads the folder as a model; with `images`, also the images
    it names (images/NAME.png, COLMAP's --image_path)."""
    if images is not None:
        check_images(rig, images, "colmap export")
    cams = out / "cameras.txt"
    imgs = out / "images.txt"
    pts = out / "points3D.txt"
    clines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
              f"# Number of cameras: {len(rig.cameras)}"]
    ilines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
              "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {len(rig.cameras)}, mean observations per image: 0"]
    for i, c in enumerate(rig.cameras, start=1):
        if c.model == "fisheye":
            model, params = "OPENCV_FISHEYE", [c.fx, c.fy, c.cx + 0.5, c.cy + 0.5, *lens.coefficients("fisheye", c.dist)]
        else:
            d = _dist5(c)
            model, params = "FULL_OPENCV", [c.fx, c.fy, c.cx + 0.5, c.cy + 0.5, d[0], d[1], d[2], d[3], d[4], 0.0, 0.0, 0.0]
        clines.append(f"{i} {model} {c.width} {c.height} " + " ".join(repr(float(p)) for p in params))
        q = _quaternion(c.R)
        ilines.append(f"{i} " + " ".join(repr(float(x)) for x in (*q, *c.t)) + f" {i} {c.name}.png")
        ilines.append("")
    cams.write_text("\n".join(clines) + "\n")
    imgs.write_text("\n".join(ilines) + "\n")
    pts.write_text("# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n# Number of points: 0\n")
    return [cams, imgs, pts] + (write_images(out, rig, images) if images is not None else [])


EXPORTERS: dict[str, Callable[..., list[Path]]] = {
    "opencv": export_opencv,
    "easymocap": export_easymocap,
    "anipose": export_anipose,
    "nerfstudio": export_nerfstudio,
    "colmap": export_colmap,
}


def export(rig: RigCalibration, fmt: str, out: str | Path, images: dict[str, np.ndarray] | None = None) -> list[Path]:
    """Write `rig` in format `fmt` into folder `out`; returns the files written. `images` (camera name
    -> pixels at the calibrated size) are the images a nerfstudio (required) or COLMAP export points at."""
    if fmt not in EXPORTERS:
        raise CalibrationError(f"unknown export format {fmt!r} (allowed: {', '.join(FORMATS)})")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CalibrationError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    return EXPORTERS[fmt](rig, out, images=images)
