"""Calibration image sets on disk and their detections.

Two layouts are read:
  DIR/CAMNAME/*.png|jpg      one folder per camera; files with the same stem are one synchronised view
  DIR/leftNN.jpg, rightNN.jpg  a stereo pair in one folder; NN (any suffix) names the view
An optional DIR/roles.json ({"left": CAMNAME, "right": CAMNAME}, written by `rig calibrate capture`)
names the stereo pair when the camera names do not.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from calibration.boards import BoardSpec, ChessboardSpec
from calibration.camera import CalibrationError
from calibration.detect import Corners, make_detector

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
_PAIR_RE = re.compile(r"^(left|right)[_-]?(.+)$", re.IGNORECASE)


def natural_key(s: str):
    """Sort key of view and camera names: "view2" before "view10"."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


@dataclass
class ImageSet:
    """Image paths per camera and view: paths[camera][view] -> Path."""

    root: Path
    paths: dict[str, dict[str, Path]]
    roles: dict[str, str] = field(default_factory=dict)  # "left"/"right" -> camera name
    empty: list[str] = field(default_factory=list)  # camera folders with no images (find_camera_images)

    @property
    def cameras(self) -> list[str]:
        return list(self.paths)

    @property
    def views(self) -> list[str]:
        return sorted({v for per in self.paths.values() for v in per})


@dataclass
class DetectionSet:
    """Everything the solver needs: image size per camera and the corners of every (camera, view)."""

    image_size: dict[str, tuple[int, int]]  # camera -> (width, height)
    corners: dict[str, dict[str, Corners]]  # camera -> view -> corners (views where the board was found)
    images_seen: dict[str, int] = field(default_factory=dict)  # camera -> number of images looked at
    sources: dict[str, dict[str, str]] = field(default_factory=dict)  # camera -> view -> file

    @property
    def cameras(self) -> list[str]:
        return list(self.image_size)

    @property
    def views(self) -> list[str]:
        return sorted({v for per in self.corners.values() for v in per})


def _is_image(p: Path) -> bool:
    # hidden files are not views: macOS leaves `._NAME.jpg` (AppleDouble metadata) beside each image
    return p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")


def find_images(root: str | Path) -> ImageSet:
    """The image set under `root` in either layout; CalibrationError when it holds none."""
    root = Path(root)
    if not root.is_dir():
        raise CalibrationError(f"{root}: no such image folder")
    paths: dict[str, dict[str, Path]] = {}
    subdirs = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and p.name != "__MACOSX")
    for d in subdirs:
        files = {f.stem: f for f in sorted(d.iterdir()) if _is_image(f)}
        if files:
            paths[d.name] = files
    empty = [d.name for d in subdirs if d.name not in paths]
    if paths and empty:
        # a camera whose folder is empty (a copy that failed, frames not yet extracted) would silently be
        # left out of the rig
        raise CalibrationError(
            f"{root}: no images in the folder of camera(s) {', '.join(repr(e) for e in empty)} (cameras with images: "
            f"{', '.join(paths)}; images are {'|'.join(s[1:] for s in IMAGE_SUFFIXES)}); add its images or move the folder out of {root}")
    paths = _match_by_number(paths)
    if not paths:
        for f in sorted(root.iterdir()):
            if not _is_image(f):
                continue
            m = _PAIR_RE.match(f.stem)
            if m:
                paths.setdefault(m.group(1).lower(), {})[m.group(2)] = f
    if not paths:
        raise CalibrationError(
            f"{root}: no calibration images (expected {root}/CAMNAME/*.png|jpg, or leftNN/rightNN images in {root})"
        )
    _check_instants_shared(root, paths)
    return ImageSet(root, paths, _read_roles(root / "roles.json", paths))


def _check_instants_shared(root: Path, paths: dict[str, dict[str, Path]]) -> None:
    """A camera none of whose images is paired with another camera's (no file name, nor the number
    that ends it, in common) cannot be placed in the rig: said before minutes of detection."""
    if len(paths) < 2:
        return
    alone = [c for c in paths if not any(set(paths[c]) & set(per) for o, per in paths.items() if o != c)]
    if alone:
        examples = ", ".join(f"{c}/{next(iter(paths[c].values())).name}" for c in paths)
        raise CalibrationError(
            f"{root}: no image of camera(s) {', '.join(repr(c) for c in alone)} is paired with another camera's "
            f"({examples}): the images of one instant need the same file name in every camera's folder, "
            "or names that end in the same number, unique within each camera")


_TRAILING_NUMBER = re.compile(r"(\d+)$")


def _match_by_number(paths: dict[str, dict[str, Path]]) -> dict[str, dict[str, Path]]:
    """Views keyed by the number that ends each file name when no two cameras share a file name
    (`back/back-02242022135219-0.jpg` and `mid/mid-02242022135221-0.jpg` are instant 0 of each
    camera), provided that number is unique within every camera; otherwise unchanged."""
    if len(paths) < 2:
        return paths
    stems = [set(per) for per in paths.values()]
    if any(a & b for i, a in enumerate(stems) for b in stems[i + 1:]):
        return paths
    numbered: dict[str, dict[str, Path]] = {}
    for cam, per in paths.items():
        keyed = {}
        for stem, path in per.items():
            m = _TRAILING_NUMBER.search(stem)
            if m is None or str(int(m.group(1))) in keyed:
                return paths
            keyed[str(int(m.group(1)))] = path
        numbered[cam] = keyed
    return numbered


def find_camera_images(root: str | Path, cameras: list[str] | None = None) -> ImageSet:
    """Each camera's own images (no instants shared between cameras): DIR/CAMNAME/* for several
    cameras, or one camera's images directly in DIR, named after DIR. `cameras`: only these."""
    root = Path(root)
    if not root.is_dir():
        raise CalibrationError(f"{root}: no such image folder")
    paths: dict[str, dict[str, Path]] = {}
    subdirs = [p for p in sorted(root.iterdir()) if p.is_dir() and not p.name.startswith(".") and p.name != "__MACOSX"]
    for d in subdirs:
        files = {f.stem: f for f in sorted(d.iterdir()) if _is_image(f)}
        if files:
            paths[d.name] = files
    # each camera is calibrated on its own: one whose folder is empty is listed, not a reason to stop
    empty = [d.name for d in subdirs if d.name not in paths] if paths else []
    if not paths:
        files = {f.stem: f for f in sorted(root.iterdir()) if _is_image(f)}
        if files:
            paths[root.resolve().name] = files
    if not paths:
        raise CalibrationError(f"{root}: no images (expected {root}/CAMNAME/*.png|jpg, or one camera's images in {root})")
    if cameras:
        missing = [c for c in cameras if c not in paths]
        if missing:
            raise CalibrationError(f"{root}: no images of camera {', '.join(repr(c) for c in missing)} (cameras: {', '.join(paths)})")
        paths = {c: paths[c] for c in cameras}
        empty = []
    return ImageSet(root, paths, empty=empty)


def _read_roles(path: Path, paths: dict) -> dict[str, str]:
    if not path.exists():
        return {}
    try:
        roles = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(roles, dict) or not all(k in ("left", "right") and isinstance(v, str) for k, v in roles.items()):
        raise CalibrationError(f'{path}: expected {{"left": CAMNAME, "right": CAMNAME}}')
    for role, name in roles.items():
        if name not in paths:
            raise CalibrationError(f"{path}: {role} camera '{name}' has no image folder")
    return roles


def read_gray(path: Path, data: bytes | None = None) -> np.ndarray:
    """The image at `path` in grey levels (decoded from `data`, its bytes, when given)."""
    if data is not None and not data:  # OpenCV asserts on an empty buffer (a file cut off, a failed copy)
        raise CalibrationError(f"{path}: cannot read this image (the file is empty)")
    try:
        if data is None:
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        else:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    except cv2.error:
        img = None
    if img is None:
        raise CalibrationError(f"{path}: cannot read this image (corrupt or not an image)")
    return img


def detect_images(
    images: ImageSet,
    board: BoardSpec,
    progress: Callable[[int, int], None] | None = None,
) -> DetectionSet:
    """Detect the board in every image. Every image of one camera must have the same size.
    What was found in an image before (same bytes, same board) comes from calibration.detection_cache."""
    from calibration import detection_cache

    detector = make_detector(board)
    board_hash = detection_cache.board_key(board)
    sizes: dict[str, tuple[int, int]] = {}
    first_file: dict[str, Path] = {}
    corners: dict[str, dict[str, Corners]] = {}
    sources: dict[str, dict[str, str]] = {}
    seen: dict[str, int] = {}
    total = sum(len(v) for v in images.paths.values())
    done = 0
    for cam, per_view in images.paths.items():
        corners[cam] = {}
        sources[cam] = {}
        seen[cam] = 0
        for view, path in sorted(per_view.items()):
            try:
                data = path.read_bytes()
            except OSError as exc:
                raise CalibrationError(f"{path}: cannot read this image ({exc.strerror or exc})") from None
            img = read_gray(path, data)
            size = (img.shape[1], img.shape[0])
            if cam not in sizes:
                sizes[cam] = size
                first_file[cam] = path
            elif size != sizes[cam]:
                raise CalibrationError(
                    f"{path}: image is {size[0]}x{size[1]} but {first_file[cam].name} of camera '{cam}' is "
                    f"{sizes[cam][0]}x{sizes[cam][1]}; all images of one camera must have the same size"
                )
            seen[cam] += 1
            found = detection_cache.detect_cached(lambda: detector(img), data, board_hash)
            if found is not None:
                corners[cam][view] = found
                sources[cam][view] = str(path)
            done += 1
            if progress:
                progress(done, total)
    if not any(corners.values()):
        tried = detector.tried() if hasattr(detector, "tried") else "the board file's board"
        check = ("cols and rows count its inner corners (a board of 10 x 7 squares has 9 x 6)" if isinstance(board, ChessboardSpec)
                 else "squares_x and squares_y count its squares, and its marker dictionary")
        raise CalibrationError(f"{images.root}: the board was not found in any of the {total} images (tried {tried}); "
                               f"check the board file: {check}")
    return DetectionSet(sizes, corners, seen, sources)
