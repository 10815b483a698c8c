"""Ground-truth accuracy of rendered calibration boards.

For the default chessboard and ChArUco board carried along their path (times 0, 2, ..., 18 s) and
seen by the six cameras of the virtual rig at 1280x720 (lens distortion included), compares
- the projection of the board's 3D corners by CameraModel.project with cv2.projectPoints;
- the rendered depth of every board pixel with the intersection of the pixel's ray, undistorted by
  cv2.undistortPoints, with the board plane (relative difference);
- the corners OpenCV's detectors find in the rendered image with that projection:
  chessboard: findChessboardCorners + cornerSubPix (11x11), and findChessboardCornersSB;
  ChArUco: CharucoDetector.detectBoard, alone and followed by cornerSubPix (5x5).
Prints, per detector, the views where it found the board and the error statistics in pixels.

    .venv/bin/python benchmarks/simulator_board_accuracy.py [--size 1280x720] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from simulator.render import render  # noqa: E402
from simulator.rig import virtual_rig  # noqa: E402
from simulator.scene import Scene  # noqa: E402

SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)


def _oriented(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Detected minus true positions, in the detector's order or reversed."""
    if np.linalg.norm(found[::-1] - truth, axis=1).mean() < np.linalg.norm(found - truth, axis=1).mean():
        found = found[::-1]
    return found - truth


def _stats(errs: list, views: int) -> dict:
    if not errs:
        return {"views_found": 0, "views": views}
    d = np.concatenate(errs)
    e = np.linalg.norm(d, axis=1)
    return {"bias_px": [round(float(v), 4) for v in d.mean(axis=0)],"views_found": len(errs), "views": views, "corners": int(e.size), "rms_px": round(float(np.sqrt(np.mean(e ** 2))), 4),
            "median_px": round(float(np.median(e)), 4), "p95_px": round(float(np.percentile(e, 95)), 4), "max_px": round(float(e.max()), 4),
            "within_0.1px": round(float(np.mean(e <= 0.1)), 4)}


def measure(kind: str, width: int, height: int, times) -> dict:
    scene = Scene(seed=0, people=0, board=kind, name="empty")
    board = scene.board
    rig = virtual_rig(6, width, height)
    found: dict[str, list] = {}
    proj_diff = depth_diff = 0.0
    views = 0
    for t in times:
        _ids, pts = scene.board_corners(t)
        for cam in rig.cameras:
            uv, _ = cam.project(pts)
            rvec, _ = cv2.Rodrigues(cam.R)
            ref, _ = cv2.projectPoints(pts, rvec, cam.t, cam.K, cam.dist)
            proj_diff = max(proj_diff, float(np.abs(uv - ref.reshape(-1, 2)).max()))
            r = render(scene, cam, t)
            gray = cv2.cvtColor(r.rgb, cv2.COLOR_RGB2GRAY)
            vv, uu = np.nonzero(r.ids == r.labels.index("board"))
            if vv.size:
                pix = np.stack([uu, vv], axis=1).astype(np.float64).reshape(-1, 1, 2)
                xy = cv2.undistortPoints(pix, cam.K, cam.dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)).reshape(-1, 2)
                R, tb = scene.board_pose(t)
                n, p = cam.R @ R[:, 2], cam.R @ tb + cam.t
                z = (n @ p) / (xy @ n[:2] + n[2])
                depth_diff = max(depth_diff, float(np.max(np.abs(r.depth[vv, uu] - z) / z)))
            views += 1
            if kind == "chessboard":
                size = (board.cols, board.rows)
                ok, c = cv2.findChessboardCorners(gray, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
                if ok:
                    c = cv2.cornerSubPix(gray, c, (5, 5), (-1, -1), SUBPIX).reshape(-1, 2)
                    found.setdefault("findChessboardCorners+cornerSubPix", []).append(_oriented(c, uv))
                ok, c = cv2.findChessboardCornersSB(gray, size, flags=cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE)
                if ok:
                    found.setdefault("findChessboardCornersSB", []).append(_oriented(c.reshape(-1, 2), uv))
            else:
                c, ids, _mc, _mi = cv2.aruco.CharucoDetector(board.cv_board()).detectBoard(gray)
                if ids is not None and len(ids) >= 4:
                    ids = ids.ravel()
                    found.setdefault("CharucoDetector", []).append(c.reshape(-1, 2) - uv[ids])
                    c2 = cv2.cornerSubPix(gray, c.astype(np.float32), (2, 2), (-1, -1), SUBPIX).reshape(-1, 2)
                    found.setdefault("CharucoDetector+cornerSubPix", []).append(c2 - uv[ids])
    return {"board": board.to_dict(), "projection_vs_cv2_max_px": proj_diff, "board_depth_vs_cv2_max_rel": depth_diff,
            "detectors": {k: _stats(v, views) for k, v in found.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    times = [2.0 * i for i in range(10)]
    res = {kind: measure(kind, w, h, times) for kind in ("chessboard", "charuco")}
    if args.json:
        print(json.dumps(res))
        return 0
    for kind, r in res.items():
        print(f"{kind} {r['board']}")
        print(f"  corners, CameraModel.project vs cv2.projectPoints: max {r['projection_vs_cv2_max_px']:.2e} px; "
              f"board depth vs cv2.undistortPoints ray-plane: max {r['board_depth_vs_cv2_max_rel']:.2e} relative")
        for name, s in r["detectors"].items():
            if s["views_found"]:
                print(f"  {name:38s} found {s['views_found']:2d}/{s['views']} views, {s['corners']:4d} corners: "
                      f"rms {s['rms_px']:.3f}  median {s['median_px']:.3f}  p95 {s['p95_px']:.3f}  max {s['max_px']:.3f} px, "
                      f"{100 * s['within_0.1px']:.1f}% within 0.1 px, mean (bias) {s['bias_px']} px")
            else:
                print(f"  {name:38s} found 0/{s['views']} views")
    return 0


if __name__ == "__main__":
    sys.exit(main())
