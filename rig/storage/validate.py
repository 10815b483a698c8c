"""`rig record validate`: is every indexed frame whole; count sets, frames, gaps, lost frames and skew.

Lost frames are gaps in a camera's frame ids: exposures the camera made that are not in the take,
whatever lost them (a link down, a stalled daemon whose ring was overwritten, a full queue). A take
can miss them with no set missing at all: a gap in every camera at once leaves no set to mark.

Two timing figures, kept apart because they measure different things:
- exposure skew (`skew_us`): how far apart the cameras' exposures of one set started, by each
  hardware-triggered camera's own clock against the pulse train (a line fitted per camera from
  device time to pulse index; the spread of the residuals across cameras). Each clock is fitted on
  its own, so a constant difference in trigger latency between two cameras does not show: that is
  a property of the cameras, measured once (`rig sync check` against a flash), not of the take;
- arrival spread (`arrival_spread_us`): how far apart the set's frames reached the host, which adds
  transfer and driver delays and says nothing about when the pictures were taken.

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
    frames_lost: dict[str, int] = field(default_factory=dict)  # gaps in each camera's frame ids
    id_gaps: dict[str, list] = field(default_factory=dict)  # each gap: {"set", "after_id", "next_id", "lost"}
    skew_us: dict[str, float] = field(default_factory=dict)  # exposure skew by the device clocks (hardware-triggered cameras)
    arrival_spread_us: dict[str, float] = field(default_factory=dict)  # host arrival times
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
            "frames_lost": self.frames_lost,
            "id_gaps": self.id_gaps,
            "skew_us": self.skew_us,
            "arrival_spread_us": self.arrival_spread_us,
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
    v.frames_lost = {c.name: 0 for c in meta.cameras}
    v.id_gaps = {c.name: [] for c in meta.cameras}
    entries = {c.name: c for c in meta.cameras}
    last_id: dict[str, int] = {}
    pulses: dict[str, list] = {c.name: [] for c in meta.cameras if c.trigger == "hardware"}  # (trigger, device ns)
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
            _follow_ids(v, cam, rec.get("frame_id"), row["set"], last_id)
            if cam in pulses and row.get("trigger") is not None and rec.get("device_ts_ns") is not None:
                pulses[cam].append((row["trigger"], rec["device_ts_ns"]))
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
        v.arrival_spread_us = _spread(np.array(skews))
    exposure = exposure_skew_us(pulses)
    if len(exposure):
        v.skew_us = _spread(exposure)
    lost = {cam: n for cam, n in v.frames_lost.items() if n}
    if lost:
        v.warnings.append("frames lost (gaps in the cameras' frame ids): " + ", ".join(
            f"{cam} {n} in {len(v.id_gaps[cam])} gap{'s' if len(v.id_gaps[cam]) > 1 else ''} (first after set {v.id_gaps[cam][0]['set']})"
            for cam, n in lost.items()))
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


def _spread(values: np.ndarray) -> dict[str, float]:
    return {"p50": float(np.percentile(values, 50)), "p99": float(np.percentile(values, 99)), "max": float(values.max())}


def _follow_ids(v: Validation, cam: str, frame_id, set_number: int, last_id: dict[str, int]) -> None:
    """Count a forward jump in `cam`'s frame ids as lost frames; a backward one is a camera that
    started counting again (it reopened), not a loss."""
    if not isinstance(frame_id, int):
        return
    before = last_id.get(cam)
    if before is not None and frame_id > before + 1:
        n = frame_id - before - 1
        v.frames_lost[cam] += n
        v.id_gaps[cam].append({"set": set_number, "after_id": before, "next_id": frame_id, "lost": n})
    last_id[cam] = frame_id


def exposure_skew_us(pulses: dict[str, list]) -> np.ndarray:
    """Per set, how far apart the hardware-triggered cameras' exposures started (us), by their own
    clocks: each camera's device timestamps against the pulse indices they answered, fitted with a
    line (its clock's offset and rate: two clocks are never compared directly), and the spread of
    the residuals across the cameras of each pulse. Needs two such cameras with 3 frames each."""
    residual: dict[str, dict[int, float]] = {}
    for cam, samples in pulses.items():
        if len(samples) < 3:
            continue
        k = np.array([p for p, _ in samples], dtype=np.float64)
        t = np.array([d for _, d in samples], dtype=np.float64)
        if np.ptp(k) == 0:
            continue
        t0 = t[0]
        fit = np.polyfit(k - k[0], t - t0, 1)
        r = (t - t0) - np.polyval(fit, k - k[0])
        # a frame far off the line (a misassigned one) must not tilt it: fit again without them
        mad = float(np.median(np.abs(r - np.median(r))))
        keep = np.abs(r - np.median(r)) <= max(10.0 * mad, 1000.0)
        if keep.sum() >= 3 and not keep.all():
            fit = np.polyfit(k[keep] - k[0], t[keep] - t0, 1)
            r = (t - t0) - np.polyval(fit, k - k[0])
        residual[cam] = dict(zip(k.astype(int).tolist(), (r / 1e3).tolist()))
    if len(residual) < 2:
        return np.array([])
    out = []
    for pulse in sorted(set().union(*residual.values())):
        vals = [res[pulse] for res in residual.values() if pulse in res]
        if len(vals) > 1:
            out.append(max(vals) - min(vals))
    return np.array(out)
