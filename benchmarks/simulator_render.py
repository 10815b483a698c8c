"""Renderer speed: milliseconds per frame at 512x288, 1024x576 and 1280x720.

For each size, a six-camera virtual rig watches the default studio with three moving people; the
benchmark renders consecutive frames (1/30 s apart) from every camera in turn with the default
anti-aliasing and lens blur, and reports:

- steady: median ms per frame once each camera has drawn the static room and props (the normal
  case: a rig's cameras do not move);
- cold: ms for a camera's first frame (its ray grid and static layer are built then);
- CPU: median process CPU time per steady frame (less disturbed than wall time on a busy machine;
  it counts OpenCV's worker threads too).

    .venv/bin/python benchmarks/simulator_render.py [--frames 10] [--sizes 512x288,1280x720] [--json]
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

from simulator.render import render  # noqa: E402
from simulator.rig import virtual_rig  # noqa: E402
from simulator.scene import Scene  # noqa: E402

SIZES = ((512, 288), (1024, 576), (1280, 720))


def bench(width: int, height: int, frames: int, people: int, seed: int) -> dict:
    scene = Scene(seed=seed, people=people)
    rig = virtual_rig(6, width, height)
    cold = []
    for cam in rig.cameras:
        t0 = time.perf_counter()
        render(scene, cam, 0.0)
        cold.append((time.perf_counter() - t0) * 1e3)
    steady, cpu = [], []
    for i in range(1, frames + 1):
        for cam in rig.cameras:
            t0, c0 = time.perf_counter(), time.process_time()
            render(scene, cam, i / 30.0)
            steady.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
    return {
        "size": f"{width}x{height}",
        "frames": len(steady),
        "steady_ms_median": round(statistics.median(steady), 1),
        "steady_ms_p90": round(sorted(steady)[int(0.9 * (len(steady) - 1))], 1),
        "steady_ms_min": round(min(steady), 1),
        "steady_cpu_ms_median": round(statistics.median(cpu), 1),
        "cold_ms_median": round(statistics.median(cold), 1),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10, help="frames per camera (default 10)")
    ap.add_argument("--sizes", default=",".join(f"{w}x{h}" for w, h in SIZES), help="comma-separated WxH list")
    ap.add_argument("--people", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    results = [bench(w, h, args.frames, args.people, args.seed) for w, h in sizes]
    info = {"cpus": os.cpu_count(), "python": platform.python_version(), "machine": platform.machine(),
            "load_average": [round(v, 2) for v in os.getloadavg()], "people": args.people}
    if args.json:
        print(json.dumps({"renderer": results, "host": info}))
    else:
        print(f"host: {info['cpus']} CPUs, load average {info['load_average']}, {args.people} people, 6 cameras")
        print(f"{'size':>10} {'steady median':>14} {'p90':>8} {'min':>8} {'CPU median':>11} {'cold (first frame)':>19}")
        for r in results:
            print(f"{r['size']:>10} {r['steady_ms_median']:>11.1f} ms {r['steady_ms_p90']:>5.1f} ms {r['steady_ms_min']:>5.1f} ms "
                  f"{r['steady_cpu_ms_median']:>8.1f} ms {r['cold_ms_median']:>16.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
