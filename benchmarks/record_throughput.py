"""Recording throughput: the rate at which `rig record`'s sequence writer puts frames on the disk,
against the disk's own sequential write rate measured in the same run, on the same filesystem,
both timed until the data is synced to the disk.

- The disk: one large file written in 8 MB blocks, with O_DIRECT (the page cache bypassed) and
  buffered then fsync'd; the better of the two is the disk's rate.
- The recorder: FrameSets of two 1920x1080 RGB cameras (fresh noise images, made beforehand so that
  making them costs nothing) offered as fast as the writer takes them (its queues push back when the
  disk falls behind), the same number of bytes as the disk test, timed from the first set until
  `close()` has written every frame and index row and synced the take's filesystem. Then the take
  is validated: every frame must be in the index.
Disk and recorder runs alternate (disk, recorder, disk, ...): a shared or virtual disk's speed drifts,
and each recorder run is compared with the disk runs on either side of it.
- Paced: sets offered at a fixed fraction of the disk's rate (0.8 by default) for a few seconds; the
  rate is sustained when no set was held up by more than one set period, every frame is in the
  index, and the writer had caught up within a second of the last set.

    .venv/bin/python benchmarks/record_throughput.py [--dir /path/on/the/disk] [--gb 2] [--rounds 3] [--json]
"""
from __future__ import annotations

import argparse
import json
import mmap
import os
import shutil
import statistics
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
FRAME_BYTES = W * H * 3
CAMS = [SimpleNamespace(name=n, role=n, width=W, height=H, pixel_format="RGB8") for n in ("left", "right")]


def disk_write_speed(folder: Path, total: int, direct: bool, chunk: int = 8 << 20) -> float:
    """Sequential write of one file in 8 MB blocks, timed until fsync returns (MB/s)."""
    path = folder / "disk-speed.bin"
    buf = mmap.mmap(-1, chunk)
    buf.write(np.random.default_rng(1).integers(0, 256, chunk, dtype=np.uint8).tobytes())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | (os.O_DIRECT if direct else 0), 0o644)
    t0 = time.monotonic()
    try:
        for _ in range(total // chunk):
            os.write(fd, buf)
        os.fsync(fd)
    finally:
        os.close(fd)
        buf.close()
    elapsed = time.monotonic() - t0
    path.unlink()
    return total / 1e6 / elapsed


def disk_rate(folder: Path, total: int) -> dict:
    runs = {}
    for direct in (True, False):
        try:
            runs["direct" if direct else "buffered"] = disk_write_speed(folder, total, direct)
        except OSError:
            pass  # no O_DIRECT on this filesystem
    return {"mb_per_s": max(runs.values()), **{k: round(v, 1) for k, v in runs.items()}}


def make_set(i: int, images: list[np.ndarray]) -> FrameSet:
    ts = time.monotonic_ns()
    return FrameSet(i, {c.name: Frame(images[(2 * i + k) % len(images)], c.name, i + 1, ts, ts, "RGB8")
                        for k, c in enumerate(CAMS)}, ts)


def recorder_speed(folder: Path, total: int, images: list[np.ndarray], tag: str) -> dict:
    """Sets as fast as the writer takes them; MB/s until every frame is written and synced."""
    root = folder / f"seq-{tag}"
    n_sets = max(1, total // (2 * FRAME_BYTES))
    cpu0 = time.process_time()
    t0 = time.monotonic()
    writer = SequenceWriter(root, CAMS, rate_hz=30.0)
    for i in range(n_sets):
        writer.write(make_set(i, images))
    writer.close()
    elapsed = time.monotonic() - t0
    cpu = time.process_time() - cpu0
    v = validate(root)
    shutil.rmtree(root)
    assert writer.error is None and sum(v.frames.values()) == 2 * n_sets, (writer.error, v.frames)
    return {"mb_per_s": writer.bytes_written / 1e6 / elapsed, "sets": n_sets, "seconds": round(elapsed, 3),
            "cpu_percent_of_one_core": round(100 * cpu / elapsed, 1)}


def paced(folder: Path, rate: float, seconds: float, images: list[np.ndarray]) -> dict:
    root = folder / f"seq-paced-{rate:g}"
    writer = SequenceWriter(root, CAMS, rate_hz=rate)
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
        writer.write(make_set(i, images))
    produce_s = time.monotonic() - t0
    writer.close()
    elapsed = time.monotonic() - t0
    written = sum(validate(root).frames.values())
    shutil.rmtree(root)
    backlog_s = elapsed - produce_s
    ok = late == 0 and written == 2 * n_sets and writer.error is None and backlog_s <= 1.0
    return {"sets_per_s": round(rate, 2), "mb_per_s": round(2 * FRAME_BYTES * rate / 1e6, 1), "sets": n_sets, "late": late,
            "frames_written": written, "backlog_s": round(backlog_s, 3), "sustained": ok}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", type=Path, default=None, help="folder on the disk to measure (default: a temp folder)")
    ap.add_argument("--gb", type=float, default=2.0, help="bytes per run (disk test and recorder alike), in GB")
    ap.add_argument("--rounds", type=int, default=3, help="recorder runs (each between two disk runs)")
    ap.add_argument("--paced", type=float, default=0.8, help="also offer sets at this fraction of the disk's rate (0: skip)")
    ap.add_argument("--paced-seconds", type=float, default=6.0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    total = int(args.gb * 1e9) // (8 << 20) * (8 << 20)
    if args.dir is not None:
        args.dir.mkdir(parents=True, exist_ok=True)  # a folder not made yet on the disk to measure
    folder = Path(tempfile.mkdtemp(prefix="record-bench-", dir=args.dir))
    say = (lambda *a: None) if args.json else print
    try:
        rng = np.random.default_rng(0)
        images = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(8)]
        disks = [disk_rate(folder, total)]
        say(f"disk: {disks[-1]['mb_per_s']:.0f} MB/s (direct {disks[-1].get('direct')}, buffered {disks[-1].get('buffered')})")
        recs = []
        for k in range(args.rounds):
            recs.append(recorder_speed(folder, total, images, str(k)))
            disks.append(disk_rate(folder, total))
            recs[-1]["disk_around_mb_per_s"] = round((disks[-2]["mb_per_s"] + disks[-1]["mb_per_s"]) / 2, 1)
            recs[-1]["ratio"] = round(recs[-1]["mb_per_s"] / recs[-1]["disk_around_mb_per_s"], 3)
            say(f"recorder: {recs[-1]['mb_per_s']:.0f} MB/s ({recs[-1]['sets']} sets of 2 x {W}x{H} RGB in {recs[-1]['seconds']} s, "
                f"{recs[-1]['cpu_percent_of_one_core']}% of a core); disk around it {recs[-1]['disk_around_mb_per_s']:.0f} MB/s: "
                f"ratio {recs[-1]['ratio']:.2f}")
            say(f"disk: {disks[-1]['mb_per_s']:.0f} MB/s (direct {disks[-1].get('direct')}, buffered {disks[-1].get('buffered')})")
        disk = statistics.median(d["mb_per_s"] for d in disks)
        result = {"frame": f"{W}x{H} RGB8 x 2 cameras", "bytes_per_run": total, "disk_runs": disks, "recorder_runs": recs,
                  "disk_median_mb_per_s": round(disk, 1),
                  "recorder_median_mb_per_s": round(statistics.median(r["mb_per_s"] for r in recs), 1),
                  "ratio_median": statistics.median(r["ratio"] for r in recs)}
        if args.paced:
            rate = args.paced * disk * 1e6 / (2 * FRAME_BYTES)
            result["paced"] = paced(folder, rate, args.paced_seconds, images)
            p = result["paced"]
            say(f"paced at {args.paced:g} x the disk's median rate: {p['sets_per_s']} sets/s ({p['mb_per_s']} MB/s) for "
                f"{args.paced_seconds:g} s: {'sustained' if p['sustained'] else 'NOT sustained'} ({p['late']} late, "
                f"{p['frames_written']}/{2 * p['sets']} frames, caught up {p['backlog_s']} s after the last set)")
        if args.json:
            print(json.dumps(result))
        else:
            print(f"median: recorder {result['recorder_median_mb_per_s']:.0f} MB/s, disk {result['disk_median_mb_per_s']:.0f} MB/s, "
                  f"ratio (each recorder run against the disk runs around it) {result['ratio_median']:.2f}")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
