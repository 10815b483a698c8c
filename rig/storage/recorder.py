"""Write FrameSets to a sequence folder (docs/sequence-format.md), fast enough for a small embedded box.

One writer thread per camera writes raw netpbm images (no compression: the disk, not the CPU, is the
limit), each image in one system call from the frame's own buffer (no copy; O_DIRECT on request). With `codec="png"`
several threads per camera compress frames to lossless PNG (the CPU is then the limit; the
compression releases the GIL, so the threads run on every core). A set's index row is appended, in
set order, once all of its images are written, and flushed at once (a `kill -9` loses nothing that
was flushed); the take's filesystem (only it: syncfs, not every disk of the host) is synced every
`sync_interval` seconds, so a power cut loses at most that much. The first write error (a full
disk) stops the recording: the index keeps every set written before it.
"""
from __future__ import annotations

import datetime as _dt
import errno
import fcntl
import json
import mmap
import os
import queue
import shutil
import sys
import threading
import time
from pathlib import Path
from typing import Optional

from common.files import atomic_write_json
from rig.errors import StorageError
from rig.storage.layout import CALIBRATION_COPY, CODECS, CONFIG_COPY, FRAMES, INDEX, META, CameraEntry, SequenceMeta, stored_layout
from rig.storage.netpbm import encode_netpbm
from sync.frames import Frame, FrameSet

QUEUE_FRAMES = 32  # per camera: frames waiting for the disk before the recorder applies back-pressure


class _Queued:
    """A frame on its way to a writer thread, for set `n`; `taken` once a writer has it."""

    __slots__ = ("n", "frame", "taken")

    def __init__(self, n: int, frame: Frame):
        self.n, self.frame, self.taken = n, frame, False


class _FrameQueue(queue.Queue):
    """A camera's queue of frames to write. An item is marked taken in the same locked step that
    removes it, so an interrupted `write` can tell a frame that reached its queue from one that did not."""

    def _get(self):
        item = self.queue.popleft()
        if item is not None:
            item.taken = True
        return item


class SequenceWriter:
    def __init__(self, root: Path, cameras: list, rig_name: str = "", rate_hz: Optional[float] = None,
                 config_file: Optional[Path] = None, calibration_file: Optional[Path] = None,
                 extra: Optional[dict] = None, sync_interval: float = 0.5, codec: str = "raw",
                 encoders: Optional[int] = None, direct: bool = False):
        """`cameras`: CameraConfig-like objects (name, role, width, height, pixel_format). `codec`:
        raw (netpbm) or png (lossless); `encoders`: PNG threads per camera (default: the CPU count
        shared among the cameras, at least one each)."""
        if codec not in CODECS:
            raise StorageError(f"unknown codec {codec!r} (choose {', '.join(CODECS)})")
        self.root = Path(root)
        self.codec = codec
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
                entries.append(CameraEntry(c.name, c.role, c.width, c.height, c.pixel_format, ch, bps, codec, getattr(c, "trigger", None)))
            self.meta = SequenceMeta(entries, rig_name, rate_hz, _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                                     dict(extra or {}))
            atomic_write_json(self.root / META, self.meta.to_dict())
            if config_file is not None:
                shutil.copyfile(config_file, self.root / CONFIG_COPY)
            if calibration_file is not None:
                shutil.copyfile(calibration_file, self.root / CALIBRATION_COPY)
            self._index = open(self.root / INDEX, "ab", buffering=0)
            self._dir_fd = os.open(self.root, os.O_RDONLY)  # names the take's filesystem to syncfs
        except OSError as exc:
            raise StorageError(f"{self.root}: cannot create the sequence ({exc.strerror})") from None
        self.entries = {e.name: e for e in entries}
        # direct=True writes raw frames with O_DIRECT (no copy into the page cache); off by default:
        # on the benchmark's (virtual, shared) disk it measured no faster than buffered writes, and
        # slower in the last comparison (docs/sequence-format.md, "Recording speed")
        self.direct = codec == "raw" and direct and _direct_works(self.root)
        self.sync_interval = sync_interval
        self._lock = threading.Lock()
        self._pending: dict[int, dict] = {}  # set number -> {"row": ..., "left": n}
        self._next_row = 0
        self._n_sets = 0
        self.sets_written = 0
        self.complete_sets = 0
        self.frames_written = {e.name: 0 for e in entries}  # frames, bytes: of the indexed sets (what the take holds)
        self.bytes_written = 0
        self.raw_bytes = 0  # what the written frames hold uncompressed: bytes_written / raw_bytes is the compression
        self.encode_cpu_s = 0.0  # CPU time the writer threads spent compressing
        self.error: Optional[StorageError] = None
        self._queues = {e.name: _FrameQueue(maxsize=QUEUE_FRAMES) for e in entries}
        if encoders:
            per_camera = encoders
        elif codec == "png":
            per_camera = max(1, (os.cpu_count() or 1) // max(1, len(entries)))
        else:
            # one sequential stream of large writes per camera: the disk is the limit (two or four
            # O_DIRECT writers per camera measured no faster on the benchmark's disk)
            per_camera = 1
        self._per_camera = per_camera
        self._threads = [threading.Thread(target=self._writer, args=(name,), name=f"writer-{name}-{k}", daemon=True)
                         for name in self._queues for k in range(per_camera)]
        self._stop_sync = threading.Event()
        self._threads.append(threading.Thread(target=self._syncer, name="sequence-sync", daemon=True))
        for t in self._threads:
            t.start()

    def _syncer(self) -> None:
        """Push written images and rows to the disk regularly: a power cut loses at most one interval."""
        while not self._stop_sync.wait(self.sync_interval):
            _syncfs(self._dir_fd)

    def backlog(self) -> int:
        """Frames queued for the disk, not yet written (the writer is behind by this many)."""
        return sum(q.qsize() for q in self._queues.values())

    # --- producer side ----------------------------------------------------------------------------
    def write(self, fs: FrameSet) -> bool:
        """Queue one FrameSet; returns False once the recording has stopped on an error."""
        if self.error is not None:
            return False
        present = [(name, f) for name, f in fs.frames.items() if f is not None]
        for name, _ in present:
            if name not in self._queues:
                raise StorageError(f"frame from camera '{name}' that the sequence does not record")
        n = self._n_sets
        self._n_sets += 1
        row = {"set": n, "trigger": fs.index, "host_ts_ns": fs.host_ts_ns, "frames": {}}
        for name in self.entries:
            row["frames"][name] = None  # a camera absent from the set is a marked gap
        with self._lock:
            self._pending[n] = {"row": row, "left": len(present), "complete": len(present) == len(self.entries), "bytes": 0, "raw": 0}
        items = [(name, _Queued(n, frame)) for name, frame in present]
        try:
            for name, item in items:
                self._queues[name].put(item)  # blocks when the disk falls behind: back-pressure
        except KeyboardInterrupt:
            # Ctrl-C (or `kill`, which `rig record` turns into the same) while waiting for room: the
            # take ends by writing what is in flight, this set's frames too; then the interrupt goes on
            try:
                for name, item in items:
                    if not self._queued(name, item):
                        self._queues[name].put(item)
            except BaseException:
                self._unqueued(n, items)  # interrupted again: what is queued is written, the rest are gaps
                raise
            raise
        except BaseException:
            self._unqueued(n, items)
            raise
        if not present:
            self._complete_rows()
        return self.error is None

    def _queued(self, name: str, item: "_Queued") -> bool:
        """Whether the frame reached its queue (it is there, or a writer has taken it)."""
        q = self._queues[name]
        with q.mutex:  # a writer takes an item (and marks it taken) under this lock
            return item.taken or any(x is item for x in q.queue)

    def _unqueued(self, n: int, items: list) -> None:
        """Mark set `n`'s frames that never reached their queue as missing, so that its row, and every
        row after it, is still written once the queued images are (an interrupted `write`)."""
        lost = sum(not self._queued(name, item) for name, item in items)
        if lost:
            with self._lock:
                p = self._pending[n]
                p["left"] -= lost
                p["complete"] = False
                self._flush_ready_rows()

    def close(self) -> None:
        for q in self._queues.values():
            for _ in range(self._per_camera):
                q.put(None)
        self._stop_sync.set()
        for t in self._threads:
            t.join()
        with self._lock:
            self._flush_ready_rows(force_sync=True)
        try:
            self._index.close()
            os.close(self._dir_fd)
        except OSError:
            pass

    # --- writer threads ---------------------------------------------------------------------------
    def _writer(self, name: str) -> None:
        q = self._queues[name]
        folder = self.root / FRAMES / name
        encoder = None
        if self.codec == "png":
            from rig.storage.png import PngEncoder

            e = self.entries[name]
            encoder = PngEncoder(e.width, e.height, e.channels, e.bytes_per_sample)
        staging = _DirectStaging(self.entries[name].frame_bytes) if encoder is None and self.direct else None
        while True:
            item = q.get()
            if item is None:
                return
            n, frame = item.n, item.frame
            if self.error is not None:
                continue  # drain: nothing more is written after the first failure
            rel = f"{FRAMES}/{name}/{frame.frame_id:08d}{self.entries[name].suffix}"
            try:
                nbytes = self._write_image(folder / rel.rsplit("/", 1)[1], frame, encoder, staging)
            except OSError as exc:
                self._fail(exc, folder / rel.rsplit("/", 1)[1])
                continue
            except Exception as exc:  # an image the encoder rejects: stop as on a write error, never silently
                self._fail(OSError(errno.EINVAL, f"cannot encode the frame ({exc})"), folder / rel.rsplit("/", 1)[1])
                continue
            rec = {"frame_id": frame.frame_id, "device_ts_ns": frame.device_ts_ns, "host_ts_ns": frame.host_ts_ns, "file": rel}
            if frame.sim_time_s is not None:
                rec["sim_time_s"] = frame.sim_time_s
            with self._lock:
                p = self._pending[n]
                p["row"]["frames"][name] = rec
                p["bytes"] += nbytes
                p["raw"] += self.entries[name].raw_bytes
                p["left"] -= 1
                if p["left"] == 0:
                    self._flush_ready_rows()

    def _write_image(self, path: Path, frame: Frame, encoder=None, staging=None) -> int:
        stored = self.entries[frame.camera].stored(frame.image)
        if staging is not None:
            return staging.write(path, encode_netpbm(stored))
        if encoder is not None:
            t0 = time.thread_time()
            parts = [encoder.encode(stored)]
            spent = time.thread_time() - t0
            with self._lock:
                self.encode_cpu_s += spent
        else:
            parts = list(encode_netpbm(stored))
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            return _write_all(fd, parts)
        finally:
            os.close(fd)

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
            # counted once the row is in the index: a frame written for a set that a failure kept
            # out of the index (another camera's frame hit the full disk) is not in the take
            for name, rec in p["row"]["frames"].items():
                self.frames_written[name] += rec is not None
            self.bytes_written += p["bytes"]
            self.raw_bytes += p["raw"]
            self._next_row += 1
        try:
            if lines:
                _write_all(self._index.fileno(), [("\n".join(lines) + "\n").encode()])
            if force_sync:
                _syncfs(self._dir_fd)
        except OSError as exc:
            if self.error is None:
                self.error = StorageError(f"{self.root / INDEX}: write failed ({exc.strerror}); recording stopped")


def _write_all(fd: int, parts: list) -> int:
    """Write the buffers in order, as one system call where the kernel takes them all (a netpbm
    header and its pixels: one writev, no copy of the pixels); returns the bytes written."""
    views = [memoryview(p).cast("B") for p in parts]
    total = sum(v.nbytes for v in views)
    while views:
        n = os.writev(fd, views)
        while views and n >= views[0].nbytes:
            n -= views[0].nbytes
            views.pop(0)
        if views and n:
            views[0] = views[0][n:]
    return total


_ALIGN = 4096  # O_DIRECT: buffer address, file offset and length in multiples of the logical block (4096 covers them all)


def _direct_works(folder: Path) -> bool:
    """Whether files in `folder` can be written with O_DIRECT (not on tmpfs before Linux 6.6, not off Linux)."""
    if not hasattr(os, "O_DIRECT"):
        return False
    path = folder / ".direct-test"
    buf = mmap.mmap(-1, _ALIGN)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_DIRECT, 0o644)
        try:
            os.write(fd, buf)
        finally:
            os.close(fd)
        return True
    except OSError:
        return False
    finally:
        buf.close()
        try:
            path.unlink()
        except OSError:
            pass


class _DirectStaging:
    """One writer thread's page-aligned buffer: a frame's header and pixels are copied into it (one
    memcpy, instead of the kernel's copy into the page cache), its whole blocks written with
    O_DIRECT, the last partial block buffered. The file is as a buffered write leaves it: a row
    names it only after both writes return, and the filesystem sync covers the tail."""

    def __init__(self, frame_bytes: int):
        self.size = -(-frame_bytes // _ALIGN) * _ALIGN
        self.buf = mmap.mmap(-1, self.size)
        self.view = memoryview(self.buf)

    def write(self, path: Path, parts) -> int:
        n = 0
        for p in parts:
            p = memoryview(p).cast("B")
            self.view[n:n + p.nbytes] = p
            n += p.nbytes
        whole = n // _ALIGN * _ALIGN
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_DIRECT, 0o644)
        try:
            if whole:
                _write_all(fd, [self.view[:whole]])
            if n > whole:
                fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_DIRECT)
                _write_all(fd, [self.view[whole:n]])
        finally:
            os.close(fd)
        return n


def _load_syncfs():
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.syncfs
        fn.argtypes = [ctypes.c_int]
        return fn
    except (OSError, AttributeError):
        return None


_SYNCFS = _load_syncfs()


def _syncfs(fd: int) -> None:
    """Push the take's filesystem to its disk: syncfs(2) where there is one, else sync(2) (every
    filesystem of the host). A sync(2) waits for other programs' and other disks' data too."""
    if _SYNCFS is None or _SYNCFS(fd) != 0:
        os.sync()
