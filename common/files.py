"""Atomic file writes: a reader (or a crash) never sees a half-written file.

The data goes to a temporary file beside the target, is flushed to the disk, and is renamed over the
target in one step; on any failure the temporary file is removed and the target is left as it was.
"""
from __future__ import annotations

import json
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator


def temporary_beside(path: Path) -> Path:
    """The temporary name used while `path` is written: same folder (so the rename is atomic), same
    suffix (writers such as cv2.imwrite choose the format by it)."""
    return path.with_name(f".{path.stem}.part{path.suffix}")


@contextmanager
def atomic_path(path: str | os.PathLike, *, make_parents: bool = False) -> Iterator[Path]:
    """Yield a temporary path to write; when the block ends without an exception it replaces `path`.

    The writer inside the block may be any library that takes a file name (torch.save, onnx.save,
    cv2.imwrite). The file is fsynced before the rename and the folder after it.
    """
    path = Path(path)
    if make_parents:
        path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_beside(path)
    try:
        yield tmp
        fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, make_parents: bool = False) -> None:
    with atomic_path(path, make_parents=make_parents) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)


def atomic_write_json(path: str | os.PathLike, obj: Any, *, make_parents: bool = False, default=None) -> None:
    """JSON with two-space indent and a final newline, written atomically."""
    text = json.dumps(obj, indent=2, default=default) + "\n"
    atomic_write_bytes(path, text.encode(), make_parents=make_parents)


def fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # some filesystems do not open folders; the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def user_cache_dir(name: str) -> Path:
    """The folder of one of the product's on-disk caches: $RIG_CACHE_DIR/NAME, else
    $XDG_CACHE_HOME/rig/NAME, else ~/.cache/rig/NAME."""
    base = os.environ.get("RIG_CACHE_DIR")
    if base:
        return Path(base) / name
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "rig" / name
