"""Runtime preprocessing speed: undistort + resize of the two source frames to the model's fine size.

For each source size (1280x720, 1920x1080 by default) and each fine size (the preview model's
512x288 and the paper model's 1024x576), the left and right cameras of a six-camera virtual rig
(with the lens distortion the simulator gives every camera) get a `Resampler` each
(inference/runtime/preprocess.py, the tables the live pipeline caches per camera); the benchmark
then times `Resampler.image` on both frames, uint8 RGB as cameras deliver them, and reports:

- two frames: median ms to preprocess both frames, over --repeat runs (after one warm-up run);
- p90 and min of the same runs;
- tables: ms to build both cameras' tables (once per camera and size; not on the per-frame path).

    .venv/bin/python benchmarks/preprocess.py [--repeat 50] [--sources 1280x720,1920x1080] [--fine 512x288,1024x576] [--threads N] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from inference.runtime.preprocess import Resampler  # noqa: E402
from simulator.rig import virtual_rig  # noqa: E402

SOURCES = ((1280, 720), (1920, 1080))
FINE = ((512, 288), (1024, 576))


def _frames(width: int, height: int, seed: int) -> list[np.ndarray]:
    """Two uint8 RGB frames with detail at every scale (the speed does not depend on content)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        small = rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8)
        img = cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR)
        img = cv2.add(img, rng.integers(0, 32, (height, width, 3), dtype=np.uint8))
        out.append(np.ascontiguousarray(img))
    return out


def bench(source: tuple[int, int], fine: tuple[int, int], repeat: int, seed: int) -> dict:
    rig = virtual_rig(6, *source)
    cams = [rig["left"], rig["right"]]
    t0 = time.perf_counter()
    resamplers = [Resampler(c, fine) for c in cams]
    tables_ms = (time.perf_counter() - t0) * 1e3
    frames = _frames(*source, seed)
    for r, f in zip(resamplers, frames):  # warm-up
        r.image(f)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for r, f in zip(resamplers, frames):
            r.image(f)
        times.append((time.perf_counter() - t0) * 1e3)
    times.sort()
    return {
        "source": f"{source[0]}x{source[1]}",
        "fine": f"{fine[0]}x{fine[1]}",
        "runs": repeat,
        "two_frames_ms_median": round(statistics.median(times), 2),
        "two_frames_ms_p90": round(times[int(0.9 * (len(times) - 1))], 2),
        "two_frames_ms_min": round(times[0], 2),
        "tables_ms": round(tables_ms, 1),
        "prefilter": resamplers[0].prefilter,
    }


def _sizes(text: str) -> list[tuple[int, int]]:
    try:
        return [tuple(int(v) for v in s.strip().split("x")) for s in text.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"sizes must be WxH[,WxH...], got {text!r}") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=50, help="timed runs per case (default 50; medians are reported)")
    ap.add_argument("--sources", default=",".join(f"{w}x{h}" for w, h in SOURCES), help="camera sizes, comma-separated WxH")
    ap.add_argument("--fine", default=",".join(f"{w}x{h}" for w, h in FINE), help="model fine sizes, comma-separated WxH")
    ap.add_argument("--threads", type=int, help="OpenCV worker threads (default: OpenCV's own, one per core)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        raise SystemExit("--repeat must be at least 1")
    if args.threads is not None:
        cv2.setNumThreads(args.threads)
    results = [bench(s, f, args.repeat, args.seed) for s in _sizes(args.sources) for f in _sizes(args.fine)]
    info = {"cpus": os.cpu_count(), "python": platform.python_version(), "machine": platform.machine(),
            "opencv": cv2.__version__, "opencv_threads": cv2.getNumThreads(),
            "load_average": [round(v, 2) for v in os.getloadavg()]}
    if args.json:
        print(json.dumps({"preprocess": results, "host": info}))
        return 0
    print(f"host: {info['cpus']} CPUs, load average {info['load_average']}, OpenCV {info['opencv']} "
          f"({info['opencv_threads']} threads); uint8 RGB frames, left + right cameras with lens distortion")
    print(f"{'source':>10} {'fine':>9} {'two frames median':>18} {'p90':>9} {'min':>9} {'tables':>9} {'prefilter':>9}")
    for r in results:
        print(f"{r['source']:>10} {r['fine']:>9} {r['two_frames_ms_median']:>15.2f} ms {r['two_frames_ms_p90']:>6.2f} ms "
              f"{r['two_frames_ms_min']:>6.2f} ms {r['tables_ms']:>6.1f} ms {r['prefilter']:>8d}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
