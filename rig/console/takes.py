"""Takes as the console names, notes and lists them (the folders `rig record` writes under the rig's storage).

- Names: `take-YYYYMMDD-HHMMSS` by default, then `-2`, `-3`, ... if that is taken; a typed name is
  refused if a take of that name exists, or if it is not a plain folder name.
- Notes are saved as they are typed: a take that exists keeps them in its folder (`notes.txt`);
  a take not yet started keeps them as a draft (`.console/notes/NAME.txt` under the storage), moved
  into the take when it has begun. Every write is atomic: a crash keeps the last saved text.
- The list: every take folder with its validation (rig.storage.validate) and, for the takes the
  console ran, the end-of-take summary.
"""
from __future__ import annotations

import re
import threading
import time
from pathlib import Path
from typing import Optional

from common.files import atomic_path
from rig.errors import ConfigError
from rig.storage.layout import META

NOTES = "notes.txt"
DRAFTS = Path(".console") / "notes"
MAX_NOTES = 64 * 1024  # characters
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,79}")


def is_take(folder: Path) -> bool:
    return (folder / META).is_file()


def check_new(storage: Path, name) -> str:
    if not isinstance(name, str) or not NAME.fullmatch(name) or name.endswith(".") or ".." in name:
        raise ConfigError(f"take name {str(name)[:40]!r}: use 1 to 80 letters, digits, '.', '_' or '-', starting with a letter or digit")
    if (Path(storage) / name).exists() and any((Path(storage) / name).iterdir()):
        raise ConfigError(f"take {name!r} exists already in {storage}; choose another name")
    return name


def next_name(storage: Path, now: Optional[float] = None) -> str:
    """take-YYYYMMDD-HHMMSS, counted up (-2, -3, ...) while that name is taken."""
    base = time.strftime("take-%Y%m%d-%H%M%S", time.localtime(now))
    name, k = base, 1
    while (Path(storage) / name).exists():
        k += 1
        name = f"{base}-{k}"
    return name


class Notes:
    def __init__(self, storage: Path):
        self.storage = Path(storage)
        self._lock = threading.Lock()

    def _path(self, take: str) -> Path:
        check_name(take)
        folder = self.storage / take
        return folder / NOTES if is_take(folder) else self.storage / DRAFTS / f"{take}.txt"

    def save(self, take: str, text) -> Path:
        if not isinstance(text, str):
            raise ConfigError("notes must be text")
        if len(text) > MAX_NOTES:
            raise ConfigError(f"notes are limited to {MAX_NOTES} characters, got {len(text)}")
        with self._lock:
            path = self._path(take)
            with atomic_path(path, make_parents=True) as tmp:
                Path(tmp).write_text(text, encoding="utf-8")
            return path

    def read(self, take: str) -> str:
        try:
            return self._path(take).read_text(encoding="utf-8")
        except (OSError, ConfigError):
            return ""

    def settle(self, take: str) -> None:
        """Move a draft into its take once the take exists (nothing when there is none)."""
        with self._lock:
            draft = self.storage / DRAFTS / f"{take}.txt"
            folder = self.storage / take
            if draft.is_file() and is_take(folder):
                with atomic_path(folder / NOTES) as tmp:
                    Path(tmp).write_text(draft.read_text(encoding="utf-8"), encoding="utf-8")
                draft.unlink()


def check_name(take) -> str:
    if not isinstance(take, str) or not NAME.fullmatch(take) or ".." in take:
        raise ConfigError(f"take name {str(take)[:40]!r}: not a take name")
    return take


_validated: dict[tuple[str, float], dict] = {}


def listing(storage: Path, summaries: dict[str, dict], running: Optional[str] = None, limit: int = 50) -> list[dict]:
    """The newest takes first: name, validation status (cached per folder and index change; none for
    the take being written, `running`), and the end-of-take summary of those the console ran."""
    from rig.storage.layout import INDEX
    from rig.storage.validate import validate

    storage = Path(storage)
    if not storage.is_dir():
        return []
    folders = sorted((p for p in storage.iterdir() if p.is_dir() and is_take(p)), key=lambda p: p.stat().st_mtime, reverse=True)[:limit]
    out = []
    for folder in folders:
        index = folder / INDEX
        stamp = index.stat().st_mtime if index.exists() else 0.0
        key = (str(folder), stamp)
        v = _validated.get(key)
        if folder.name == running:
            v = {"state": "recording"}
        elif v is None:
            try:
                r = validate(folder)
                v = {"readable": r.readable, "sets": r.sets, "complete_sets": r.complete_sets, "errors": r.errors[:3],
                     "duration_s": round(r.duration_s, 2)}
            except Exception as exc:  # a damaged take is listed as such
                v = {"readable": False, "errors": [str(exc)]}
            _validated[key] = v
        out.append({"take": folder.name, "validation": v, "summary": summaries.get(folder.name)})
    return out


def suggest(storage: Path, last: Optional[str]) -> str:
    """The name the page offers next: the last take's name counted up (scene-07 -> scene-08, keeping
    the digits' width, past any that exist), else a timestamped one."""
    m = re.fullmatch(r"(.*?)(\d+)", last or "")
    if not m:
        return next_name(storage)
    stem, digits = m.group(1), m.group(2)
    k = int(digits)
    while True:
        k += 1
        name = f"{stem}{k:0{len(digits)}d}"
        if not (Path(storage) / name).exists() and NAME.fullmatch(name):
            return name
