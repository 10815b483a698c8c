"""Where commands write: checked before the work starts, so that a mistyped or unwritable output
costs nothing and never loses a result, and recorded files are never overwritten.

All raise `ConfigError` (exit 2: the output path is input the user gave).
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from rig.errors import ConfigError


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _check_folder_writable(folder: Path, what: Path) -> None:
    """Create nothing; try a temporary file in the nearest existing folder of `folder`."""
    base = _nearest_existing(folder)
    if not base.is_dir():
        raise ConfigError(f"{what}: {base} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=base):
            pass
    except OSError as exc:
        raise ConfigError(f"{what}: cannot write in {base} ({exc.strerror or exc})") from None


def output_file(path: str | os.PathLike, *, overwrite: bool = True) -> Path:
    """A file the command will write (a calibration, a model, a PNG): its folder must be writable
    (it is created later if missing); with overwrite=False an existing file is refused."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder; name a file")
    if path.exists() and not overwrite:
        raise ConfigError(f"{path}: already exists; choose a new name (nothing was overwritten)")
    _check_folder_writable(path.parent, path)
    return path


def new_output_folder(path: str | os.PathLike) -> Path:
    """A folder the command fills with recorded data: it must not exist yet or be empty, and its
    parent must be writable. Recorded frames are never overwritten or appended to."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise ConfigError(f"{path}: is a file; name a new folder")
        if any(path.iterdir()):
            raise ConfigError(f"{path}: folder is not empty; choose a new folder (nothing was overwritten)")
    _check_folder_writable(path, path)
    return path


def output_folder(path: str | os.PathLike) -> Path:
    """A folder the command writes files into (exports): may exist; must be writable."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{path}: is a file; name a folder")
    _check_folder_writable(path, path)
    return path
