"""Can this disk keep up with this rig? The rig's data rate from its config, and the disk's
sequential write rate measured by a short, bounded test file in the output folder (removed after).

    need = rig_data_rate(cfg)              # bytes/s the cameras deliver, as stored raw
    disk = measure_write_rate(folder)      # bytes/s this disk takes, synced (None: too little free space to measure)

The test writes large aligned blocks with O_DIRECT where the filesystem allows it (the page cache
would otherwise take the first gigabytes at memory speed and say nothing of the disk), else
buffered writes timed until fsync returns. It stops after `seconds` or `max_bytes`, whichever comes
first, and never takes more than a quarter of the free space.
"""
from __future__ import annotations

import mmap
import os
import secrets
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from rig.errors import StorageError
from rig.storage.layout import stored_layout

TEST_FILE = ".rig-disk-write-test"  # + "-PID-RANDOM.tmp": a name of its own, never a leftover's or another measurement's
CHUNK = 8 << 20  # large writes: what the recorder's frames are, and what a disk streams fastest


class DiskTooSlow(StorageError):
    """The rig delivers more bytes per second than the output disk takes (refused before the take)."""

    exit_code = 2


@dataclass
class DiskRate:
    bytes_per_s: float
    bytes: int  # written by the test
    seconds: float  # until the data was on the disk
    direct: bool  # O_DIRECT (the page cache bypassed) or buffered with fsync


def camera_rate_hz(cfg, cam) -> float:
    """Frames per second a camera delivers in a take: the board's rate for triggered cameras."""
    if cfg.trigger is not None and cam.trigger in ("hardware", "software"):
        return float(cfg.trigger.rate_hz)
    return float(cam.fps)


def camera_data_rate(cfg, cam) -> float:
    """Bytes per second one camera's frames take on disk, stored raw (width x height x samples x
    bytes per sample x rate; Bayer mosaics are stored at one sample per pixel)."""
    channels, bps = stored_layout(cam.pixel_format)
    return cam.width * cam.height * channels * bps * camera_rate_hz(cfg, cam)


def rig_data_rate(cfg, cameras=None) -> float:
    """Bytes per second the cameras take on disk, raw: `cameras` (`rig record` passes those that send
    frames to the host, not cameras recording to their own card), by default all of the rig's."""
    return sum(camera_data_rate(cfg, c) for c in (cfg.cameras if cameras is None else cameras))


def nearest_existing_folder(path: Path) -> Path:
    p = Path(path).absolute()
    while not p.is_dir() and p != p.parent:
        p = p.parent
    return p


def measure_write_rate(folder: str | os.PathLike, seconds: float = 0.5, max_bytes: int = 256 << 20) -> Optional[DiskRate]:
    """The disk's sequential write rate in `folder` (or its nearest existing parent), or None when
    the free space is too small to measure anything (under 4 MB free, a megabyte of test). Raises StorageError when the
    folder cannot be written at all."""
    folder = nearest_existing_folder(Path(folder))
    free = shutil.disk_usage(folder).free
    budget = min(max_bytes, free // 4) // mmap.PAGESIZE * mmap.PAGESIZE
    if budget < (1 << 20):
        return None
    chunk = min(CHUNK, budget)
    buf = mmap.mmap(-1, chunk)  # page-aligned, as O_DIRECT needs
    buf.write(os.urandom(1 << 16) * (chunk >> 16))  # not zeros: a compressing filesystem would flatter itself
    path = folder / f"{TEST_FILE}-{os.getpid()}-{secrets.token_hex(4)}.tmp"
    try:
        return _timed_write(path, buf, budget, seconds, direct=True) or _timed_write(path, buf, budget, seconds, direct=False)
    except OSError as exc:
        raise StorageError(f"{folder}: cannot measure the disk's write rate ({exc.strerror})") from None
    finally:
        buf.close()
        try:
            path.unlink()
        except OSError:
            pass


def _timed_write(path: Path, buf: mmap.mmap, budget: int, seconds: float, direct: bool) -> Optional[DiskRate]:
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
    if direct:
        if not hasattr(os, "O_DIRECT"):
            return None
        flags |= os.O_DIRECT
    try:
        fd = os.open(path, flags, 0o600)
    except OSError:
        if direct:
            return None  # the filesystem takes no O_DIRECT (tmpfs): measure buffered
        raise
    written = 0
    try:
        t0 = time.monotonic()
        while written < budget and (written == 0 or time.monotonic() - t0 < seconds):
            try:
                written += os.write(fd, memoryview(buf)[:min(len(buf), budget - written)])
            except OSError:
                if direct and written == 0:
                    return None  # O_DIRECT refused at the first write (alignment the filesystem wants)
                raise
        os.fsync(fd)
        elapsed = time.monotonic() - t0
    finally:
        os.close(fd)
    return DiskRate(written / elapsed, written, elapsed, direct)


def check_disk(cfg, folder: str | os.PathLike, ratio: float = 1.0, cameras=None) -> tuple[float, Optional[DiskRate]]:
    """(the rig's stored data rate in bytes/s, the disk's measured rate); raises DiskTooSlow when the
    disk is slower. `ratio`: how many times smaller compression stores the frames (1 for raw)."""
    need = rig_data_rate(cfg, cameras) / ratio
    # four seconds of the rig's data (16 MB at least, 256 MB at most): a small rig's take starts at
    # once, a fast one is measured over enough bytes to pass any cache
    disk = measure_write_rate(folder, max_bytes=int(min(256 << 20, max(16 << 20, 4 * need))))
    if disk is not None and need > disk.bytes_per_s:
        how = "" if ratio == 1.0 else f" at a compression ratio of {ratio:g}"
        raise DiskTooSlow(
            f"{nearest_existing_folder(Path(folder))}: the disk writes {disk.bytes_per_s / 1e6:.0f} MB/s (measured now), the rig "
            f"delivers {need / 1e6:.0f} MB/s{how}: frames would be lost; record to a faster disk, lower the rate or size, "
            f"record with --compress png (with --compress-ratio R, R measured on an earlier take), or skip this check with --no-disk-check")
    return need, disk
