"""Calibration benchmark: board detection time per 1280x720 image, and the time to solve a six-camera
rig from 50 views (intrinsics, stereo pair, joint bundle adjustment), with the accuracy reached.

    .venv/bin/python benchmarks/calibration.py [--views 50] [--json] [--synthetic]
    .venv/bin/python benchmarks/calibration.py --session [--cameras 6] [--size 640x360]

`--session`: the calibration `rig demo` makes. The simulated calibration session of an N-camera rig
(simulator.calibration_session: the A0 board held at stations through the volume) is rendered at
every station, detected, and solved with k3 held, from all the stations and from shorter first parts
of the session; each result is compared with the simulator's exact cameras.

With the simulator installed, the six-camera arc rig (1280x720) watches an A0 ChArUco board carried
through the volume for `--views` time steps; detection is timed on every rendered image and the solve on
those detections, and the result is compared with the simulator's ground truth. Rendering is not timed.
`--synthetic` (or no simulator) times detection on the board seen through known homographies and the
solve on exact corner projections with 0.1 px noise. Chessboard detection is always timed on the
homography images too.
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
from calibration.compare import describe, errors_against_truth  # noqa: E402
from calibration.detect import make_detector  # noqa: E402
from calibration.images import DetectionSet  # noqa: E402
from calibration.solve import Options, calibrate_rig  # noqa: E402
from calibration.synthetic import arc_rig, board_poses, observe, warp_board  # noqa: E402

CHARUCO = CharucoSpec(11, 8, 0.105, 0.078, "DICT_5X5_100")  # A0 size
CHESSBOARD = ChessboardSpec(9, 6, 0.06)


def simulated_sequence(n_views: int):
    """(truth, {camera: [(view, grey image)]}) rendered by the simulator, or None without it."""
    try:
        import cv2

        from simulator.rig import virtual_rig
        from simulator.scene import Scene
        from simulator.sensor import NOMINAL_EXPOSURE_S, SensorModel
    except ImportError:
        return None
    truth = virtual_rig(6, 1280, 720)
    scene = Scene(seed=0, people=0, board=CHARUCO)
    frames = {}
    for cam in truth.cameras:
        sensor = SensorModel(scene, cam, {"motion_blur": False})
        frames[cam.name] = [
            (f"{k:04d}", cv2.cvtColor(sensor.expose(scene.board_period * k / n_views, NOMINAL_EXPOSURE_S, sensor.frame_rng(k)), cv2.COLOR_RGB2GRAY))
            for k in range(n_views)
        ]
    return truth, frames


def warped_frames(board, n: int):
    rng = np.random.default_rng(0)
    frames = []
    for _ in range(n):
        cx, cy = rng.uniform(350, 930), rng.uniform(220, 500)
        w, h = rng.uniform(250, 500), rng.uniform(180, 330)
        quad = [[cx - w / 2, cy - h / 2], [cx + w / 2, cy - h / 2], [cx + w / 2, cy + h / 2], [cx - w / 2, cy + h / 2]]
        frames.append(warp_board(board, np.array(quad) + rng.normal(0, 20, (4, 2)))[0])
    return frames


def time_detection(board, images):
    """Per-image detection time (ms) and the detections."""
    detector = make_detector(board)
    detector(images[0])  # the first call builds lookup tables
    times, found = [], []
    for img in images:
        t0 = time.perf_counter()
        found.append(detector(img))
        times.append((time.perf_counter() - t0) * 1000)
    stats = {"images": len(images), "found": sum(c is not None for c in found), "ms_median": round(statistics.median(times), 2),
             "ms_mean": round(statistics.mean(times), 2), "ms_max": round(max(times), 2)}
    return stats, found


def time_solve(detections: DetectionSet, truth):
    t0 = time.perf_counter()
    result = calibrate_rig(detections, CHARUCO)
    seconds = time.perf_counter() - t0
    return {
        "cameras": len(detections.cameras),
        "views": len(detections.views),
        "camera_views": sum(len(v) for v in detections.corners.values()),
        "corners": sum(len(c) for per in detections.corners.values() for c in per.values()),
        "seconds": round(seconds, 3),
        "rms_px": result.rig.meta["rms_px"],
        "worst_error": {k: round(v, 4) for k, v in errors_against_truth(result.rig, truth).worst.items()},
    }


def session_accuracy(n_cameras: int, width: int, height: int) -> dict:
    """Errors against the truth of a session's calibration, from all stations and from its first
    parts (a capture with fewer --views), with the time per rendered and detected image."""
    from rig.cameras.sim import sim_rig_config
    from rig.config import parse_config
    from simulator.calibration_session import CalibrationSession
    from simulator.sensor import NOMINAL_EXPOSURE_S

    session = CalibrationSession(parse_config(sim_rig_config(n_cameras=n_cameras, width=width, height=height)), CHARUCO)
    detector = make_detector(CHARUCO)
    corners: dict[str, dict] = {c: {} for c in session.cameras}
    t0 = time.perf_counter()
    for k in range(session.sets):
        for c in session.cameras:
            sensor = session.sensor(c)
            found = detector(sensor.expose(session.scene_time(k), NOMINAL_EXPOSURE_S, sensor.frame_rng(k)))
            if found is not None:
                corners[c][f"{k:04d}"] = found
    per_image_ms = (time.perf_counter() - t0) * 1000 / (session.sets * len(session.cameras))
    out = {"cameras": n_cameras, "size": f"{width}x{height}", "stations": session.sets, "render_and_detect_ms_per_image": round(per_image_ms, 1),
           "by_stations": {}}
    for n in sorted({session.sets, (2 * session.sets) // 3, session.sets // 2, session.sets // 3}, reverse=True):
        sub = {c: {v: x for v, x in per.items() if int(v) < n} for c, per in corners.items()}
        det = DetectionSet({c: (width, height) for c in session.cameras}, sub, {c: n for c in session.cameras})
        result = calibrate_rig(det, CHARUCO, Options(fix_k3=True))
        out["by_stations"][n] = {"views_used": result.rig.meta["views_used"],
                                 "worst_error": {k: round(v, 4) for k, v in errors_against_truth(result.rig, session.truth).worst.items()},
                                 "warnings": result.rig.meta["report"]["warnings"]}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=50, help="time steps (views) of the six-camera sequence")
    ap.add_argument("--synthetic", action="store_true", help="do not render: homography images and exact projections")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--session", action="store_true", help="the simulated calibration session `rig demo` uses (see above)")
    ap.add_argument("--cameras", type=int, default=6, help="with --session: cameras in the rig (default 6)")
    ap.add_argument("--size", default="640x360", help="with --session: image size (default 640x360, the demo's)")
    args = ap.parse_args()
    if args.session:
        w, h = (int(v) for v in args.size.lower().split("x"))
        res = session_accuracy(args.cameras, w, h)
        if args.json:
            print(json.dumps(res))
            return 0
        print(f"session: {res['cameras']} cameras at {res['size']}, {res['stations']} stations, "
              f"{res['render_and_detect_ms_per_image']} ms per image rendered and detected")
        for n, r in res["by_stations"].items():
            print(f"  first {n} stations: {describe(r['worst_error'])}; views used {r['views_used']}"
                  + (f"; {len(r['warnings'])} warnings" if r["warnings"] else ""))
        return 0

    results = {}
    seq = None if args.synthetic else simulated_sequence(args.views)
    if seq is not None:
        truth, frames = seq
        names = [c.name for c in truth.cameras]
        flat = [img for n in names for _, img in frames[n]]
        stats, found = time_detection(CHARUCO, flat)
        results["detect_charuco"] = {"source": "simulator renders with sensor noise (A0 ChArUco, 6-camera rig)", **stats}
        corners, i = {}, 0
        for n in names:
            corners[n] = {}
            for view, _ in frames[n]:
                if found[i] is not None:
                    corners[n][view] = found[i]
                i += 1
        det = DetectionSet({n: (1280, 720) for n in names}, corners, {n: args.views for n in names})
        results["solve"] = {"source": "detections in the simulator renders", **time_solve(det, truth)}
    else:
        stats, _ = time_detection(CHARUCO, warped_frames(CHARUCO, 12))
        results["detect_charuco"] = {"source": "board through known homographies", **stats}
        truth = arc_rig(6)
        det = observe(truth, CHARUCO, board_poses(args.views), noise_px=0.1)
        results["solve"] = {"source": "exact projections with 0.1 px noise", **time_solve(det, truth)}
    stats, _ = time_detection(CHESSBOARD, warped_frames(CHESSBOARD, 12))
    results["detect_chessboard"] = {"source": "board through known homographies", **stats}

    if args.json:
        print(json.dumps(results))
        return 0
    for key in ("detect_charuco", "detect_chessboard"):
        d = results[key]
        print(f"{key}: {d['ms_median']:.1f} ms median, {d['ms_mean']:.1f} ms mean, {d['ms_max']:.1f} ms max per 1280x720 image "
              f"({d['found']}/{d['images']} found; {d['source']})")
    s = results["solve"]
    print(f"solve: {s['cameras']} cameras x {s['views']} views ({s['camera_views']} camera views, {s['corners']} corners): "
          f"{s['seconds']:.2f} s ({s['source']})")
    print(f"accuracy, worst camera: {describe(s['worst_error'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
