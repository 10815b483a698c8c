"""Write FrameSets to a sequence folder (docs/sequence-format.md), fast enough for a small embedded box.

One writer thread per camera writes raw netpbm images (no compression: the disk, not the CPU, is the
limit). A set's index row is appended, in set order, once all of its images are written, and
flushed at once (a `kill -9` loses nothing that was flushed); the filesystem is synced every
`sync_interval` seconds, so a power cut loses at most that much. The first write error (a full
disk) stops the recording: the index keeps every set written before it.
"""
from __future__ import annotations

import datetime as _dt
import errno
import json
import os
import queue
import shutil
import threading
from pathlib import Path
from typing import Optional

from common.files import atomic_write_json
from rig.errors import StorageError
from rig.storage.layout import CALIBRATION_COPY, CONFIG_COPY, FRAMES, INDEX, META, CameraEntry, SequenceMeta, stored_layout
from rig.storage.netpbm import encode_netpbm
from sync.frames import Frame, FrameSet

QUEUE_FRAMES = 32  # per camera: frames waiting for the disk before the recorder applies back-pressure


class SequenceWriter:
    def __init__(self, root: Path, cameras: list, rig_name: str = "", rate_hz: Optional[float] = None,
                 config_file: Optional[Path] = None, calibration_file: Optional[Path] = None,
                 extra: Optional[dict] = None, sync_interval: float = 0.5):
        """`cameras`: CameraConfig-like objects (name, role, width, height, pixel_format)."""
        self.root = Path(root)
        # never write over or into what is there: a take, or any file of a take's names
        taken = [n for n in (INDEX, META, FRAMES, CONFIG_COPY, CALIBRATION_COPY) if (self.root / n).exists()]
        if taken:
            what = "already holds a sequence" if INDEX in taken or META in taken else f"already holds {', '.join(taken)}"
            raise StorageError(f"{self.root}: {what}; choose a new folder (nothing was overwritten)")
        try:
            for c in cameras:
                (self.root / FRAMES / c.name).mkdir(parents=True, exist_ok=True)
            entries = []
            for c in cameras:
                ch, bps = stored_layout(c.pixel_format)
                entries.append(CameraEntry(c.name, c.role, c.width, c.height, c.pixel_format, ch, bps))
            self.meta = SequenceMeta(entries, rig_name, rate_hz, _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                                     dict(extra or {}))
            atomic_write_json(self.root / META, self.meta.to_dict())
            if config_file is not None:
                shutil.copyfile(config_file, self.root / CONFIG_COPY)
            if calibration_file is not None:
                shutil.copyfile(calibration_file, self.root / CALIBRATION_COPY)
            self._index = open(self.root / INDEX, "ab", buffering=0)
        except OSError as exc:
            raise StorageError(f"{self.root}: cannot create the sequence ({exc.strerror})") from None
        self.entries = {e.name: e for e in entries}
        self.sync_interval = sync_interval
        self._lock = threading.Lock()
        self._pending: dict[int, dict] = {}  # set number -> {"row": ..., "left": n}
        self._next_row = 0
        self._n_sets = 0
        self.sets_written = 0
        self.complete_sets = 0
        self.frames_written = {e.name: 0 for e in entries}
        self.bytes_written = 0
        self.error: Optional[StorageError] = None
        self._queues = {e.name: queue.Queue(maxsize=QUEUE_FRAMES) for e in entries}
        self._threads = [threading.Thread(target=self._writer, args=(name,), name=f"writer-{name}", daemon=True)
                         for name in self._queues]
        self._stop_sync = threading.Event()
        self._threads.append(threading.Thread(target=self._syncer, name="sequence-sync", daemon=True))
        for t in self._threads:
            t.start()

    def _syncer(self) -> None:
        """Push written images and rows to the disk regularly: a power cut loses at most one interval."""
        while not self._stop_sync.wait(self.sync_interval):
            os.sync()

    # --- producer side ----------------------------------------------------------------------------
    def write(self, fs: FrameSet) -> bool:
        """Queue one FrameSet; returns False once the recording has stopped on an error."""
        if self.error is not None:
            return False
        n = self._n_sets
        self._n_sets += 1
        row = {"set": n, "trigger": fs.index, "host_ts_ns": fs.host_ts_ns, "frames": {}}
        present = [(name, f) for name, f in fs.frames.items() if f is not None]
        for name in self.entries:
            row["frames"][name] = None  # a camera absent from the set is a marked gap
        with self._lock:
            self._pending[n] = {"row": row, "left": len(present), "complete": len(present) == len(self.entries)}
        for name, frame in present:
            if name not in self._queues:
                raise StorageError(f"frame from camera '{name}' that the sequence does not record")
            self._queues[name].put((n, frame))  # blocks when the disk falls behind: back-pressure
        if not present:
            self._complete_rows()
        return self.error is None

    def close(self) -> None:
        for q in self._queues.values():
            q.put(None)
        self._stop_sync.set()
        for t in self._threads:
            t.join()
        with self._lock:
            self._flush_ready_rows(force_sync=True)
        try:
            self._index.close()
        except OSError:
            pass

    # --- writer threads ---------------------------------------------------------------------------
    def _writer(self, name: str) -> None:
        q = self._queues[name]
        folder = self.root / FRAMES / name
        while True:
            item = q.get()
            if item is None:
                return
            n, frame = item
            if self.error is not None:
                continue  # drain: nothing more is written after the first failure
            rel = f"{FRAMES}/{name}/{frame.frame_id:08d}{self.entries[name].suffix}"
            try:
                nbytes = self._write_image(folder / rel.rsplit("/", 1)[1], frame)
            except OSError as exc:
                self._fail(exc, folder / rel.rsplit("/", 1)[1])
                continue
            rec = {"frame_id": frame.frame_id, "device_ts_ns": frame.device_ts_ns, "host_ts_ns": frame.host_ts_ns, "file": rel}
            if frame.sim_time_s is not None:
                rec["sim_time_s"] = frame.sim_time_s
            with self._lock:
                self.bytes_written += nbytes
                self.frames_written[name] += 1
                p = self._pending[n]
                p["row"]["frames"][name] = rec
                p["left"] -= 1
                if p["left"] == 0:
                    self._flush_ready_rows()

    def _write_image(self, path: Path, frame: Frame) -> int:
        header, pixels = encode_netpbm(self.entries[frame.camera].stored(frame.image))
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(fd, header)
            _write_all(fd, pixels)
        finally:
            os.close(fd)
        return len(header) + pixels.nbytes

    def _fail(self, exc: OSError, path: Path) -> None:
        try:
            path.unlink()  # never leave a torn image behind
        except OSError:
            pass
        if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            msg = f"{self.root}: disk full ({exc.strerror}); recording stopped, the sequence is valid up to the last written set"
        else:
            msg = f"{path}: write failed ({exc.strerror}); recording stopped, the sequence is valid up to the last written set"
        with self._lock:
            if self.error is None:
                self.error = StorageError(msg)

    def _complete_rows(self) -> None:
        with self._lock:
            self._flush_ready_rows()

    def _flush_ready_rows(self, force_sync: bool = False) -> None:
        """Append, in set order, every row whose images are all written (caller holds the lock)."""
        lines = []
        while self._next_row in self._pending and self._pending[self._next_row]["left"] == 0 and self.error is None:
            p = self._pending.pop(self._next_row)
            lines.append(json.dumps(p["row"], separators=(",", ":")))
            self.sets_written += 1
            self.complete_sets += p["complete"]
            self._next_row += 1
        try:
            if lines:
                _write_all(self._index.fileno(), ("\n".join(lines) + "\n").encode())
            if force_sync:
                os.sync()
        except OSError as exc:
            if self.error is None:
                self.error = StorageError(f"{self.root / INDEX}: write failed ({exc.strerror}); recording stopped")


def _write_all(fd: int, data) -> None:
    view = memoryview(data).cast("B")
    while view:
        n = os.write(fd, view)
        view = view[n:]
