"""Grab N frames from every camera of a rig: PNG files plus a `frames.jsonl` index.

Each camera runs in its own thread. A frame's PNG is written under a temporary name, synced and
renamed (common/files.py), then its record is appended to `frames.jsonl` and flushed, so whatever
happens later (a camera vanishing, Ctrl-C, a kill, a power cut) every listed frame is on disk and
intact.
"""
from __future__ import annotations

import json
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from common.files import atomic_path
from rig.cameras import live_cameras, open_camera, records_to_card
from rig.capture.session import RigSession, prerender_note
from rig.config import RigConfig
from rig.errors import ConfigError, DeviceError, RigError, StorageError
from sync.frames import Frame

INDEX = "frames.jsonl"


@dataclass
class CameraResult:
    frames: int = 0
    dropped: int = 0
    incomplete: int = 0
    first_ts: Optional[int] = None
    last_ts: Optional[int] = None
    error: Optional[RigError] = None

    @property
    def fps(self) -> float:
        if self.frames < 2 or self.first_ts is None or self.last_ts == self.first_ts:
            return 0.0
        return (self.frames - 1) * 1e9 / (self.last_ts - self.first_ts)


@dataclass
class GrabResult:
    out_dir: Path
    cameras: dict[str, CameraResult] = field(default_factory=dict)
    session_errors: list[RigError] = field(default_factory=list)  # trigger board or camera lost mid-train

    @property
    def errors(self) -> list[RigError]:
        return [r.error for r in self.cameras.values() if r.error is not None] + self.session_errors

    def summary(self) -> dict:
        return {
            "out": str(self.out_dir),
            "frames": {n: r.frames for n, r in self.cameras.items()},
            "dropped": {n: r.dropped for n, r in self.cameras.items()},
            "fps": {n: round(r.fps, 3) for n, r in self.cameras.items()},
            "errors": [str(e) for e in self.errors],
        }


def write_image(path: Path, image: np.ndarray) -> None:
    """Write a PNG atomically: a crash never leaves a torn image under the final name."""
    img = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    try:
        with atomic_path(path) as tmp:  # the temporary name keeps `.png`, which tells cv2 the format
            if not cv2.imwrite(str(tmp), img):
                raise StorageError(f"{path}: could not write image (disk full or not writable?)")
    except OSError as exc:  # the fsync or the rename of a written image failed
        raise StorageError(f"{path}: could not write image ({exc.strerror})") from None


class _Index:
    """frames.jsonl, appended and flushed one record at a time from several threads."""

    def __init__(self, path: Path):
        try:
            self._f = open(path, "x", buffering=1)  # "x": never append to an earlier grab's index
        except FileExistsError:
            raise ConfigError(f"{path.parent}: already holds a grab; choose a new folder (nothing was overwritten)") from None
        except OSError as exc:
            raise StorageError(f"{path}: cannot create the index ({exc.strerror})") from None
        self._lock = threading.Lock()

    def append(self, record: dict) -> None:
        line = json.dumps(record) + "\n"
        with self._lock:
            self._f.write(line)
            self._f.flush()

    def close(self) -> None:
        self._f.close()


def grab(cfg: RigConfig, n: int, out_dir: Path, timeout: float = 2.0,
         notes: Optional[Callable[[str], None]] = None) -> GrabResult:
    """Grab `n` frames per camera into `out_dir`, which must not hold a grab already (its index
    would be appended to and its images overwritten). `notes` hears the start-up phases."""
    if n < 1:
        raise ConfigError(f"-n: must be at least 1, got {n}")
    out_dir = Path(out_dir)
    if (out_dir / INDEX).exists():
        raise ConfigError(f"{out_dir}: already holds a grab; choose a new folder (nothing was overwritten)")
    live = live_cameras(cfg.cameras, "there are no live frames to grab")  # a camera recording to its card has none
    if len(live) < len(cfg.cameras) and notes is not None:
        notes(f"not grabbing {', '.join(c.name for c in cfg.cameras if c not in live)}: records to its card, no live frames")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for c in live:
            (out_dir / c.name).mkdir(exist_ok=True)
    except OSError as exc:
        raise StorageError(f"{out_dir}: cannot create output folder ({exc.strerror})") from None
    result = GrabResult(out_dir)
    if any(c.trigger == "hardware" for c in live):
        return _grab_with_board(cfg, n, out_dir, result, notes)
    cameras = []
    try:
        for c in live:  # open all first: a bad URI fails before anything is written
            cameras.append(open_camera(c))
        note = prerender_note({cam.name: cam for cam in cameras})
        if note and notes is not None:
            notes(note)
        index = _Index(out_dir / INDEX)
        try:
            threads = []
            for cam in cameras:
                r = result.cameras.setdefault(cam.name, CameraResult())
                t = threading.Thread(target=_grab_camera, args=(cam, n, out_dir, index, r, timeout), daemon=True)
                threads.append(t)
                t.start()
            for t in threads:
                t.join()
        finally:
            index.close()
    finally:
        for cam in cameras:
            try:
                cam.close()
            except Exception:
                pass
    return result


def _save(frame: Frame, i: int, out_dir: Path, index: _Index, r: CameraResult) -> None:
    rel = Path(frame.camera) / f"{i:06d}.png"
    write_image(out_dir / rel, frame.image)
    record = {"camera": frame.camera, "frame_id": frame.frame_id, "device_ts_ns": frame.device_ts_ns,
              "host_ts_ns": frame.host_ts_ns, "file": str(rel), "pixel_format": frame.pixel_format}
    if frame.trigger_index is not None:
        record["trigger_index"] = frame.trigger_index
    index.append(record)
    r.frames += 1
    r.first_ts = frame.host_ts_ns if r.first_ts is None else r.first_ts
    r.last_ts = frame.host_ts_ns


def _grab_with_board(cfg: RigConfig, n: int, out_dir: Path, result: GrabResult,
                     notes: Optional[Callable[[str], None]]) -> GrabResult:
    """Hardware-triggered cameras: a train of N pulses from the rig's trigger board."""
    for c in cfg.cameras:
        if not records_to_card(c):
            result.cameras[c.name] = CameraResult()
    index = _Index(out_dir / INDEX)
    write_error: Optional[StorageError] = None
    try:
        with RigSession(cfg, on_phase=notes) as session:
            session.start(pulses=n)
            try:
                for fs in session.framesets():
                    for frame in fs:
                        r = result.cameras[frame.camera]
                        _save(frame, r.frames, out_dir, index, r)
                    if session.train_done.is_set() or all(r.frames >= n for r in result.cameras.values()):
                        session.stop()
            except StorageError as exc:  # a full disk ends the grab; every frame listed so far is whole
                write_error = exc
                session.stop()
            stats = session.camera_stats()
            errors = session.errors()
    finally:
        index.close()
    for name, r in result.cameras.items():
        r.dropped = stats.get(name, {}).get("dropped", 0)
    result.session_errors = [DeviceError(line) for line in errors] + ([write_error] if write_error else [])
    return result


def _grab_camera(cam, n: int, out_dir: Path, index: _Index, r: CameraResult, timeout: float) -> None:
    try:
        cam.start()
        for i in range(n):
            if cam.settings.trigger == "software":
                cam.software_trigger()
            frame: Frame = cam.get_frame(timeout)
            _save(frame, i, out_dir, index, r)
    except RigError as exc:
        r.error = exc
    except Exception as exc:  # keep other cameras going; report this one's failure in one line
        r.error = DeviceError(f"{cam.name}: {type(exc).__name__}: {exc}")
    finally:
        r.dropped = cam.stats.dropped
        r.incomplete = cam.stats.incomplete
        try:
            cam.stop()
        except Exception:
            pass
