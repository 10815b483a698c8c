"""`rig record repair`: make a damaged take readable again, keeping every good set.

Only the index is rewritten; no image is touched. Line by line:
- a line that is not a whole index row (garbage, a torn last row) is dropped: it names no frame
  that could be read back anyway;
- a frame whose image is missing, torn (wrong size; a PNG without its end chunk), has a damaged header, or whose record is
  malformed, is marked missing (`null`) in its set, as the recorder marks a dropped frame; the set
  and its other cameras' frames are kept; with `check_pixels` (`--pixels`) so is one whose image
  does not decode (a PNG damaged inside: its chunks' checksums fail);
- a camera the sequence does not record (not in sequence.json) is removed from its row, and a
  recorded camera absent from a row is added to it as missing.
Every other line is kept byte for byte. Before the index is replaced (atomically), the original is
kept beside it as `index.before-repair-<UTC time>.jsonl`, a new name each time, so no earlier backup is
ever overwritten. A take with nothing to repair is left as it is (repairing twice changes nothing).
"""
from __future__ import annotations

import datetime as _dt
import json
import os
from pathlib import Path, PurePosixPath
from typing import Any, Optional

from common.files import atomic_write_bytes
from rig.storage.layout import INDEX, CameraEntry, ImageError, SequenceError, SequenceMeta

BACKUP_PREFIX = "index.before-repair-"


def repair(root: str | Path, check_pixels: bool = False) -> dict[str, Any]:
    """Repair `root`'s index as the module says. Returns what `rig record repair --json` prints:
    kept_sets, dropped_lines, frames_marked_missing, backup (None when nothing changed), and
    `dropped`, one entry per change: what (line | frame | camera), line, set, camera, file, reason."""
    root = Path(root)
    meta = SequenceMeta.load(root)
    entries = {c.name: c for c in meta.cameras}
    index = root / INDEX
    try:
        data = index.read_bytes()
    except FileNotFoundError:
        raise SequenceError(f"{root}: not a sequence ({INDEX} missing)") from None
    out: list[bytes] = []
    changes: list[dict[str, Any]] = []
    kept = 0
    for line_no, line, whole in _lines(data):
        row, why = _parse(line, whole)
        if why is not None:
            changes.append({"what": "line", "line": line_no, "bytes": len(line) + whole, "reason": why})
            continue
        row_changes = _repair_row(root, entries, row, line_no, check_pixels)
        changes.extend(row_changes)
        out.append(json.dumps(row, separators=(",", ":")).encode() + b"\n" if row_changes else line + b"\n")
        kept += 1
    new = b"".join(out)
    backup: Optional[Path] = None
    if new != data:
        backup = _keep_original(root, data)
        try:
            atomic_write_bytes(index, new)
        except OSError as exc:
            raise SequenceError(f"{index}: could not write the repaired index ({exc.strerror}); "
                                f"the original is unchanged (a copy is in {backup.name})") from None
    dropped_lines = sum(c["what"] == "line" for c in changes)
    return {
        "path": str(root),
        "changed": backup is not None,
        "sets_before": kept + dropped_lines,
        "kept_sets": kept,
        "dropped_lines": dropped_lines,
        "frames_marked_missing": sum(c["what"] == "frame" for c in changes),
        "removed_bytes": len(data) - len(new),
        "backup": str(backup) if backup is not None else None,
        "dropped": changes,
    }


def _lines(data: bytes):
    """(1-based line number, line without its newline, whether it ended with a newline)."""
    pos, n = 0, 0
    while pos < len(data):
        n += 1
        nl = data.find(b"\n", pos)
        if nl < 0:
            yield n, data[pos:], False
            return
        yield n, data[pos:nl], True
        pos = nl + 1


def _parse(line: bytes, whole: bool) -> tuple[Optional[dict], Optional[str]]:
    """The row of a line, or why the line is dropped."""
    if not whole:
        try:
            json.loads(line)
        except ValueError:
            return None, "torn last line (the recording was interrupted mid-row)"
        # a whole row that lost only its newline: kept (the rewrite adds the newline)
    if not line.strip():
        return None, "empty line"
    try:
        row = json.loads(line)
    except ValueError:  # JSON and UTF-8 errors alike
        return None, "not JSON (corrupt line)"
    if not isinstance(row, dict) or not isinstance(row.get("set"), int) or not isinstance(row.get("frames"), dict):
        return None, "not an index row (no set number or frames)"
    return row, None


def _repair_row(root: Path, entries: dict[str, CameraEntry], row: dict, line_no: int,
                check_pixels: bool = False) -> list[dict[str, Any]]:
    """Fix one row in place; returns its changes."""
    changes = []
    frames = row["frames"]
    for cam in list(frames):
        if cam not in entries:
            del frames[cam]
            changes.append({"what": "camera", "line": line_no, "set": row["set"], "camera": cam,
                            "reason": "a camera this sequence does not record (not in sequence.json): removed from the set"})
            continue
        rec = frames[cam]
        if rec is None:
            continue
        why = frame_damage(root, entries[cam], rec)
        if why is None and check_pixels:
            why = _does_not_decode(root / rec["file"], entries[cam])
        if why is not None:
            frames[cam] = None
            changes.append({"what": "frame", "line": line_no, "set": row["set"], "camera": cam,
                            "file": rec.get("file") if isinstance(rec, dict) else None, "reason": why})
    for cam in entries:
        if cam not in frames:
            frames[cam] = None
            changes.append({"what": "frame", "line": line_no, "set": row["set"], "camera": cam, "file": None,
                            "reason": "absent from the row: marked missing"})
    return changes


def frame_damage(root: Path, entry: CameraEntry, rec: Any) -> Optional[str]:
    """Why one frame record cannot be read back, or None when its image is whole."""
    if not (isinstance(rec, dict) and isinstance(rec.get("file"), str) and isinstance(rec.get("host_ts_ns"), int)):
        return "malformed frame record"
    rel = PurePosixPath(rec["file"])
    if rel.is_absolute() or ".." in rel.parts:
        return f"{rec['file']} is outside the sequence folder"
    path = root / rel
    try:
        if path.suffix != entry.suffix:
            return f"not a {entry.suffix} image (the camera is recorded as {entry.codec})"
        return entry.damage(path)
    except FileNotFoundError:
        return "image file missing"
    except OSError as exc:
        return f"image cannot be read ({exc.strerror})"
    return None


def _does_not_decode(path: Path, entry: CameraEntry) -> Optional[str]:
    """Why a whole-looking image cannot be decoded, or None when it decodes."""
    from rig.storage.png import quiet_decoder

    try:
        with quiet_decoder():
            entry.read(path)
    except ImageError:
        return "image does not decode (damaged inside)"
    except OSError as exc:
        return f"image cannot be read ({exc.strerror})"
    return None


def _keep_original(root: Path, data: bytes, prefix: str = BACKUP_PREFIX, doing: str = "repairing") -> Path:
    """Write the index as it was to a new backup file beside it (never over an earlier one)."""
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    for n in range(1, 1000):
        path = root / f"{prefix}{stamp}{'' if n == 1 else f'-{n}'}.jsonl"
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            continue
        except OSError as exc:
            raise SequenceError(f"{root}: cannot keep a copy of the index before {doing} it ({exc.strerror}); nothing was changed") from None
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        except OSError as exc:
            os.close(fd)
            path.unlink(missing_ok=True)
            raise SequenceError(f"{path}: cannot keep a copy of the index before {doing} it ({exc.strerror}); nothing was changed") from None
        os.close(fd)
        return path
    raise SequenceError(f"{root}: too many index backups from this second; nothing was changed")


keep_index_copy = _keep_original  # also used by `rig record align` (rig.storage.align)
