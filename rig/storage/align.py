"""`rig record align TAKE`: put the frames of cameras that cannot be triggered on the pulses' axis.

GoPros, webcams and any camera in trigger mode `free` expose when their own clock says. During the
take the trigger board flashed its LED in their view (`rig record` fires a flash soon after the start
and one near the end: the take's `flashes.jsonl`, each with its place on the trigger axis). Here,
for each such camera:

1. the frames exposed around each flash (chosen by their own timestamps, tied to the host clock
   by the camera's least delay: on a loaded host frames arrive seconds late and in bursts, so by
   arrival the frames near a flash can be another flash's) give the flash's onset on the camera's
   own clock, to a fraction of a frame (sync.alignment.find_flash: a frame the flash starts
   halfway through is half lit);
2. the onsets and the flashes' places on the trigger axis give a line from the camera's clock to
   the axis (two flashes: its offset and its rate; one: its offset at the nominal rate);
3. every frame of the camera goes to the pulse nearest its exposure start on that line, with its
   offset from it in pulse periods (-0.5 .. 0.5), and the index is rewritten so that each set holds
   the camera's frame of its own pulse (null where the camera has none).

A camera is left as it was, with the reason as its `problem`, when a flash cannot be found, when the
flashes give a clock rate more than 1 % off (one was matched to the wrong flash), when its timestamps
go back (its stream started again during the take: two clocks), or when the flashes place its frames
only to half a pulse period or worse (frames missing around a flash): its frames are then never put
in a set that may be the wrong one.

The index as it was is kept beside it (`index.before-align-<UTC>.jsonl`, as `rig record repair`
does), and `alignment.json` records what was found per camera: the flashes' onsets and their
uncertainty, the clock rate, frames placed and moved, and the camera's latency (how long after its
exposure a frame reached the host), which live grouping can use (`latency_ms` in the config).

Cameras that recorded to their own card have no frames in the index: their downloaded videos are
aligned by the same flashes (rig.storage.align_video), each video's mapping from frame number to
trigger position going into `alignment.json` under `videos`; the index is not touched for them.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from common.files import atomic_write_bytes, atomic_write_json
from rig.storage.index import scan_index
from rig.storage.align_video import align_videos
from rig.storage.flash_fit import check_flash_shape, fit_clock, read_flashes
from rig.storage.layout import CONFIG_COPY, INDEX, SequenceError, SequenceMeta, read_image_file
from rig.storage.media import MANIFEST, MediaManifest
from rig.storage.repair import keep_index_copy
from sync.alignment import brightness_trace, find_flash
from sync.errors import SyncError

BACKUP_PREFIX = "index.before-align-"
REPORT = "alignment.json"
# Frames looked at around a flash: those exposed from BEFORE_S before it to AFTER_S after its end,
# on the host clock as the camera's least delay puts them (a GoPro's frames reach the host a few
# hundred ms after their exposure at best; AFTER_S leaves room for that and the frames after it).
BEFORE_S, AFTER_S = 0.5, 1.5
# The least delay is taken over the frames that arrived this close to the flash, so that the camera
# clock's drift against the host's over a long take does not move the window.
DELAY_SPAN_S = 60.0
# A camera whose frames the flashes place only to half a pulse period or worse is not aligned:
# any of its frames could land in a neighbouring set.
MAX_ERROR_PERIODS = 0.5


@dataclass
class CameraAlignment:
    camera: str
    flashes: list[dict[str, Any]] = field(default_factory=list)  # per flash: onset, uncertainty, frames used
    rate_ppm: Optional[float] = None  # how fast the camera's clock runs against the board's (two flashes or more)
    rate_ppm_error: Optional[float] = None  # how far rate_ppm may be off (the flashes' onset uncertainties)
    frames: int = 0  # frames of the camera in the take
    placed: int = 0  # frames that landed in a set of the take
    moved: int = 0  # of those, in another set than the live grouping put them
    latency_ms: Optional[float] = None  # median delay from exposure start to host arrival
    error_periods: Optional[float] = None  # the alignment's uncertainty, in pulse periods
    problem: Optional[str] = None  # why the camera could not be aligned (then its frames are untouched)

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items()}


def free_cameras(root: Path) -> list[str]:
    """The take's cameras that were not hardware-triggered (from its copy of the rig config)."""
    from rig.config import load_config

    config = root / CONFIG_COPY
    if not config.is_file():
        raise SequenceError(f"{root}: no {CONFIG_COPY} in the take: name the cameras to align with --camera")
    cfg = load_config(config, check_calibration=False)
    return [c.name for c in cfg.cameras if c.trigger != "hardware"]


def _camera_settings(root: Path) -> dict[str, Any]:
    from rig.config import load_config

    try:
        return {c.name: c for c in load_config(root / CONFIG_COPY, check_calibration=False).cameras}
    except Exception:  # noqa: BLE001 - a take without its config copy: nominal values
        return {}


def align(root: str | Path, cameras: Optional[Sequence[str]] = None) -> dict[str, Any]:
    """Align the take's free-running cameras (or `cameras`) and rewrite its index, and align the
    videos of its card-recording cameras (rig.storage.align_video); the report."""
    root = Path(root)
    meta = SequenceMeta.load(root)
    flashes = read_flashes(root)
    recorded = [c.name for c in meta.cameras]
    manifest = MediaManifest.load(root) if (root / MANIFEST).is_file() else None
    card = list(manifest.cameras) if manifest is not None else []
    if cameras:
        unknown = [n for n in cameras if n not in recorded and n not in card]
        if unknown:
            raise SequenceError(f"{root}: no camera {', '.join(unknown)} in the take (it has {', '.join(recorded + card)})")
        names = [n for n in cameras if n in recorded]
        video_cameras = [n for n in cameras if n in card]
    else:
        names = [n for n in free_cameras(root) if n in recorded and n not in card]
        video_cameras = card
    if not names and not video_cameras:
        raise SequenceError(f"{root}: every camera of the take was hardware-triggered: nothing to align")
    if not meta.rate_hz:
        raise SequenceError(f"{root}: the take does not say its trigger rate (sequence.json rate_hz)")
    rate_hz = float(meta.rate_hz)
    settings = _camera_settings(root)
    results = []
    backup = None
    if names:
        data = (root / INDEX).read_bytes()
        rows = scan_index(root).rows
        for name in names:
            result, placement = _align_camera(root, name, rows, flashes, rate_hz, settings.get(name))
            results.append(result)
            if placement is not None:
                _regroup(rows, name, placement, result)
        if any(r.problem is None for r in results):
            backup = keep_index_copy(root, data, BACKUP_PREFIX, "aligning")
            new = b"".join(json.dumps(r, separators=(", ", ": ")).encode() + b"\n" for r in rows)
            try:
                atomic_write_bytes(root / INDEX, new)
            except OSError as exc:
                raise SequenceError(f"{root / INDEX}: could not write the aligned index ({exc.strerror}); the original is "
                                    f"unchanged (a copy is in {backup.name})") from None
    videos = []
    if video_cameras:
        exposures = {n: settings[n].exposure_us for n in video_cameras if n in settings and settings[n].exposure_us}
        videos = align_videos(manifest, flashes, rate_hz, video_cameras, exposures)
    report = {"path": str(root), "rate_hz": rate_hz, "flashes": flashes, "backup": str(backup) if backup else None,
              "cameras": {r.camera: r.to_dict() for r in results}, "videos": [v.to_dict() for v in videos]}
    atomic_write_json(root / REPORT, report)
    return report


def _align_camera(root: Path, name: str, rows: list[dict], flashes: list[dict], rate_hz: float, cfg):
    """(CameraAlignment, {frame_id: (trigger, offset)} or None when it cannot be aligned)."""
    result = CameraAlignment(name)
    frames = {}
    for row in rows:
        rec = row["frames"].get(name)
        if rec is not None and isinstance(rec.get("device_ts_ns"), int):
            frames[int(rec["frame_id"])] = (rec, row.get("trigger"))
    result.frames = len(frames)
    if len(frames) < 3:
        result.problem = f"{len(frames)} frames with timestamps in the take: too few to align"
        return result, None
    restart = _clock_restart(frames)
    if restart is not None:
        result.problem = restart
        return result, None
    period_ns = 1e9 / rate_hz
    fps = float(getattr(cfg, "fps", 0) or rate_hz)
    exposure_ns = float(getattr(cfg, "exposure_us", 0) or 0) * 1e3 or 1e9 / fps
    device = np.array([rec["device_ts_ns"] for rec, _ in frames.values()], dtype=np.float64)
    host = np.array([rec["host_ts_ns"] for rec, _ in frames.values()], dtype=np.float64)
    files = [rec["file"] for rec, _ in frames.values()]
    points = []  # (onset on the camera's clock, place on the trigger axis, uncertainty ns)
    for f in flashes:
        lo, hi = f["host_ns"] - BEFORE_S * 1e9, f["host_ns"] + f["ms"] * 1e6 + AFTER_S * 1e9
        # Not by arrival: on a loaded host a stream's frames come seconds late and in bursts, so the
        # frames arriving around a flash can be another flash's, and its own may arrive after the
        # window. A frame never arrives before it is exposed, so the least delay (host minus camera
        # time) of the frames around the flash ties the camera's clock to the host's.
        around = np.abs(host - f["host_ns"]) <= DELAY_SPAN_S * 1e9
        least = float(np.min((host - device)[around] if around.any() else host - device))
        pick = np.flatnonzero((device + least >= lo) & (device + least <= hi))
        near = sorted((int(device[i]), files[i]) for i in pick)
        entry = {"trigger": f["trigger"], "frames": len(near)}
        try:
            if len(near) < 3:
                raise SyncError(f"only {len(near)} frames near it")
            images = [read_image_file(root / file) for _, file in near]  # raw or PNG
            trace = brightness_trace(images)
            est = find_flash([t for t, _ in near], trace, exposure_ns, duration_ns=f["ms"] * 1e6)
            check_flash_shape(trace, [t for t, _ in near], est, f["ms"])
        except (SyncError, OSError, ValueError) as exc:
            entry["problem"] = f"flash at trigger {f['trigger']:.2f} not found: {exc}"
            result.flashes.append(entry)
            continue
        entry.update(onset_ns=est.onset_ns, uncertainty_periods=round(est.uncertainty_ns / period_ns, 4))
        result.flashes.append(entry)
        points.append((est.onset_ns, f["trigger"], est.uncertainty_ns))
    if not points:
        result.problem = "; ".join(e.get("problem", "") for e in result.flashes) or "no flash"
        return result, None
    try:
        fit = fit_clock(points, rate_hz)
    except SyncError as exc:
        result.problem = str(exc)
        return result, None
    stamps = [rec["device_ts_ns"] for rec, _ in frames.values()]
    # frames beyond the flashes take the rate's uncertainty along: the take's worst frame is stated
    result.rate_ppm, result.rate_ppm_error = fit.rate_ppm, fit.rate_ppm_error
    result.error_periods = fit.error_over(min(stamps), max(stamps))
    if result.error_periods >= MAX_ERROR_PERIODS:
        loose = [e for e in result.flashes if e.get("uncertainty_periods", 0) >= MAX_ERROR_PERIODS]
        why = (f"the flash at trigger {loose[0]['trigger']:.2f} is pinned to {loose[0]['uncertainty_periods']:.2f} periods "
               "(frames missing around it)" if loose else "the flashes disagree or lie close together")
        result.problem = (f"the flashes place its frames only to {result.error_periods:.2f} pulse periods: {why}; "
                          "its frames could go to a neighbouring set")
        return result, None
    placement, delays = {}, []
    for frame_id, (rec, _) in frames.items():
        pos = float(fit.position(rec["device_ts_ns"]))
        n = int(np.floor(pos + 0.5))
        placement[frame_id] = (n, pos - n)
        # the flash's host time ties the axis to the host clock: where this exposure began on it
        ref = flashes[0]
        host_at = ref["host_ns"] + (pos - ref["trigger"]) * period_ns
        delays.append(rec["host_ts_ns"] - host_at)
    result.latency_ms = round(float(np.median(delays)) / 1e6, 3)
    return result, placement


def _clock_restart(frames: dict[int, tuple[dict, Any]]) -> Optional[str]:
    """Why the camera's timestamps are not one clock (its stream started again during the take, its
    presentation times back at zero), or None: a line through the flashes holds for one clock only."""
    ids = sorted(frames)
    stamps = [frames[i][0]["device_ts_ns"] for i in ids]
    for k in range(1, len(ids)):
        if stamps[k] <= stamps[k - 1]:
            return (f"its clock went back at frame {ids[k]} ({stamps[k - 1] / 1e9:.3f} s, then {stamps[k] / 1e9:.3f} s): "
                    "its stream started again during the take, and one line through the flashes cannot place both parts")
    return None


def _regroup(rows: list[dict], name: str, placement: dict[int, tuple[int, float]], result: CameraAlignment) -> None:
    """Each set gets the camera's frame of its own pulse: the frame placed nearest it, else null."""
    records = {}
    was_in = {}
    for row in rows:
        rec = row["frames"].get(name)
        if rec is not None:
            records[int(rec["frame_id"])] = rec
            was_in[int(rec["frame_id"])] = row.get("trigger")
    best: dict[int, tuple[float, int]] = {}
    for frame_id, (n, offset) in placement.items():
        if n not in best or abs(offset) < best[n][0]:
            best[n] = (abs(offset), frame_id)
    for row in rows:
        pick = best.get(row.get("trigger"))
        if pick is None:
            row["frames"][name] = None
            continue
        frame_id = pick[1]
        rec = dict(records[frame_id])
        rec["offset"] = round(placement[frame_id][1], 4)
        row["frames"][name] = rec
        result.placed += 1
        result.moved += was_in.get(frame_id) != row.get("trigger")
