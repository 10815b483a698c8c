"""What a camera daemon costs a session, against opening the camera in the session's own process, in
one run on this machine:

1. latency per 1280x720 RGB frame: from the moment the camera hands the frame over (its host
   timestamp: the sim camera stamps it when its readout completes) to `get_frame` returning it in
   the session; in-process (the backend's queue) and through a daemon (copied into the ring, mapped
   and copied out by the reader in another process); p50 / p90 / p99 and the difference of the p50s;
2. six cameras at 30 Hz through `rig up`: a session reads every camera's frames for some seconds,
   hardware-triggered by the emulated board; frames delivered, sets complete, frames lost.

    .venv/bin/python benchmarks/daemon_overhead.py [--frames 300] [--seconds 10] [--size 1280x720] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from rig.sim.rig_config import sim_rig_config  # noqa: E402
from rig.config import dump_config, load_config, parse_config  # noqa: E402


def write_config(folder: Path, n: int, width: int, height: int, trigger: str) -> Path:
    data = sim_rig_config(n_cameras=n, width=width, height=height, fps=30.0, trigger=trigger)
    data["rig"]["name"] = f"bench-{n}cam-{trigger}"
    data["sim"]["loop_frames"] = 6
    path = folder / f"rig-{n}-{trigger}.toml"
    path.write_text(dump_config(parse_config(data)))
    return path


def latencies(camera, frames: int) -> np.ndarray:
    from sync.frames import monotonic_ns

    out = []
    camera.start()
    try:
        while len(out) < frames:
            f = camera.get_frame(timeout=2.0)
            out.append((monotonic_ns() - f.host_ts_ns) / 1e6)
    finally:
        camera.stop()
    return np.array(out[10:])  # the first frames include the start


def wait_for(path: Path, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        if time.monotonic() > deadline:
            raise SystemExit(f"{path} did not appear within {timeout:g} s")
        time.sleep(0.05)


def pcts(a: np.ndarray) -> dict:
    return {"p50_ms": round(float(np.percentile(a, 50)), 3), "p90_ms": round(float(np.percentile(a, 90)), 3),
            "p99_ms": round(float(np.percentile(a, 99)), 3), "frames": int(a.size)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    width, height = (int(x) for x in args.size.split("x"))
    tmp = Path(tempfile.mkdtemp(prefix="rig-daemon-bench-"))
    # the rings in memory, as the daemons' default /dev/shm/rig puts them (a ring in a disk-backed
    # folder is written back to the disk and measures that too)
    shm = Path(tempfile.mkdtemp(prefix="rig-daemon-bench-", dir="/dev/shm")) if Path("/dev/shm").is_dir() else tmp
    os.environ["RIG_SHM_ROOT"] = str(shm / "shm")
    from rig.cameras import open_camera as open_in_process
    from rig.daemon.client import LocalDaemonCamera, open_camera

    one = load_config(write_config(tmp, 1, width, height, "free"), check_calibration=False)
    cam_cfg = one.cameras[0]
    in_process = latencies(open_in_process(cam_cfg), args.frames)

    daemon = subprocess.Popen([sys.executable, "-m", "rig", "daemon", cam_cfg.name, "-c", str(tmp / "rig-1-free.toml"), "--no-advertise"],
                              cwd=REPO, stderr=subprocess.DEVNULL)
    try:
        wait_for(shm / "shm" / one.name / f"{cam_cfg.name}.json")
        cam = open_camera(cam_cfg)
        assert isinstance(cam, LocalDaemonCamera), type(cam)
        through_daemon = latencies(cam, args.frames)
        cam.close()
    finally:
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(30)
    result = {"size": f"{width}x{height}", "in_process": pcts(in_process), "daemon": pcts(through_daemon)}
    result["overhead_p50_ms"] = round(result["daemon"]["p50_ms"] - result["in_process"]["p50_ms"], 3)

    six_path = write_config(tmp, 6, width, height, "hardware")
    six = load_config(six_path, check_calibration=False)
    up = subprocess.Popen([sys.executable, "-m", "rig", "up", "-c", str(six_path), "--no-advertise"], cwd=REPO,
                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for c in six.cameras:
            wait_for(shm / "shm" / six.name / f"{c.name}.json")
        from rig.capture.session import RigSession

        with RigSession(six) as session:
            assert all(isinstance(c, LocalDaemonCamera) for c in session.cameras.values())
            sets = complete = 0
            for fs in session.framesets(seconds=args.seconds):
                sets += 1
                complete += fs.complete
            stats = session.camera_stats()
        result["six_cameras"] = {"seconds": args.seconds, "rate_hz": 30.0, "sets": sets, "complete_sets": complete,
                                 "frames": {n: s["delivered"] for n, s in stats.items()},
                                 "lost": {n: s["lost_frames"] + s["dropped"] for n, s in stats.items()}}
    finally:
        up.send_signal(signal.SIGTERM)
        up.wait(60)
        if shm != tmp:
            shutil.rmtree(shm, ignore_errors=True)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"per {result['size']} RGB frame, camera hand-over to get_frame (ms): in-process {result['in_process']}, "
              f"through a daemon {result['daemon']}; p50 overhead {result['overhead_p50_ms']:+.3f} ms")
        s = result["six_cameras"]
        print(f"six cameras at 30 Hz through `rig up`, {s['seconds']:g} s: {s['sets']} sets, {s['complete_sets']} complete; "
              f"frames {s['frames']}; lost {s['lost']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
