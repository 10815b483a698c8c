"""Capture throughput of the aravis:// backend against the reference tool, on Aravis's fake GigE camera.

For each frame rate, a fresh `arv-fake-gv-camera-0.8 -i 127.0.0.1` free-runs 640x480 Mono8 for the
given duration, read once by our backend (rig.cameras.aravis) and once by `arv-camera-test-0.8` (the
reference), each against its own fresh fake camera. Prints frames/s of each, the ratio, gaps in our
frame ids, and our per-frame cost from popped buffer to Frame.

    .venv/bin/python benchmarks/capture_throughput.py [--seconds 5] [--fps 100 200] [--json]
"""
from __future__ import annotations

import argparse
import json
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rig.cameras.aravis import AravisCamera  # noqa: E402
from rig.config import CameraConfig  # noqa: E402

ADDRESS = "127.0.0.1"


def _port_free() -> bool:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind((ADDRESS, 3956))
        return True
    except OSError:
        return False
    finally:
        s.close()


class FakeCamera:
    def __enter__(self):
        while not _port_free():
            time.sleep(0.05)
        self.proc = subprocess.Popen(["arv-fake-gv-camera-0.8", "-i", ADDRESS], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        while _port_free():
            time.sleep(0.02)
        return self

    def __exit__(self, *exc):
        self.proc.kill()
        self.proc.wait()


def run_ours(fps: float, seconds: float) -> dict:
    cfg = CameraConfig(name="cam", uri=f"aravis://{ADDRESS}", width=640, height=480, pixel_format="Mono8", fps=fps,
                       trigger="free", exposure_us=min(1000.0, 0.5e6 / fps))
    decode_s: list[float] = []
    with FakeCamera():
        cam = AravisCamera(cfg.uri, cfg)
        original = cam._decode

        def timed_decode(buf):
            t = time.perf_counter()
            frame = original(buf)
            decode_s.append(time.perf_counter() - t)
            return frame

        cam._decode = timed_decode
        cam.start()
        first = cam.get_frame(2.0)  # the clock starts at the first frame, as the reference's does
        ids = [first.frame_id]
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            ids.append(cam.get_frame(2.0).frame_id)
        elapsed = time.monotonic() - t0
        stream = cam.stream_statistics()
        cam.close()
    gaps = int(sum(b - a - 1 for a, b in zip(ids, ids[1:])))
    cost = np.array(decode_s) * 1e3
    return {
        "frames_per_s": (len(ids) - 1) / elapsed,
        "frames": len(ids),
        "gaps": gaps,
        "incomplete": cam.stats.incomplete,
        "buffer_to_frame_ms_mean": float(cost.mean()),
        "buffer_to_frame_ms_p99": float(np.percentile(cost, 99)),
        "stream_failures": stream.get("n_failures", 0),
    }


def run_reference(fps: float, seconds: float) -> dict:
    cmd = ["arv-camera-test-0.8", "-n", ADDRESS, "-f", str(fps), "-w", "640", "-h", "480", "-e", str(min(1000.0, 0.5e6 / fps)),
           "--no-packet-socket", "-a", "--duration", str(int(seconds))]
    with FakeCamera():
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 30).stdout
    per_second = [int(m) for m in re.findall(r"^(\d+) frames/s", out, re.M)]
    completed = re.search(r"n_completed_buffers\s*=\s*(\d+)", out)
    failures = re.search(r"n_failures\s*=\s*(\d+)", out)
    if not per_second:
        raise RuntimeError(f"arv-camera-test-0.8 printed no frame rate:\n{out}")
    return {
        "frames_per_s": float(np.mean(per_second)),
        "per_second": per_second,
        "completed": int(completed.group(1)) if completed else None,
        "failures": int(failures.group(1)) if failures else None,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--fps", type=float, nargs="+", default=[100.0, 200.0])
    ap.add_argument("--rounds", type=int, default=3, help="alternate reference and ours this many times; medians are reported")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    results = []
    for fps in args.fps:
        refs, ours_runs = [], []
        for _ in range(args.rounds):  # alternate, so a change in machine load hits both alike
            refs.append(run_reference(fps, args.seconds))
            ours_runs.append(run_ours(fps, args.seconds))
        ref_fps = float(np.median([r["frames_per_s"] for r in refs]))
        our_fps = float(np.median([o["frames_per_s"] for o in ours_runs]))
        ours = {
            "frames_per_s": our_fps,
            "runs_frames_per_s": [round(o["frames_per_s"], 2) for o in ours_runs],
            "gaps": sum(o["gaps"] for o in ours_runs),
            "incomplete": sum(o["incomplete"] for o in ours_runs),
            "buffer_to_frame_ms_mean": float(np.mean([o["buffer_to_frame_ms_mean"] for o in ours_runs])),
            "buffer_to_frame_ms_p99": float(np.max([o["buffer_to_frame_ms_p99"] for o in ours_runs])),
        }
        ref = {"frames_per_s": ref_fps, "runs_frames_per_s": [round(r["frames_per_s"], 2) for r in refs],
               "failures": sum(r["failures"] or 0 for r in refs)}
        ratio = our_fps / ref_fps
        results.append({"fps": fps, "ours": ours, "reference": ref, "ratio": ratio})
        if not args.json:
            print(f"{fps:5.0f} fps requested: ours {our_fps:7.1f} frames/s {ours['runs_frames_per_s']} ({ours['gaps']} gaps, "
                  f"{ours['incomplete']} incomplete), arv-camera-test {ref_fps:7.1f} frames/s {ref['runs_frames_per_s']} "
                  f"({ref['failures']} failed buffers) -> ratio {ratio:.3f}; buffer->Frame {ours['buffer_to_frame_ms_mean']:.3f} ms mean, "
                  f"{ours['buffer_to_frame_ms_p99']:.3f} ms p99")
    if args.json:
        print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
