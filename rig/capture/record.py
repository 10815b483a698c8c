"""`rig record`: run the rig in sync and write every FrameSet to a sequence folder.

Cameras that record to their own card (a GoPro with `?record=card`) are not in the sets: their
shutters are pressed once the take runs and released when it ends (rig.capture.cards), and their
videos are downloaded into the take's `media/` folder afterwards (rig.capture.fetch)."""
from __future__ import annotations

import json
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from rig.cameras import live_cameras
from rig.config import RigConfig
from rig.errors import ConfigError
from rig.progress import StatusLine, rate, rate_text
from rig.truth import take_truth
from rig.capture.cards import CardShutters
from rig.capture.session import TAKE_NEEDS_LIVE
from rig.capture.tap import guard, tapped
from rig.storage.disk import check_disk, rig_data_rate
from rig.storage.layout import FLASHES
from rig.storage.recorder import SequenceWriter

RECORD_MAX_WAIT_S = 2.0  # how long a set waits for a late frame before it is written without it
# A set reaching the writer this long after its frames arrived means the disk (or, compressing, the
# CPU) cannot keep up: the sets in between wait in memory. Beyond this, sets are skipped, counted and
# reported, until the writer has caught up, rather than filling the host's memory until it fails.
BEHIND_LIMIT_S = RECORD_MAX_WAIT_S + 2.0
# Cameras that cannot be triggered are aligned to the pulses afterwards by the board's LED flashing
# in their view (`rig record align`): once soon after the take starts and once near its end, so the
# alignment also measures each camera's clock rate. A flash lasts a few frame periods: the fit uses
# both of its edges.
FLASH_MS = 150
FLASH_AT_S = 0.6  # after the first set; and this long before the end of a take of known length


class _Flasher:
    """Fires the take's LED flashes from a thread of its own (the board answers within a round
    trip, the take's writing must not wait for it) and appends each to the take's flashes file."""

    def __init__(self, session, out: Path):
        self.session, self.path = session, Path(out) / FLASHES
        self.fired: list[dict] = []
        self._threads: list[threading.Thread] = []

    def fire(self) -> None:
        t = threading.Thread(target=self._flash, name="rig-record-flash", daemon=True)
        t.start()
        self._threads.append(t)

    def _flash(self) -> None:
        flash = self.session.flash(FLASH_MS)
        if flash is None or flash.get("trigger") is None:
            return
        self.fired.append(flash)
        with open(self.path, "a") as f:
            f.write(json.dumps(flash) + "\n")

    def join(self) -> None:
        for t in self._threads:
            t.join(timeout=2.0)


@dataclass
class RecordResult:
    out: Path
    sets: int = 0
    complete_sets: int = 0
    frames: dict[str, int] = field(default_factory=dict)
    delivered: dict[str, int] = field(default_factory=dict)
    grouped: dict[str, int] = field(default_factory=dict)  # placed in a set
    drops: dict[str, int] = field(default_factory=dict)
    lost_in_transfer: dict[str, int] = field(default_factory=dict)  # gaps in the frame ids: exposures that never arrived
    id_gaps: dict[str, list] = field(default_factory=dict)  # where: {"after_id", "next_id", "lost", "at_s"}
    seconds: float = 0.0
    bytes: int = 0
    cpu_s: float = 0.0
    errors: list[str] = field(default_factory=list)
    stopped_by: str = "done"
    flashes: int = 0
    media: Optional[dict] = None  # card cameras: what rig.capture.fetch reported
    codec: str = "raw"
    raw_bytes: int = 0  # what the written frames hold uncompressed
    encode_cpu_s: float = 0.0
    sets_skipped: int = 0  # sets not written because the writer had fallen too far behind
    frames_skipped: int = 0
    behind_max_s: float = 0.0  # the most a set waited between its frames' arrival and the writer
    data_mb_per_s: Optional[float] = None  # the rig's raw data rate (config), checked against the disk
    disk_mb_per_s: Optional[float] = None  # the disk's rate, measured before the take

    @property
    def frames_lost(self) -> dict[str, int]:
        """Frames of the take's sets that are not in the sequence: placed in a set and not written
        (a set skipped, a full disk), or never delivered (gaps in the camera's frame ids: a link
        down, a stalled daemon whose ring was overwritten, a full queue), whatever the cause.
        Frames from outside the take's train (a shared board pulses on for other sessions) are not
        the take's."""
        return {n: max(0, self.grouped.get(n, 0) - self.frames.get(n, 0)) + self.lost_in_transfer.get(n, 0) for n in self.frames}

    def to_dict(self) -> dict:
        return {
            "out": str(self.out),
            "sets": self.sets,
            "complete_sets": self.complete_sets,
            "frames": self.frames,
            "frames_lost": self.frames_lost,
            "lost_in_transfer": self.lost_in_transfer,
            "id_gaps": self.id_gaps,
            "drops": self.drops,
            "seconds": round(self.seconds, 3),
            "sets_per_s": round(self.sets / self.seconds, 3) if self.seconds else 0.0,
            "mb_per_s": round(self.bytes / 1e6 / self.seconds, 3) if self.seconds else 0.0,
            "cpu_percent": round(100.0 * self.cpu_s / self.seconds, 1) if self.seconds else 0.0,
            "stopped_by": self.stopped_by,
            "flashes": self.flashes,
            "media": self.media,
            "codec": self.codec,
            "compression_ratio": round(self.raw_bytes / self.bytes, 3) if self.bytes else None,
            "encode_ms_per_frame": (round(1e3 * self.encode_cpu_s / sum(self.frames.values()), 2)
                                    if self.codec != "raw" and sum(self.frames.values()) else None),
            "sets_skipped": self.sets_skipped,
            "frames_skipped": self.frames_skipped,
            "behind_max_s": round(self.behind_max_s, 3),
            "data_mb_per_s": self.data_mb_per_s,
            "disk_mb_per_s": self.disk_mb_per_s,
            "errors": self.errors,
        }


def record(cfg: RigConfig, out: Path, seconds: Optional[float] = None, sets: Optional[int] = None,
           status: Optional[StatusLine] = None, notes: Optional[Callable[[str], None]] = None,
           flash: Optional[bool] = None, codec: str = "raw", disk_check: bool = True,
           compress_ratio: Optional[float] = None, stop: Optional[threading.Event] = None,
           tap=None) -> RecordResult:
    """Record to the new folder `out`; `status` shows the take as it goes, `notes` hears the start-up
    phases (rig/progress.py). `flash`: flash the board's LED for `rig record align` (default: when
    the rig has free-running cameras and a trigger board). `codec`: raw or png (lossless).
    `disk_check`: before anything starts, measure the output disk and refuse (DiskTooSlow, exit 2)
    a rig whose data rate it cannot take; `compress_ratio`: with png, the compression ratio to count
    (an earlier take's `compression_ratio`); unknown, compression counts for nothing.
    `stop`: set it to end the take early, as its length would (every set in flight is written).
    `tap`: an onlooker of the take (the console's previews and controls, rig.capture.tap.SessionTap):
    told of the open session, of each set written, and of the end; it never holds the take up."""
    from rig.capture.session import RigSession

    calibration = _check_take(cfg, seconds, sets, compress_ratio)
    live = live_cameras(cfg.cameras, TAKE_NEEDS_LIVE)  # the cameras of the sets
    cards = [c.name for c in cfg.cameras if c not in live]
    rate = cfg.trigger.rate_hz if cfg.trigger else max(c.fps for c in live)
    data_rate, disk = rig_data_rate(cfg, live), None
    if disk_check:
        # half a second, said nowhere: a refusal must stay the one line on stderr; before the cameras open: a take the disk cannot hold is refused up front, not cut short
        _, disk = check_disk(cfg, out, ratio=(compress_ratio or 1.0) if codec != "raw" else 1.0, cameras=live)
    writer = SequenceWriter(out, live, rig_name=cfg.name, rate_hz=rate, config_file=cfg.path,
                            calibration_file=calibration, extra=take_truth(cfg), codec=codec)
    result = RecordResult(Path(out), codec=codec, data_mb_per_s=round(data_rate / 1e6, 1),
                          disk_mb_per_s=round(disk.bytes_per_s / 1e6, 1) if disk is not None else None)
    clock = _TakeClock()
    session = None
    flashes = None
    shutters = None
    tap = guard(tap)
    if flash is None:
        flash = cfg.trigger is not None and any(c.trigger == "free" for c in cfg.cameras)
    try:
        # A recording can wait for late frames (a busy host, a slow disk) longer than live output can.
        session = RigSession(cfg, max_wait_s=RECORD_MAX_WAIT_S, on_phase=notes)
        with session, tapped(tap, session):
            # A board rig records a train of exactly N pulses; otherwise the session is stopped when
            # enough is recorded, and every set still in flight is written before the end.
            session.start(pulses=sets if (sets is not None and session.board is not None) else 0)
            shutters = _press_shutters(session, Path(out), notes)
            try:
                if flash and session.board is not None:
                    flashes = _Flashes(_Flasher(session, Path(out)), {c.name for c in live if c.trigger == "free"},
                                       seconds if seconds is not None else sets / rate)
                _write_sets(session, writer, result, clock, seconds=seconds, sets=sets, flashes=flashes, status=status,
                            notes=notes, out=out, stop=stop, tap=tap)
                session_stats = session.camera_stats()
                result.errors.extend(session.errors())
                if flashes is not None:
                    flashes.flasher.join()
            finally:
                if shutters is not None:
                    shutters.release()  # also when the take is interrupted: the cameras stop recording
    except KeyboardInterrupt:
        result.stopped_by = "interrupt"
        session_stats = {}
        if session is not None:
            session_stats = _write_in_flight(session, writer, result, notes)
    finally:
        writer.close()  # (leaving the session released any shutter still pressed)
    if shutters is not None:
        result.errors.extend(shutters.errors)
    if cards and shutters is not None and result.stopped_by != "interrupt":
        result.media = _fetch_media(out, notes, result.errors)
    elif cards:
        result.errors.append(f"{', '.join(cards)}: their videos were not downloaded (the take was interrupted); "
                             f"`rig record fetch {out}` brings them into the take")
    result.flashes = len(flashes.flasher.fired) if flashes is not None else 0
    _tally(result, writer, clock, session_stats)
    return result


# Deflate, PNG's compression, never stores data more than 1032 times smaller: a stated ratio above
# this is a mistake, and it would let the disk check pass any disk.
MAX_COMPRESS_RATIO = 1000.0


def _check_take(cfg: RigConfig, seconds: Optional[float], sets: Optional[int], compress_ratio: Optional[float]) -> Optional[Path]:
    """The take's length and options, and the calibration file it copies (None: none)."""
    if seconds is None and sets is None:
        raise ConfigError("record: give --seconds S or --sets N")
    if (seconds is not None and seconds <= 0) or (sets is not None and sets <= 0):
        raise ConfigError("record: --seconds and --sets must be positive")
    calibration = None
    if cfg.calibration:
        calibration = cfg.resolve(cfg.calibration)
        if not calibration.is_file():
            raise ConfigError(f"rig.calibration: {calibration} does not exist (calibrate with `rig calibrate run`, or remove the key)")
    if compress_ratio is not None and not 1.0 <= compress_ratio <= MAX_COMPRESS_RATIO:
        # inf (or 1e308) divided the rig's data rate to nothing: the disk check passed any disk
        raise ConfigError(f"record: --compress-ratio must be from 1 to {MAX_COMPRESS_RATIO:g} (an earlier take's "
                          f"compression_ratio), got {compress_ratio:g}")
    return calibration


def _press_shutters(session, out: Path, notes: Optional[Callable[[str], None]]) -> Optional[CardShutters]:
    """The card cameras' shutters, pressed once the pulses run, before the first set is written:
    the take's first flash comes after that (sets wait in the session's queue meanwhile)."""
    if not session.card_cameras:
        return None
    shutters = CardShutters(session.card_cameras, out)
    if notes is not None:
        notes(f"pressing the shutters of {', '.join(session.card_cameras)} (recording to their cards)")
    shutters.press()
    return shutters


class _TakeClock:
    """The take's time and CPU: both run from its first set, after the clock warm-up (from the call
    when no set came)."""

    def __init__(self) -> None:
        self.t0 = time.monotonic()
        self.cpu0 = time.process_time()
        self.t_first: Optional[float] = None
        self.t_first_ns: Optional[int] = None

    def first_set(self) -> None:
        self.t_first = time.monotonic()
        self.t_first_ns = time.monotonic_ns()
        self.cpu0 = time.process_time()

    def elapsed(self) -> float:
        return time.monotonic() - (self.t_first if self.t_first is not None else self.t0)


class _Flashes:
    """When the take's LED flashes fire: the first FLASH_AT_S after every free-running camera
    delivers (a GoPro's stream takes a while to start), the second near the end of the take."""

    def __init__(self, flasher: _Flasher, free_cameras: set[str], length_s: float):
        self.flasher = flasher
        self.waiting_for = set(free_cameras)
        self.times = [FLASH_AT_S] + ([length_s - FLASH_AT_S - FLASH_MS / 1000] if length_s >= 4 * FLASH_AT_S else [])

    def after_set(self, fs, elapsed: float) -> None:
        if self.waiting_for:
            self.waiting_for -= {n for n, f in fs.frames.items() if f is not None}
            if not self.waiting_for:  # every free-running camera delivers: the first flash is due
                first = elapsed + FLASH_AT_S
                self.times = [first] + [t for t in self.times[1:] if t > first + 1.0]
        while not self.waiting_for and self.times and elapsed >= self.times[0]:
            self.times.pop(0)
            self.flasher.fire()


def _write_sets(session, writer: SequenceWriter, result: RecordResult, clock: _TakeClock, *, seconds: Optional[float],
                sets: Optional[int], flashes: Optional[_Flashes], status: Optional[StatusLine],
                notes: Optional[Callable[[str], None]], out: Path, stop: Optional[threading.Event] = None, tap=None) -> None:
    """Write the session's sets until the take has its length, the board's train ended, `stop` is
    set or the storage failed; then the sets still in flight."""
    def over() -> bool:
        return (stop is not None and stop.is_set()) or (seconds is not None and clock.t_first is not None and clock.elapsed() >= seconds)

    for fs in session.framesets(until=over):
        if _behind(fs, result, notes):
            continue
        if not writer.write(fs):
            result.stopped_by = "storage"
            session.stop()
            break
        result.sets += 1
        if tap is not None:
            tap.frame_set(fs, {"sets": result.sets, "complete": writer.complete_sets, "skipped": result.sets_skipped,
                               "bytes": writer.bytes_written})
        if clock.t_first is None:
            clock.first_set()
        elapsed = clock.elapsed()
        if flashes is not None:
            flashes.after_set(fs, elapsed)
        if status is not None:
            status.update(_status_text(result, writer, session, elapsed, out))
        done = (sets is not None and result.sets >= sets) or (seconds is not None and elapsed >= seconds)
        if done or session.train_done.is_set():
            session.stop()  # flushes the last sets; the loop writes them and ends


def _write_in_flight(session, writer: SequenceWriter, result: RecordResult, notes: Optional[Callable[[str], None]]) -> dict:
    """After an interruption: leaving the `with` block stopped the session, which grouped the frames
    still in flight into its last sets; write them too, so an interrupted take loses no delivered
    frame. The cameras' statistics."""
    while writer.error is None and (fs := session.next_set(timeout=0)) is not None:
        if not _behind(fs, result, notes):
            writer.write(fs)
    return session.camera_stats()


def _tally(result: RecordResult, writer: SequenceWriter, clock: _TakeClock, session_stats: dict) -> None:
    """What the take wrote, how long it took and what the cameras delivered, into `result`."""
    result.seconds = clock.elapsed()
    result.cpu_s = time.process_time() - clock.cpu0
    result.sets = writer.sets_written
    result.complete_sets = writer.complete_sets
    result.frames = dict(writer.frames_written)
    result.bytes = writer.bytes_written
    result.raw_bytes = writer.raw_bytes
    result.encode_cpu_s = writer.encode_cpu_s
    if result.sets_skipped:
        result.errors.append(f"the recording fell {result.behind_max_s:.1f} s behind the cameras (the disk or, compressing, the "
                             f"CPU is too slow): {result.sets_skipped} sets ({result.frames_skipped} frames) were skipped, "
                             f"not written; the index shows them as gaps")
    result.delivered = {n: s.get("delivered", 0) for n, s in session_stats.items()}
    result.grouped = {n: s.get("grouped", 0) for n, s in session_stats.items()}
    result.drops = {n: s.get("dropped", 0) for n, s in session_stats.items()}
    result.lost_in_transfer = {n: s.get("lost_frames", 0) for n, s in session_stats.items()}
    t0 = clock.t_first_ns
    result.id_gaps = {n: [{"after_id": g["after_id"], "next_id": g["next_id"], "lost": g["lost"],
                           "at_s": round((g["host_ts_ns"] - t0) / 1e9, 3) if t0 is not None else None} for g in s.get("id_gaps", [])]
                      for n, s in session_stats.items() if s.get("id_gaps")}
    lost = {n: k for n, k in result.lost_in_transfer.items() if k}
    if lost:
        result.errors.append("frames lost (gaps in the cameras' frame ids: a link down, a stalled daemon or a full queue): " + "; ".join(
            f"{n} {k}" + (f" (first {result.id_gaps[n][0]['lost']} after frame {result.id_gaps[n][0]['after_id']}"
                          + (f", {result.id_gaps[n][0]['at_s']:.1f} s into the take" if result.id_gaps[n][0]['at_s'] is not None else "") + ")"
                          if result.id_gaps.get(n) else "")
            for n, k in lost.items()))
    if writer.error is not None:
        result.errors.append(str(writer.error))
        result.stopped_by = "storage"


def _behind(fs, result: RecordResult, notes: Optional[Callable[[str], None]]) -> bool:
    """Whether to skip this set: the writer is more than BEHIND_LIMIT_S behind the cameras (the
    time since the set's last frame arrived). Counted; said once when it starts."""
    arrived = max([f.host_ts_ns for f in fs.frames.values() if f is not None] or [fs.host_ts_ns])
    behind = (time.monotonic_ns() - arrived) / 1e9
    result.behind_max_s = max(result.behind_max_s, behind)
    if behind <= BEHIND_LIMIT_S:
        return False
    if result.sets_skipped == 0 and notes is not None:
        notes(f"the recording is {behind:.1f} s behind the cameras: skipping sets until it catches up (they are counted)")
    result.sets_skipped += 1
    result.frames_skipped += sum(f is not None for f in fs.frames.values())
    return True


def _fetch_media(out: Path, notes: Optional[Callable[[str], None]], errors: list[str]) -> dict:
    """Download what the card cameras recorded; a camera left with files to fetch is an error."""
    from rig.capture.fetch import fetch

    media = fetch(out, notes=notes)
    for name, cam in media["cameras"].items():
        if cam["problem"]:
            left = "" if cam["state"] == "done" else f"; `rig record fetch {out}` resumes the download"
            errors.append(f"{name}: {cam['problem']}{left}")
    return media


def _status_text(result: RecordResult, writer: SequenceWriter, session, elapsed: float, out: Path) -> str:
    drops = " ".join(f"{n}:{s.get('dropped', 0)}" for n, s in session.camera_stats().items())
    free = shutil.disk_usage(out).free / 1e9
    # `elapsed` runs from the first set: the sets after it came in that time; no rate at all until
    # it spans enough time and sets to be one
    sets_per_s = rate(result.sets - 1, elapsed)
    mb_per_s = sets_per_s * writer.bytes_written / 1e6 / result.sets if sets_per_s is not None else None
    return (f"{elapsed:6.1f} s  {result.sets} sets  {rate_text(sets_per_s)} sets/s  drops {drops}  "
            f"{rate_text(mb_per_s, 6)} MB/s  {free:6.1f} GB free")
