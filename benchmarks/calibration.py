"""Calibration benchmark: board detection time per 1280x720 image, and the time to solve a six-camera
rig from 50 views (intrinsics, stereo pair, joint bundle adjustment), with the solver's accuracy.

    .venv/bin/python benchmarks/calibration.py [--views 50] [--cameras 6] [--images 12] [--json]

Detection runs on frames the simulator renders of the board in the volume when the simulator's renderer
is installed, else on the printed board seen through known homographies (calibration.synthetic).
The solve runs on exact corner positions from a known six-camera arc with 0.1 px Gaussian noise, so it
measures the solver alone.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.boards import CharucoSpec, ChessboardSpec  # noqa: E402
from calibration.detect import make_detector  # noqa: E402
from calibration.geometry import rotation_angle_deg  # noqa: E402
from calibration.solve import calibrate_rig  # noqa: E402
from calibration.synthetic import arc_rig, board_poses, in_frame_of, observe, warp_board  # noqa: E402

CHARUCO = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
CHESSBOARD = ChessboardSpec(9, 6, 0.06)


def rendered_frames(n: int):
    """(source, [grey 1280x720 images]) from the simulator, or None when its renderer is not available."""
    try:
        from simulator.render import render
        from simulator.rig import virtual_rig
        from simulator.scene import Scene
    except ImportError:
        return None
    rig = virtual_rig(6, 1280, 720)
    scene = Scene(seed=0, people=0, board=CHARUCO)
    period = getattr(scene, "board_period", 10.0)
    import cv2

    frames = []
    for i in range(n):
        cam = rig.cameras[i % len(rig.cameras)]
        t = period * (i + 0.5) / n
        frames.append(cv2.cvtColor(render(scene, cam, t).rgb, cv2.COLOR_RGB2GRAY))
    return "simulator renders (6-camera rig, board carried through the volume)", frames


def warped_frames(board, n: int):
    rng = np.random.default_rng(0)
    frames = []
    for _ in range(n):
        cx, cy = rng.uniform(350, 930), rng.uniform(220, 500)
        w, h = rng.uniform(250, 500), rng.uniform(180, 330)
        quad = [[cx - w / 2 + rng.normal(0, 20), cy - h / 2 + rng.normal(0, 20)], [cx + w / 2 + rng.normal(0, 20), cy - h / 2 + rng.normal(0, 20)],
                [cx + w / 2 + rng.normal(0, 20), cy + h / 2 + rng.normal(0, 20)], [cx - w / 2 + rng.normal(0, 20), cy + h / 2 + rng.normal(0, 20)]]
        frames.append(warp_board(board, quad)[0])
    return frames


def time_detection(board, frames, repeats: int = 3):
    detector = make_detector(board)
    detector(frames[0])  # first call builds lookup tables
    times = []
    found = 0
    for img in frames:
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            c = detector(img)
            best = min(best, time.perf_counter() - t0)
        found += c is not None
        times.append(best * 1000)
    return {"images": len(frames), "found": found, "ms_median": round(statistics.median(times), 2), "ms_mean": round(statistics.mean(times), 2),
            "ms_max": round(max(times), 2)}


def time_solve(n_cameras: int, n_views: int):
    truth = arc_rig(n_cameras)
    det = observe(truth, CHARUCO, board_poses(n_views), noise_px=0.1)
    t0 = time.perf_counter()
    result = calibrate_rig(det, CHARUCO)
    seconds = time.perf_counter() - t0
    gt = in_frame_of(truth, result.left)
    worst = {"focal_pct": 0.0, "principal_px": 0.0, "rotation_deg": 0.0, "position_mm": 0.0}
    for cam in result.rig.cameras:
        g = gt[cam.name]
        worst["focal_pct"] = max(worst["focal_pct"], 100 * abs(cam.fx / g.fx - 1), 100 * abs(cam.fy / g.fy - 1))
        worst["principal_px"] = max(worst["principal_px"], float(np.hypot(cam.cx - g.cx, cam.cy - g.cy)))
        worst["rotation_deg"] = max(worst["rotation_deg"], rotation_angle_deg(cam.R, g.R))
        worst["position_mm"] = max(worst["position_mm"], 1000 * float(np.linalg.norm(cam.center - g.center)))
    corners = sum(len(c) for per in det.corners.values() for c in per.values())
    return {
        "cameras": n_cameras,
        "views": n_views,
        "observations": sum(len(v) for v in det.corners.values()),
        "corners": corners,
        "seconds": round(seconds, 3),
        "iterations": result.solution.iterations,
        "rms_px": result.rig.meta["rms_px"],
        "worst_error": {k: round(v, 4) for k, v in worst.items()},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=50)
    ap.add_argument("--cameras", type=int, default=6)
    ap.add_argument("--images", type=int, default=12, help="1280x720 images to time detection on")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    rendered = rendered_frames(args.images)
    results = {}
    if rendered is not None:
        source, frames = rendered
        results["detect_charuco"] = {"source": source, **time_detection(CHARUCO, frames)}
    else:
        results["detect_charuco"] = {"source": "board through known homographies (simulator renderer not installed)",
                                     **time_detection(CHARUCO, warped_frames(CHARUCO, args.images))}
    results["detect_chessboard"] = {"source": "board through known homographies", **time_detection(CHESSBOARD, warped_frames(CHESSBOARD, args.images))}
    results["solve"] = time_solve(args.cameras, args.views)
    if args.json:
        print(json.dumps(results))
        return 0
    for key in ("detect_charuco", "detect_chessboard"):
        d = results[key]
        print(f"{key}: {d['ms_median']:.1f} ms median, {d['ms_mean']:.1f} ms mean, {d['ms_max']:.1f} ms max per 1280x720 image "
              f"({d['found']}/{d['images']} found; {d['source']})")
    s = results["solve"]
    print(f"solve: {s['cameras']} cameras x {s['views']} views ({s['observations']} camera views, {s['corners']} corners): "
          f"{s['seconds']:.2f} s, {s['iterations']} iterations in the last round")
    w = s["worst_error"]
    print(f"solve accuracy (0.1 px noise), worst camera: focal {w['focal_pct']:.4f}%, principal point {w['principal_px']:.3f} px, "
          f"rotation {w['rotation_deg']:.4f} deg, position {w['position_mm']:.3f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
