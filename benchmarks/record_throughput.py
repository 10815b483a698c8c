"""Recording throughput: the highest sustained rate (sets/s) at which the sequence writer keeps up with
two 1920x1080 RGB cameras without losing a frame, against the disk's own sequential write speed
measured in the same run, on the same filesystem (both timed until the data is synced to the disk).

Method: FrameSets of fresh frames (pre-generated noise images, so producing them costs nothing) are
offered at a fixed rate for a few seconds; the rate is sustained if every set was accepted on time
(the writer never pushed back for longer than one set period), every frame is in the index, and
the writer had caught up within a second (or 10% of the trial) of the last set: the disk, not the
page cache, kept pace.
The rate is raised until it is not sustained; the best sustained rate is reported.

    .venv/bin/python benchmarks/record_throughput.py [--dir /path/on/the/disk] [--seconds 4] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rig.storage.recorder import SequenceWriter  # noqa: E402
from rig.storage.validate import validate  # noqa: E402
from sync.frames import Frame, FrameSet  # noqa: E402

W, H = 1920, 1080


def disk_write_speed(folder: Path, total_mb: int = 4096, chunk_mb: int = 8) -> float:
    """Sequential write of one large file in 8 MB chunks, timed until fsync returns (MB/s)."""
    path = folder / "disk-speed.bin"
    chunk = np.random.default_rng(1).integers(0, 256, chunk_mb << 20, dtype=np.uint8).tobytes()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    t0 = time.monotonic()
    try:
        for _ in range(total_mb // chunk_mb):
            os.write(fd, chunk)
        os.fsync(fd)
    finally:
        os.close(fd)
    elapsed = time.monotonic() - t0
    path.unlink()
    return total_mb * (1 << 20) / 1e6 / elapsed


def run_rate(folder: Path, rate: float, seconds: float, images: list[np.ndarray]) -> dict:
    cams = [SimpleNamespace(name=n, role=n, width=W, height=H, pixel_format="RGB8") for n in ("left", "right")]
    root = folder / f"seq-{rate:g}"
    writer = SequenceWriter(root, cams, rate_hz=rate)
    period = 1.0 / rate
    n_sets = max(1, int(seconds * rate))
    late = 0
    t0 = time.monotonic()
    for i in range(n_sets):
        due = t0 + i * period
        now = time.monotonic()
        if now < due:
            time.sleep(due - now)
        elif now - due > period:
            late += 1  # the writer held the producer up by more than a set period: frames would be lost
        ts = time.monotonic_ns()
        frames = {c.name: Frame(images[(2 * i + k) % len(images)], c.name, i + 1, ts, ts, "RGB8") for k, c in enumerate(cams)}
        writer.write(FrameSet(i, frames, ts))
    produce_s = time.monotonic() - t0
    writer.close()  # waits for the writers and syncs: the disk must have kept pace, not the page cache
    elapsed = time.monotonic() - t0
    v = validate(root)
    written = sum(v.frames.values())
    shutil.rmtree(root)
    backlog_s = elapsed - produce_s  # what was still unwritten when the last set was offered
    ok = late == 0 and written == 2 * n_sets and writer.error is None and backlog_s <= max(1.0, 0.1 * seconds)
    return {"rate": rate, "sets": n_sets, "late": late, "frames_written": written, "sustained": ok,
            "backlog_s": round(backlog_s, 3), "mb_per_s": writer.bytes_written / 1e6 / elapsed}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", type=Path, default=None, help="folder on the disk to measure (default: a temp folder)")
    ap.add_argument("--seconds", type=float, default=8.0, help="length of each trial")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="record-bench-", dir=args.dir))
    try:
        rng = np.random.default_rng(0)
        images = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(8)]
        disk_runs = [disk_write_speed(folder)]
        frame_mb = (W * H * 3) / 1e6
        trials = []
        best = None
        rate = 5.0
        while rate <= 1000:
            r = run_rate(folder, rate, args.seconds, images)
            trials.append(r)
            if not args.json:
                print(f"  {rate:6.1f} sets/s: {'sustained' if r['sustained'] else 'NOT sustained'} "
                      f"({r['late']} late, {r['frames_written']}/{2 * r['sets']} frames, {r['mb_per_s']:.0f} MB/s)")
            if not r["sustained"]:
                break
            best = r
            rate *= 1.15
        disk_runs.append(disk_write_speed(folder))  # again after the trials: the disk's speed varies
        disk = max(disk_runs)
        disk_sets = disk / (2 * frame_mb)
        result = {
            "frame": f"{W}x{H} RGB8 x 2 cameras",
            "best_sustained_sets_per_s": best["rate"] if best else 0.0,
            "best_mb_per_s": best["mb_per_s"] if best else 0.0,
            "disk_write_mb_per_s": disk,
            "disk_write_runs_mb_per_s": disk_runs,
            "disk_limit_sets_per_s": disk_sets,
            "ratio": (best["rate"] / disk_sets) if best else 0.0,
            "trials": trials,
        }
        if args.json:
            print(json.dumps(result))
        else:
            print(f"disk sequential write: {disk:.0f} MB/s (best of {', '.join(f'{d:.0f}' for d in disk_runs)}) = {disk_sets:.1f} sets/s of 2 x {W}x{H} RGB")
            print(f"recorder: {result['best_sustained_sets_per_s']:.1f} sets/s sustained without loss "
                  f"({result['best_mb_per_s']:.0f} MB/s), {100 * result['ratio']:.0f}% of the disk's limit")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
