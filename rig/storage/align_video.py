"""`rig record align`, for the videos card-recording cameras made during a take (rig.storage.media).

A video's frame k exposes from its presentation time (pts) on, on the camera's own clock. The board
flashed its LED twice during the take (flashes.jsonl: each flash's place on the trigger axis and its
host time). For each downloaded video:

1. where each flash should be in the video follows from the host clock: the flash's host time less
   the time the camera said it began encoding (media.json); the frames within WINDOW_S of that
   (never reaching halfway to another flash) are decoded (PyAV), shrunk to at most 320 pixels wide,
   grey;
2. the flash's onset on the video's clock, to a fraction of a frame (sync.alignment: brightness_trace,
   find_flash, with each frame's exposure from its pts for the configured `exposure_us`, else a full
   frame period), and the check that what brightened is shaped like the flash;
3. the onsets and the flashes' places give the line from the video's clock to the trigger axis (two
   flashes: offset and rate; one: offset at the nominal rate): rig.storage.flash_fit.

The result per video: the trigger position of frame 0's exposure start, pulses per frame (and per
second of the video's clock), the clock rate in ppm, and the uncertainty in pulse periods and in
frame periods. Frame k of a constant-rate video exposes from trigger position
`trigger_at_frame0 + k * pulses_per_frame`; any frame from `trigger_at_frame0 + (pts_s - pts0_s) *
pulses_per_second`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from rig.storage.flash_fit import check_flash_shape, fit_clock
from rig.storage.media import MediaManifest
from sync.alignment import brightness_trace, find_flash
from sync.errors import SyncError

WINDOW_S = 2.0  # how far from its expected place a flash is looked for (the camera's start-up delay, host jitter)
MAX_WIDTH = 320  # frames are shrunk to this width before the flash is looked for (as brightness_trace does)


@dataclass
class VideoAlignment:
    camera: str
    file: str  # in the take: media/CAM/NAME
    frames: Optional[int] = None
    fps: Optional[float] = None
    pts0_s: Optional[float] = None  # presentation time of frame 0
    flashes: list[dict[str, Any]] = field(default_factory=list)
    trigger_at_frame0: Optional[float] = None  # trigger-axis position of frame 0's exposure start
    pulses_per_frame: Optional[float] = None
    pulses_per_second: Optional[float] = None  # of the video's own clock (its pts)
    rate_ppm: Optional[float] = None  # how fast the camera's clock runs against the board's (two flashes or more)
    rate_ppm_error: Optional[float] = None  # how far rate_ppm may be off (the flashes' onset uncertainties)
    error_periods: Optional[float] = None  # uncertainty in pulse periods
    error_frames: Optional[float] = None  # the same in the video's frame periods
    problem: Optional[str] = None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def align_videos(manifest: MediaManifest, flashes: list[dict], rate_hz: float, cameras: Optional[list[str]] = None,
                 exposures_us: Optional[dict[str, float]] = None) -> list[VideoAlignment]:
    """Every file of the manifest's cameras (or `cameras`); a file not downloaded yet is a problem."""
    out = []
    for name, cam in manifest.cameras.items():
        if cameras is not None and name not in cameras:
            continue
        ref_ns = cam.encoding_host_ns or cam.pressed_host_ns
        if not cam.files:
            out.append(VideoAlignment(name, "", problem=cam.problem or "no video of the take is known yet "
                                      f"(`rig record fetch {manifest.root}`)"))
            continue
        for f in cam.files:
            result = VideoAlignment(name, f.file)
            if f.state != "done":
                result.problem = f"not downloaded yet (`rig record fetch {manifest.root}` brings it)"
            elif ref_ns is None:
                result.problem = "media.json does not say when the camera began recording: no place to look for the flashes"
            else:
                _align_one(manifest.root / f.file, result, flashes, rate_hz, ref_ns, (exposures_us or {}).get(name))
            out.append(result)
    return out


def _align_one(path: Path, result: VideoAlignment, flashes: list[dict], rate_hz: float, ref_ns: int,
               exposure_us: Optional[float]) -> None:
    import av

    try:
        container = av.open(str(path))
    except (OSError, av.FFmpegError) as exc:
        result.problem = f"{path}: cannot open the video ({exc})"
        return
    with container:
        stream = container.streams.video[0]
        rate = stream.average_rate or stream.guessed_rate
        if not rate:
            result.problem = f"{path}: the video does not say its frame rate"
            return
        fps = float(rate)
        result.fps = round(fps, 6)
        result.frames = int(stream.frames) or None
        tb = float(stream.time_base)
        first = _first_pts(container, stream)
        if first is None:
            result.problem = f"{path}: no frame in the video"
            return
        result.pts0_s = first * tb
        exposure_ns = float(exposure_us) * 1e3 if exposure_us else 1e9 / fps
        expected = [result.pts0_s + (f["host_ns"] - ref_ns) / 1e9 for f in flashes]
        points = []
        for i, f in enumerate(flashes):
            lo = expected[i] - WINDOW_S
            hi = expected[i] + f["ms"] / 1e3 + WINDOW_S
            if i > 0:  # never as far as halfway to the neighbouring flashes
                lo = max(lo, 0.5 * (expected[i - 1] + flashes[i - 1]["ms"] / 1e3 + expected[i]))
            if i + 1 < len(flashes):
                hi = min(hi, 0.5 * (expected[i] + f["ms"] / 1e3 + expected[i + 1]))
            entry: dict[str, Any] = {"trigger": f["trigger"], "expected_s": round(expected[i], 3)}
            try:
                times, images = _window(container, stream, lo, hi)
                entry["frames"] = len(times)
                if len(times) < 3:
                    raise SyncError(f"only {len(times)} frames of the video within {WINDOW_S:g} s of where it should be")
                trace = brightness_trace(images)
                est = find_flash(times, trace, exposure_ns, duration_ns=f["ms"] * 1e6)
                check_flash_shape(trace, times, est, f["ms"])
            except (SyncError, ValueError, av.FFmpegError) as exc:
                entry["problem"] = f"flash at trigger {f['trigger']:.2f} not found: {exc}"
                result.flashes.append(entry)
                continue
            entry.update(onset_s=round(est.onset_ns / 1e9, 6),
                         uncertainty_periods=round(est.uncertainty_ns * rate_hz / 1e9, 4))
            result.flashes.append(entry)
            points.append((est.onset_ns, f["trigger"], est.uncertainty_ns))
    if not points:
        result.problem = "; ".join(e.get("problem", "") for e in result.flashes) or "no flash during the video"
        return
    try:
        fit = fit_clock(points, rate_hz)
    except SyncError as exc:
        result.problem = str(exc)
        return
    result.trigger_at_frame0 = round(float(fit.position(result.pts0_s * 1e9)), 5)
    result.pulses_per_second = round(fit.slope * 1e9, 7)
    result.pulses_per_frame = round(fit.slope * 1e9 / fps, 7)
    result.rate_ppm, result.rate_ppm_error = fit.rate_ppm, fit.rate_ppm_error
    last_s = result.pts0_s + ((result.frames or 1) - 1) / fps  # the video's last frame: the rate's uncertainty grows to it
    result.error_periods = fit.error_over(result.pts0_s * 1e9, last_s * 1e9)
    result.error_frames = round(result.error_periods * fps / rate_hz, 4)


def _first_pts(container, stream) -> Optional[int]:
    container.seek(0, stream=stream, backward=True)
    for frame in container.decode(stream):
        if frame.pts is not None:
            return int(frame.pts)
    return None


def _window(container, stream, lo_s: float, hi_s: float) -> tuple[list[float], list[np.ndarray]]:
    """The frames whose pts lie in [lo_s, hi_s]: their pts in ns and small grey images."""
    tb = float(stream.time_base)
    container.seek(max(0, int(lo_s / tb)), stream=stream, backward=True)  # the key frame at or before lo_s
    times, images = [], []
    for frame in container.decode(stream):
        if frame.pts is None:
            continue
        t = frame.pts * tb
        if t < lo_s:
            continue
        if t > hi_s:
            break
        k = max(1, int(np.ceil(frame.width / MAX_WIDTH)))
        small = frame.reformat(width=frame.width // k, height=frame.height // k, format="gray", interpolation="AREA")
        times.append(t * 1e9)
        images.append(small.to_ndarray())
    return times, images
