"""On-disk cache of board detections, so that `rig calibrate run` run again on the same images (with
other lens models, held intrinsics, priors, another reference camera) does not detect them again.

Detection is most of a calibration's time (a ChArUco board in 84 real images: 23 of 26 s). What it
finds in an image is a pure function of the image's bytes, the board and the detector's code, so
an entry is named by a hash of all three (the code by a hash of the modules that detect, and the
OpenCV version). An entry holds the corner ids and points, or that the board was not found. It is
written atomically; an entry that does not load for any reason is ignored and detected again,
never an error.

Where: $RIG_CACHE_DIR/detections, else $XDG_CACHE_HOME/rig/detections, else ~/.cache/rig/detections.
RIG_DETECTION_CACHE=0 turns it off. Entries are small (a few kB each).
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from calibration.detect import Corners
from common.files import atomic_path, user_cache_dir

FORMAT_VERSION = 1
_ROOT = Path(__file__).resolve().parent.parent
_SOURCES = ("calibration/detect.py", "calibration/boards.py", "calibration/detection_cache.py")
NOT_FOUND = "not found"


def cache_dir() -> Path:
    return user_cache_dir("detections")


def enabled() -> bool:
    return os.environ.get("RIG_DETECTION_CACHE", "1").strip() not in ("0", "no", "off", "false")


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    h = hashlib.sha256(f"format {FORMAT_VERSION} opencv {cv2.__version__} numpy {np.__version__}".encode())
    for rel in _SOURCES:
        p = _ROOT / rel
        h.update(rel.encode())
        h.update(p.read_bytes() if p.is_file() else b"(absent)")
    return h.hexdigest()


def board_key(board) -> str:
    """What of the board shapes the detection: its whole description."""
    return hashlib.sha256(json.dumps(board.to_dict(), sort_keys=True, default=str).encode()).hexdigest()


def entry_key(image_bytes: bytes, board_hash: str) -> str:
    h = hashlib.sha256(code_version().encode())
    h.update(board_hash.encode())
    h.update(hashlib.sha256(image_bytes).digest())
    return h.hexdigest()


def _path(key: str) -> Path:
    return cache_dir() / key[:2] / f"{key}.npz"


def load(key: str) -> tuple[bool, Optional[Corners]]:
    """(hit, corners): corners None on a hit means the board is not in the image."""
    path = _path(key)
    try:
        with np.load(path, allow_pickle=False) as f:
            if str(f["key"]) != key:
                return False, None
            if str(f["status"]) == NOT_FOUND:
                return True, None
            ids = np.asarray(f["ids"], dtype=np.int64)
            points = np.asarray(f["points"], dtype=np.float64)
    except Exception:  # noqa: BLE001 - absent, partial or damaged: detect again
        return False, None
    if ids.ndim != 1 or points.shape != (len(ids), 2):
        return False, None
    return True, Corners(ids, points)


def store(key: str, corners: Optional[Corners]) -> None:
    path = _path(key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                if corners is None:
                    np.savez(f, key=np.array(key), status=np.array(NOT_FOUND))
                else:
                    np.savez(f, key=np.array(key), status=np.array("found"), ids=np.asarray(corners.ids, np.int64),
                             points=np.asarray(corners.points, np.float64))
    except OSError:
        pass  # a cache that cannot be written (read-only home, full disk) only costs time


def detect_cached(detect: Callable[[], Optional[Corners]], image_bytes: bytes, board_hash: str) -> Optional[Corners]:
    """`detect()`'s result for the image whose file holds `image_bytes`, from the cache when it was
    found before (for the board whose `board_key` is `board_hash`); a new result is kept."""
    if not enabled():
        return detect()
    key = entry_key(image_bytes, board_hash)
    hit, found = load(key)
    if not hit:
        found = detect()
        store(key, found)
    return found
