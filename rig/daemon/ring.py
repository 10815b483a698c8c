"""A camera's frame ring: slots of frames in a shared-memory file, one writer, any number of readers.

The camera daemon creates the file (/dev/shm/rig/<rig>/<camera> by default: `default_path`), maps it
read-write and copies each frame once, straight from the camera's array into a slot. Readers open
the file read-only, map it with ACCESS_READ and copy out only the frames they ask for. Readers never
write, so one that dies (even SIGKILLed mid-read) leaves the ring as it was.

Why a plain file and not `multiprocessing.shared_memory`: on Python 3.11 a process that attaches to
a SharedMemory segment registers it with its resource tracker, which unlinks it when that process
exits (CPython gh-82300), so one reader's exit would take the ring away from everyone. A file under
/dev/shm is the same memory, with lifetime rules we control: the writer creates it (header written
and file sized under a temporary name, then os.replace, so no reader ever maps a half-made file) and
removes it on close(unlink=True).

Layout, little-endian, every section 64-byte aligned:

  header (HEADER_SIZE = 192 bytes)
    0   magic           8s   b"RIGRING\\0"
    8   version         u32  VERSION
    12  slots           u32
    16  height          u32
    20  width           u32
    24  channels        u32  1: frames are HxW, else HxWxC
    28  dtype code      u32  1 = uint8, 2 = uint16
    32  pixel format    16s  ASCII, NUL-padded (the camera's configured format, e.g. "BayerRG8")
    48  camera          64s  UTF-8, NUL-padded
    112 writer pid      i64
    120 heartbeat ns    i64  time.monotonic_ns() of the writer's last heartbeat() or write()
    128 write sequence  u64  frames written so far; frame k (from 0) lives in slot k % slots
    136 created ns      i64  time.time_ns() at creation
    144 closed          u32  1 once the writer closed cleanly
    152 slot stride     u64  bytes from one slot to the next
    160 (reserved, zero)
  slot i at HEADER_SIZE + i * stride
    0   lock            u64  sequence lock: 2k+1 while frame k is written, 2k+2 once it is complete
    8   seq             u64  k
    16  frame_id        i64
    24  device_ts_ns    i64
    32  host_ts_ns      i64
    40  trigger_index   i64  -1 = None
    48  exposure_us     f64  NaN = None
    56  sim_time_s      f64  NaN = None
    64  pixel_format    u32  index into sync.frames.PIXEL_FORMATS
    72  progress        u64  k * 65536 + rows of frame k's pixels copied in so far (while it is written)
    128 pixels          height*width*channels*itemsize, C order; stride = 128 + that, rounded up to 64

Sequence lock: the writer stores 2k+1, writes metadata and pixels, stores 2k+2, then the header's
write sequence k+1. A reader of frame k loads the lock (2k+2 or it is not there: smaller = not
written yet, larger = overwritten), copies, and loads the lock again: unchanged = a whole frame,
changed = the writer started frame k+slots over it while we copied, so frame k is gone (the lock only
grows, a retry could only confirm it): FrameOverwritten, never torn pixels. x86 keeps stores in
program order (TSO), so the order above is what other cores see. On weakly ordered CPUs (ARM) the lock
is still checked on both sides, but Python offers no explicit fence; the lock and the data are kept
as separate numpy assignments (each an aligned 8-byte store for the lock words) to give the best
order a Python process can.

Streaming read: the writer copies the pixels in bands of rows and says after each how many rows of
frame k are in (`progress`). A reader that finds frame k being written copies each band as soon as
it is in, so its copy out runs alongside the writer's copy in instead of after it (for 1280x720 RGB
that is most of the 0.2-0.4 ms the copy out takes), then checks the lock as above: 2k+2 = frame k
complete and its slot not reused, so every band it copied was frame k's.
"""
from __future__ import annotations

import math
import mmap
import os
import struct
import tempfile
import time
from pathlib import Path
from typing import Callable, Optional, Union

import numpy as np

from common.errors import ReportedError
from rig.daemon import paths
from sync.frames import PIXEL_FORMATS, Frame

MAGIC = b"RIGRING\0"
VERSION = 2  # 2: the progress word (streaming reads)
HEADER = struct.Struct("<8sIIIIII16s64sqqQqI4xQ")  # offsets above; HEADER.size == 160
HEADER_SIZE = 192
HEARTBEAT_AT, SEQ_AT, CLOSED_AT = 120, 128, 144
PIXELS_AT = 128  # within a slot
PROGRESS_AT = 72  # within a slot
ROWS = 65536  # progress = k * ROWS + rows copied (a frame has fewer than ROWS rows)
BANDS = 8  # the writer copies a frame in this many bands of rows
STREAM_WAIT_S = 0.05  # how long a streaming reader waits for the writer's next band before it gives up
DTYPES = {1: np.dtype("<u1"), 2: np.dtype("<u2")}
SLOT_META = np.dtype({"names": ["seq", "frame_id", "device_ts_ns", "host_ts_ns", "trigger_index", "exposure_us",
                                "sim_time_s", "pixel_format"],
                      "formats": ["<u8", "<i8", "<i8", "<i8", "<i8", "<f8", "<f8", "<u4"],
                      "offsets": [8, 16, 24, 32, 40, 48, 56, 64], "itemsize": 72})
PathLike = Union[str, os.PathLike]


class RingError(ReportedError):
    exit_code = 2


class RingLayoutError(RingError):
    """The file is not a frame ring this code can read: wrong magic, another version, truncated."""


class FrameNotReady(RingError):
    """The frame asked for has not been written (completely) yet."""


class FrameOverwritten(RingError):
    """The frame asked for is gone: the writer reused its slot (before or while it was read)."""


def default_path(rig: str, camera: str) -> Path:
    """/dev/shm/rig/<rig>/<camera> ($RIG_SHM_ROOT instead of /dev/shm/rig): rig.daemon.paths."""
    return paths.ring_path(rig, camera)


def _align(n: int) -> int:
    return (n + 63) // 64 * 64


def file_size(slots: int, height: int, width: int, channels: int, itemsize: int) -> int:
    """Bytes of a ring file of this geometry (what `create` sizes it to): `rig doctor` weighs the rings
    a rig's daemons will create against the room in /dev/shm."""
    return HEADER_SIZE + slots * _align(PIXELS_AT + height * width * channels * itemsize)


class _Mapped:
    """What writer and reader share: the geometry, and numpy views over the mapping."""

    def _map(self, mm: mmap.mmap, slots: int, shape: tuple, dtype: np.dtype, stride: int) -> None:
        self._mm, self.slots, self.shape, self.dtype, self._stride = mm, slots, shape, dtype, stride
        word = lambda fmt, at: np.ndarray((), fmt, buffer=mm, offset=at)  # noqa: E731
        self._heartbeat, self._seq, self._closed = word("<i8", HEARTBEAT_AT), word("<u8", SEQ_AT), word("<u4", CLOSED_AT)
        self._locks = np.ndarray((slots,), "<u8", buffer=mm, offset=HEADER_SIZE, strides=(stride,))
        self._meta = np.ndarray((slots,), SLOT_META, buffer=mm, offset=HEADER_SIZE, strides=(stride,))
        self._progress = np.ndarray((slots,), "<u8", buffer=mm, offset=HEADER_SIZE + PROGRESS_AT, strides=(stride,))
        inner = np.empty(shape, dtype).strides
        self._pixels = np.ndarray((slots, *shape), dtype, buffer=mm, offset=HEADER_SIZE + PIXELS_AT,
                                  strides=(stride, *inner))

    def _unmap(self) -> None:
        if self._mm is None:
            return
        mm = self._mm
        self._mm = self._heartbeat = self._seq = self._closed = self._locks = self._meta = self._progress = self._pixels = None
        try:
            mm.close()
        except BufferError:  # a view someone still holds: the mapping goes with it
            pass

    def latest(self) -> int:
        """The write sequence: frames written so far (the newest is latest() - 1)."""
        return int(self._seq)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class FrameRing(_Mapped):
    """The writer: creates the ring file and owns it."""

    @classmethod
    def create(cls, path: PathLike, *, slots: int, height: int, width: int, channels: int, dtype, pixel_format: str,
               camera: str) -> "FrameRing":
        path = Path(path)
        code = next((c for c, d in DTYPES.items() if d == np.dtype(dtype)), None)
        if code is None:
            raise RingError(f"{path}: frame dtype {np.dtype(dtype)} is not supported (uint8 or uint16)")
        if height >= ROWS:
            raise RingError(f"{path}: frames of {height} rows: at most {ROWS - 1}")
        if min(slots, height, width, channels) < 1:
            raise RingError(f"{path}: slots, height, width and channels must be >= 1 "
                            f"(got {slots}, {height}, {width}, {channels})")
        fmt, name = pixel_format.encode("ascii", "replace"), camera.encode("utf-8")
        if len(fmt) > 16 or len(name) > 64:
            raise RingError(f"{path}: pixel format {pixel_format!r} (16 bytes at most) or camera name {camera!r} "
                            f"(64 bytes UTF-8 at most) is too long")
        shape = (height, width) if channels == 1 else (height, width, channels)
        stride = _align(PIXELS_AT + height * width * channels * DTYPES[code].itemsize)
        size = file_size(slots, height, width, channels, DTYPES[code].itemsize)
        path.parent.mkdir(mode=0o755, parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            os.fchmod(fd, 0o644)
            os.ftruncate(fd, size)
            mm = mmap.mmap(fd, size, access=mmap.ACCESS_WRITE)
            HEADER.pack_into(mm, 0, MAGIC, VERSION, slots, height, width, channels, code, fmt, name, os.getpid(),
                             time.monotonic_ns(), 0, time.time_ns(), 0, stride)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        finally:
            ino = os.fstat(fd).st_ino
            os.close(fd)  # the mapping keeps the file
        ring = cls()
        ring.path, ring.camera, ring.pixel_format, ring._ino, ring._next = path, camera, pixel_format, ino, 0
        ring._map(mm, slots, shape, DTYPES[code], stride)
        return ring

    def write(self, frame: Frame, started: Optional[Callable[[], None]] = None) -> int:
        """Copies `frame` into the next slot; returns its sequence number k. `started()` is called
        once the slot is marked as being written, before the pixels are copied."""
        if self._mm is None:
            raise RingError(f"{self.path}: the ring is closed")
        image = frame.image
        if image.shape != self.shape or image.dtype != self.dtype:
            raise RingError(f"{self.path}: frame of shape {image.shape} {image.dtype} does not fit the ring's "
                            f"{self.shape} {self.dtype}")
        try:
            fmt = PIXEL_FORMATS.index(frame.pixel_format)
        except ValueError:
            raise RingError(f"{self.path}: unknown pixel format {frame.pixel_format!r} "
                            f"(one of {', '.join(PIXEL_FORMATS)})") from None
        k = self._next
        meta = (k, frame.frame_id, frame.device_ts_ns, frame.host_ts_ns,
                -1 if frame.trigger_index is None else frame.trigger_index,
                math.nan if frame.exposure_us is None else frame.exposure_us,
                math.nan if frame.sim_time_s is None else frame.sim_time_s, fmt)
        i = k % self.slots
        self._locks[i] = 2 * k + 1  # odd: being written
        self._meta[i] = meta
        self._progress[i] = k * ROWS
        if started is not None:
            started()
        slot, rows = self._pixels[i], self.shape[0]
        step = -(-rows // BANDS)
        for r in range(step, rows + step, step):  # in bands, saying after each how far it got (streaming readers)
            r = min(r, rows)
            np.copyto(slot[r - step:r], image[r - step:r])
            self._progress[i] = k * ROWS + r
        self._locks[i] = 2 * k + 2  # even: frame k complete
        self._seq[...] = k + 1
        self._heartbeat[...] = time.monotonic_ns()
        self._next = k + 1
        return k

    def heartbeat(self) -> None:
        if self._mm is not None:
            self._heartbeat[...] = time.monotonic_ns()

    def close(self, unlink: bool = True) -> None:
        """Marks the ring closed (readers see it), unmaps it, and removes the file (if it is still ours)."""
        if self._mm is None:
            return
        self._closed[...] = 1
        self._unmap()
        if unlink:
            try:
                if os.stat(self.path).st_ino == self._ino:  # not a newer writer's ring under the same name
                    self.path.unlink()
            except FileNotFoundError:
                pass


class RingReader(_Mapped):
    """A reader: maps a ring read-only and copies frames out of it."""

    @classmethod
    def attach(cls, path: PathLike) -> "RingReader":
        path = Path(path)
        try:
            with open(path, "rb") as f:
                head = f.read(HEADER_SIZE)
                size = os.fstat(f.fileno()).st_size
                if not head:
                    raise RingLayoutError(f"{path}: not a frame ring (an empty file)")
                if head[:8] != MAGIC:
                    raise RingLayoutError(f"{path}: not a frame ring (wrong magic {head[:8]!r})")
                version = int.from_bytes(head[8:12], "little")
                if version != VERSION:
                    raise RingLayoutError(f"{path}: frame ring layout version {version}, this reader knows {VERSION}")
                if len(head) < HEADER_SIZE:
                    raise RingLayoutError(f"{path}: truncated frame ring ({size} bytes, the header alone is {HEADER_SIZE})")
                (_, _, slots, height, width, channels, code, fmt, name, pid, _, _, created, _,
                 stride) = HEADER.unpack_from(head)
                if code not in DTYPES or not slots or stride < _align(PIXELS_AT + height * width * channels * DTYPES[code].itemsize):
                    raise RingLayoutError(f"{path}: corrupt frame ring header (dtype code {code}, {slots} slots, "
                                          f"{height}x{width}x{channels}, stride {stride})")
                want = HEADER_SIZE + slots * stride
                if size != want:
                    raise RingLayoutError(f"{path}: truncated frame ring ({size} bytes, its header says {want})")
                mm = mmap.mmap(f.fileno(), want, access=mmap.ACCESS_READ)
        except FileNotFoundError:
            raise RingError(f"{path}: no frame ring (is the camera daemon running?)") from None
        except (IsADirectoryError, PermissionError) as exc:
            raise RingError(f"{path}: cannot open the frame ring ({exc.strerror})") from None
        reader = cls()
        reader.path, reader.pid, reader.created_ns = path, pid, created
        reader.pixel_format = fmt.rstrip(b"\0").decode("ascii", "replace")
        reader.camera = name.rstrip(b"\0").decode("utf-8", "replace")
        reader._map(mm, slots, (height, width) if channels == 1 else (height, width, channels), DTYPES[code], stride)
        return reader

    @property
    def heartbeat_ns(self) -> int:
        return int(self._heartbeat)

    @property
    def write_seq(self) -> int:
        return int(self._seq)

    @property
    def closed(self) -> bool:
        return bool(self._closed)

    def read(self, k: int) -> Frame:
        """Frame k (its image a copy); FrameNotReady if not written yet, FrameOverwritten if gone."""
        return self.read_into(k, np.empty(self.shape, self.dtype))

    def read_into(self, k: int, out: np.ndarray) -> Frame:
        """As read(), copying the pixels into `out` (the ring's shape and dtype), the returned Frame's image."""
        if self._mm is None:
            raise RingError(f"{self.path}: the reader is closed")
        if k < 0:
            raise FrameOverwritten(f"{self.path}: there is no frame {k}")
        i, want = k % self.slots, 2 * k + 2
        before = int(self._locks[i])
        streamed = False
        if before == want - 1:  # being written: copy it band by band behind the writer
            streamed = self._stream(i, k, out)
            before = int(self._locks[i])
            if before == want - 1:
                raise FrameNotReady(f"{self.path}: frame {k} is still being written")
        if before < want:
            raise FrameNotReady(f"{self.path}: frame {k} is not written yet ({self.write_seq} so far)")
        if before > want:
            raise FrameOverwritten(f"{self.path}: frame {k} was overwritten (the ring holds {self.slots})")
        meta = self._meta[i].item()  # a tuple of Python values: a copy
        if not streamed:
            np.copyto(out, self._pixels[i])
        else:
            self.streamed += 1
        if int(self._locks[i]) != before or meta[0] != k:  # the writer reused the slot while we copied
            raise FrameOverwritten(f"{self.path}: frame {k} was overwritten while it was read")
        _, frame_id, device_ts, host_ts, trigger, exposure, sim_time, fmt = meta
        return Frame(image=out, camera=self.camera, frame_id=frame_id, device_ts_ns=device_ts, host_ts_ns=host_ts,
                     pixel_format=PIXEL_FORMATS[fmt] if fmt < len(PIXEL_FORMATS) else str(fmt),
                     exposure_us=None if math.isnan(exposure) else exposure,
                     trigger_index=None if trigger == -1 else trigger,
                     sim_time_s=None if math.isnan(sim_time) else sim_time)

    streamed = 0  # frames read while they were written

    def _stream(self, i: int, k: int, out: np.ndarray) -> bool:
        """Copies frame k's rows out of slot i as the writer puts them in; True once every row is
        copied (whole if the slot's lock is then 2k+2: read_into checks), False when the writer moved
        on or stalled. Waits for the writer's next band by yielding the CPU, at most STREAM_WAIT_S each."""
        src, rows, done = self._pixels[i], self.shape[0], 0
        give_up = time.monotonic() + STREAM_WAIT_S
        while done < rows:
            p = int(self._progress[i])
            if p // ROWS == k and p % ROWS > done:
                upto = p % ROWS
                np.copyto(out[done:upto], src[done:upto])
                done, give_up = upto, time.monotonic() + STREAM_WAIT_S
                continue
            if int(self._locks[i]) != 2 * k + 1 or time.monotonic() > give_up:
                return False  # the writer moved on (or stalled): read_into copies or refuses by the lock
            time.sleep(0)
        while int(self._locks[i]) == 2 * k + 1 and time.monotonic() < give_up:
            time.sleep(0)  # the last band is in; the lock's 2k+2 follows at once
        return True

    def writing(self, k: int) -> bool:
        """Frame k is being copied into its slot right now."""
        return self._mm is not None and k >= 0 and int(self._locks[k % self.slots]) == 2 * k + 1

    def wait(self, k: int, timeout: float) -> bool:
        """True once frame k is written (False after `timeout` s): polls, sleeping 0.2 ms up to 2 ms."""
        deadline, nap = time.monotonic() + timeout, 0.0002
        while True:
            if int(self._seq) > k:
                return True
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            time.sleep(min(nap, left))
            nap = min(nap * 2, 0.002)

    def writer_alive(self, stale_s: float = 2.0) -> bool:
        """The writer's process exists, its heartbeat is younger than `stale_s` and it has not closed."""
        if self.closed or time.monotonic_ns() - self.heartbeat_ns > stale_s * 1e9:
            return False
        return paths.pid_alive(self.pid)

    def close(self) -> None:
        self._unmap()
