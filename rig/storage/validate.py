"""`rig record validate`: is every indexed frame whole; count sets, frames, gaps and skew.

`rig record repair` is rig/storage/repair.py.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from rig.storage.index import scan_index
from rig.storage.layout import CALIBRATION_COPY, INDEX, CameraEntry, ImageError, SequenceMeta
from rig.storage.media import media_problems
from rig.storage.png import quiet_decoder
from rig.storage.repair import frame_damage


@dataclass
class Validation:
    root: Path
    sets: int = 0
    complete_sets: int = 0
    frames: dict[str, int] = field(default_factory=dict)
    missing: dict[str, int] = field(default_factory=dict)
    gaps: int = 0  # trigger indices skipped between consecutive sets
    skew_us: dict[str, float] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    torn_tail: bool = False
    readable_sets: int = 0
    calibrated: bool = False
    duration_s: float = 0.0

    @property
    def readable(self) -> bool:
        return not self.errors

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": str(self.root),
            "readable": self.readable,
            "sets": self.sets,
            "complete_sets": self.complete_sets,
            "incomplete_sets": self.sets - self.complete_sets,
            "readable_sets": self.readable_sets,
            "frames": self.frames,
            "missing": self.missing,
            "gaps": self.gaps,
            "skew_us": self.skew_us,
            "duration_s": round(self.duration_s, 3),
            "torn_tail": self.torn_tail,
            "calibrated": self.calibrated,
            "errors": self.errors,
            "warnings": self.warnings,
        }


def frame_problem(root: Path, entries: dict[str, CameraEntry], row: dict, cam: str, rec: Optional[dict]) -> Optional[str]:
    """What is wrong with one frame record of an index row, or None. A null record (a marked gap) is fine."""
    if cam not in entries:
        return f"set {row['set']}: unknown camera '{cam}'"
    if rec is None:
        return None
    # what `rig record repair` would mark missing: the same test (size, header, a file in the take)
    damage = frame_damage(root, entries[cam], rec)
    if damage is None:
        return None
    name = rec.get("file") if isinstance(rec, dict) else None
    return f"set {row['set']}: {name or cam}: {damage}"


def check_whole(roots: list[str | Path], what: str = "nothing was trained or written") -> None:
    """Every indexed frame of every take present and whole (its size and header, as `validate`
    without pixels); SequenceError (one line) naming the first damaged one otherwise: a damaged take
    is refused before a run starts, not at the first batch that reads the frame."""
    from rig.storage.layout import SequenceError

    for root in roots:
        found = validate(root)
        if found.errors:
            more = len(found.errors) - 1
            raise SequenceError(f"{root}: damaged ({found.errors[0]}{f'; and {more} more' if more else ''}); `rig record validate {root}` "
                                f"lists every one, `rig record repair {root}` keeps every good set ({what})")


def validate(root: str | Path, check_pixels: bool = False) -> Validation:
    """Check every indexed frame is present and whole; count sets, frames, gaps, skew."""
    root = Path(root)
    v = Validation(root)
    meta = SequenceMeta.load(root)
    scan = scan_index(root)
    v.torn_tail = scan.torn_tail
    if scan.torn_tail:
        v.warnings.append(f"{INDEX}: torn last row (recording was interrupted); `rig record repair` removes it")
    for ln in scan.corrupt_lines:
        v.errors.append(f"{INDEX}: line {ln} is corrupt")
    v.frames = {c.name: 0 for c in meta.cameras}
    v.missing = {c.name: 0 for c in meta.cameras}
    entries = {c.name: c for c in meta.cameras}
    skews = []
    last_trigger = None
    first_ts = last_ts = None
    first_bad_set = None
    for row in scan.rows:
        v.sets += 1
        complete = True
        ts = []
        row_ok = True
        for cam, rec in row["frames"].items():
            problem = frame_problem(root, entries, row, cam, rec)
            if problem is None and rec is not None and check_pixels:
                try:
                    with quiet_decoder():
                        entries[cam].read(root / rec["file"])
                except ImageError as exc:
                    problem = str(exc)
            if problem is not None:
                v.errors.append(problem)
                row_ok = False
                continue
            if rec is None:
                complete = False
                v.missing[cam] += 1
                continue
            v.frames[cam] += 1
            ts.append(rec["host_ts_ns"])
        if not row_ok and first_bad_set is None:
            first_bad_set = v.sets - 1
        if complete:
            v.complete_sets += 1
        if len(ts) > 1:
            skews.append((max(ts) - min(ts)) / 1e3)
        if ts:
            first_ts = min(ts) if first_ts is None else first_ts
            last_ts = max(ts)
        trig = row.get("trigger")
        if trig is not None and last_trigger is not None and trig > last_trigger + 1:
            v.gaps += trig - last_trigger - 1
        if trig is not None:
            last_trigger = trig
    v.readable_sets = v.sets if first_bad_set is None else first_bad_set
    if skews:
        s = np.array(skews)
        v.skew_us = {"p50": float(np.percentile(s, 50)), "p99": float(np.percentile(s, 99)), "max": float(s.max())}
    if first_ts is not None and last_ts is not None:
        v.duration_s = (last_ts - first_ts) / 1e9
    cal = root / CALIBRATION_COPY
    if cal.exists():
        from calibration.camera import CalibrationError, RigCalibration

        try:
            RigCalibration.load(cal)
            v.calibrated = True
        except CalibrationError as exc:
            v.errors.append(str(exc))
    media_errors, media_warnings = media_problems(root)  # videos of cameras that recorded to their cards
    v.errors.extend(media_errors)
    v.warnings.extend(media_warnings)
    if v.sets == 0:
        v.warnings.append("no frame sets recorded")
    return v
