"""On-disk cache of the simulated cameras' pre-rendered loops.

Rendering a camera's loop takes seconds (every frame is rendered several times over the exposure
for motion blur), and every start of a simulated rig needs it; the loop is a pure function of the
scene, the camera, the sensor options, the exposure and the code, so it is rendered once and kept.

A cache file is named by a hash of everything that shapes the loop (`loop_key`), including a hash
of the simulator's own source (any change of the renderer or the sensor model re-renders) and the
numpy and OpenCV versions. It is an uncompressed .npz (loading must be fast: it is the warm start)
written atomically; it also holds the full key, checked on load with every array's shape and type,
and the zip's checksums catch a damaged file. A file that does not load for any reason is ignored
(the loop is rendered and the file replaced), never an error.

Where: $RIG_CACHE_DIR/sim-loops, else $XDG_CACHE_HOME/rig/sim-loops, else ~/.cache/rig/sim-loops.
How much: at most $RIG_SIM_LOOP_CACHE_MB megabytes (default 2048; 0 turns the cache off); the
least recently used files go first.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np

from common.files import atomic_path, user_cache_dir

FORMAT_VERSION = 1  # bump when the file layout or what a loop holds changes
DEFAULT_MAX_MB = 2048
ARRAYS = ("frames", "clean", "sigma16")  # what a loop holds, all uint8 (loop_frames, H, W, 3)
STALE_PART_S = 3600.0  # a half-written file this old was left by a process that died

_ROOT = Path(__file__).resolve().parent.parent
# What the loop's pixels depend on: the simulator package, and the camera and board models it uses.
_SOURCES = ("simulator", "calibration/camera.py", "calibration/boards.py")


def cache_dir() -> Path:
    return user_cache_dir("sim-loops")


def max_bytes() -> int:
    """The size bound of the cache folder; 0 = no cache. A malformed setting keeps the default."""
    try:
        mb = float(os.environ.get("RIG_SIM_LOOP_CACHE_MB", DEFAULT_MAX_MB))
    except ValueError:
        mb = DEFAULT_MAX_MB
    return max(0, int(mb * 1e6))


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """A hash of the source that renders and digitises a loop, and of the libraries' versions."""
    h = hashlib.sha256(f"format {FORMAT_VERSION} numpy {np.__version__} opencv {cv2.__version__}".encode())
    files = []
    for rel in _SOURCES:
        p = _ROOT / rel
        files.extend(sorted(p.rglob("*.py")) if p.is_dir() else [p])
    for f in files:
        h.update(str(f.relative_to(_ROOT)).encode())
        h.update(f.read_bytes() if f.is_file() else b"(absent)")
    return h.hexdigest()


def scene_fingerprint(scene) -> Optional[dict[str, Any]]:
    """What a Scene is built from (its content is a pure function of this), or None for an object
    this module does not know how to describe (then its loop is not cached)."""
    if getattr(scene, "board_path", None) is not None:
        return None  # a board moved by a function (a calibration session) is not described by these fields
    try:
        board = scene.board
        return {"seed": int(scene.seed), "name": str(scene.name), "motion": str(scene.motion),
                "people": len(scene.persons), "board": None if board is None else board.to_dict(),
                "board_period": float(scene.board_period)}
    except AttributeError:
        return None


def loop_key(description: dict[str, Any]) -> str:
    """The canonical text of a loop's description (JSON, sorted keys) with the code version."""
    return json.dumps({"code": code_version(), **description}, sort_keys=True, default=str)


def _file_of(key: str, folder: Path) -> Path:
    return folder / (hashlib.sha256(key.encode()).hexdigest()[:40] + ".npz")


def load(key: str, shape: tuple[int, ...], folder: Optional[Path] = None) -> Optional[dict[str, np.ndarray]]:
    """The cached loop of `key` (arrays of `shape`, uint8), or None when absent or unusable."""
    if max_bytes() == 0:
        return None
    path = _file_of(key, folder or cache_dir())
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None  # a hash collision or a foreign file: render
            arrays = {name: z[name] for name in ARRAYS}
    except Exception:  # absent, truncated, damaged, not a zip: any of them means render it again
        return None
    if any(a.shape != tuple(shape) or a.dtype != np.uint8 for a in arrays.values()):
        return None
    try:
        os.utime(path)  # least recently used goes first
    except OSError:
        pass
    return arrays


def store(key: str, arrays: dict[str, np.ndarray], folder: Optional[Path] = None) -> Optional[Path]:
    """Keep a rendered loop; returns its file, or None when the cache is off or cannot be written
    (a full disk or a read-only home only costs the next start a render)."""
    limit = max_bytes()
    if limit == 0:
        return None
    folder = folder or cache_dir()
    path = _file_of(key, folder)
    try:
        with atomic_path(path, make_parents=True) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, key=np.array(key), **{name: arrays[name] for name in ARRAYS})
        evict(folder, limit, keep=path)
    except OSError:
        return None
    return path


def evict(folder: Path, limit: int, keep: Optional[Path] = None) -> list[Path]:
    """Remove the least recently used loops until the folder holds at most `limit` bytes (never
    `keep`, the file just written), and half-written files that a dead process left behind."""
    removed = []
    now = time.time()
    entries = []
    for p in folder.glob("*.npz"):
        try:
            st = p.stat()
        except OSError:
            continue  # another process removed it
        if p.name.startswith("."):
            if now - st.st_mtime > STALE_PART_S:
                p.unlink(missing_ok=True)
                removed.append(p)
            continue
        entries.append((st.st_mtime, st.st_size, p))
    total = sum(size for _, size, _ in entries)
    for _, size, p in sorted(entries, key=lambda e: e[0]):
        if total <= limit:
            break
        if keep is not None and p == keep:
            continue
        try:
            p.unlink()
        except OSError:
            continue
        total -= size
        removed.append(p)
    return removed
