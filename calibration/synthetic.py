"""Synthetic calibration data with known ground truth, for tests and benchmarks of the solver and the
detector alone (the simulator renders whole scenes; this is much cheaper and isolates one stage).

- `arc_rig`, `board_poses`, `observe`: board corners projected by known cameras (CameraModel.project,
  the distortion model the file stores) plus Gaussian pixel noise: solver error apart from detection.
- `warp_board`: the printable board seen through a known homography, antialiased: detector accuracy.
"""
from __future__ import annotations

import numpy as np

from calibration.boards import BoardSpec
from calibration.camera import CameraModel, RigCalibration, intrinsics_from_fov, look_at
from calibration.detect import Corners
from calibration.geometry import rodrigues
from calibration.images import DetectionSet


def arc_rig(n: int = 6, width: int = 1280, height: int = 720, radius: float = 3.0, spread_deg: float = 60.0) -> RigCalibration:
    """n cameras on an arc facing the origin, left and right outermost, mild lens distortion."""
    names = ["left"] + [f"sup{i}" for i in range(1, n - 1)] + ["right"]
    cams = []
    for i, name in enumerate(names):
        a = np.radians(-spread_deg / 2 + spread_deg * i / (n - 1))
        eye = np.array([radius * np.sin(a), 1.4 + 0.05 * i, radius * np.cos(a)])
        R, t = look_at(eye, (0.0, 1.1, 0.0))
        K = intrinsics_from_fov(width, height, 60.0 + 2 * i)
        K[0, 2] += 7 - 3 * i
        K[1, 2] += -4 + 2 * i
        dist = np.array([-0.08 + 0.01 * i, 0.05, 0.0004, -0.0003, -0.01])
        cams.append(CameraModel(name, width, height, K, dist, R, t))
    return RigCalibration(cams)


def board_poses(n_views: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board-to-world poses: the board carried through the volume, tilted, roughly facing the arc."""
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(n_views):
        centre = np.array([rng.uniform(-0.8, 0.8), rng.uniform(0.6, 1.7), rng.uniform(-0.6, 0.8)])
        # Board normal (its +z) points away from the cameras (towards -z world); tilt it up to ~35 degrees.
        tilt = rng.normal(0, 0.35, size=3)
        R = rodrigues(np.array([np.pi, 0.0, 0.0])) @ rodrigues(tilt)
        poses.append((R, centre))
    return poses


def observe(rig: RigCalibration, board: BoardSpec, poses, noise_px: float = 0.1, seed: int = 1, min_corners: int = 6) -> DetectionSet:
    rng = np.random.default_rng(seed)
    ids, obj = board.object_points()
    w_m, h_m = board.size_m
    centre_board = np.array([w_m / 2, h_m / 2, 0.0])
    corners: dict[str, dict[str, Corners]] = {c.name: {} for c in rig.cameras}
    for v, (R, c) in enumerate(poses):
        world = (obj - centre_board) @ R.T + c
        normal = R[:, 2]
        for cam in rig.cameras:
            # A board seen from behind or edge-on is not detected.
            view_dir = world.mean(axis=0) - cam.center
            if np.dot(normal, view_dir) / np.linalg.norm(view_dir) < 0.3:
                continue
            uv, z = cam.project(world)
            inside = (z > 0) & (uv[:, 0] > 2) & (uv[:, 1] > 2) & (uv[:, 0] < cam.width - 3) & (uv[:, 1] < cam.height - 3)
            if inside.sum() < min_corners:
                continue
            pts = uv[inside] + rng.normal(0, noise_px, size=(int(inside.sum()), 2))
            corners[cam.name][f"{v:04d}"] = Corners(ids[inside], pts)
    sizes = {c.name: (c.width, c.height) for c in rig.cameras}
    return DetectionSet(sizes, corners, {c.name: len(poses) for c in rig.cameras})


def warp_board(board: BoardSpec, quad, size=(1280, 720), ppm: float = 1000.0, supersample: int = 4):
    """The board's printable image seen through the homography that puts its square grid's corners at
    `quad` (4 pixel positions, clockwise from the grid's top-left), antialiased by supersampling.

    Returns (grey image, H) with H mapping board metres (x, y) to pixels.
    """
    import cv2

    img = board.image(ppm)
    m = board.margin_m
    w_m, h_m = board.size_m
    src = np.float32([[0, 0], [w_m, 0], [w_m, h_m], [0, h_m]])
    H = cv2.getPerspectiveTransform(src, np.float32(quad))
    # Board-image pixel centre i sits at board coordinate (i + 0.5) / ppm - margin.
    A = np.array([[1 / ppm, 0, 0.5 / ppm - m], [0, 1 / ppm, 0.5 / ppm - m], [0, 0, 1]])
    s = supersample
    # Output pixel centre j is the mean of supersampled centres s*j .. s*j + s-1.
    S = np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1]])
    big = cv2.warpPerspective(img, S @ H @ A, (size[0] * s, size[1] * s), flags=cv2.INTER_LINEAR, borderValue=255)
    return cv2.resize(big, size, interpolation=cv2.INTER_AREA), H


def ring_rig(n: int = 4, width: int = 960, height: int = 720, radius: float = 1.3, hfov_deg: float = 60.0,
             seed: int = 0, spread_deg: float = 40.0) -> RigCalibration:
    """n cameras on a ring around the origin, looking at it from the same side of the board (spread
    over `spread_deg` about +z), at slightly different heights; lenses with mild distortion and principal
    points off the image centre, each a little different."""
    rng = np.random.default_rng(seed)
    names = [f"cam_{i}" for i in range(n)]
    cams = []
    for i, name in enumerate(names):
        a = np.radians(spread_deg * (i / max(n - 1, 1) - 0.5))
        eye = np.array([radius * np.sin(a), 0.3 * np.cos(1.7 * i), radius * np.cos(a)])
        R, t = look_at(eye, (0.0, 0.0, 0.0))
        K = intrinsics_from_fov(width, height, hfov_deg + 4.0 * i)
        K[0, 2] += rng.uniform(-12, 12)
        K[1, 2] += rng.uniform(-10, 10)
        dist = np.array([-0.12 + 0.02 * i, 0.06, 0.0005, -0.0004, 0.0])
        cams.append(CameraModel(name, width, height, K, dist, R, t))
    return RigCalibration(cams)


def board_path(n_instants: int, reach: float = 0.45, seed: int = 0, speed: float = 1.0):
    """A board carried smoothly through the volume around the origin and turned as it goes: its
    board-to-world pose at (fractional) instant k, facing +z (the cameras) within about 35 degrees.
    The hand's motion is a sum of slow sines (about one turn each over the session, times `speed`), so
    a camera one instant out of step sees the board a little further along its path, not elsewhere."""
    rng = np.random.default_rng(seed)
    freq = speed * rng.uniform(0.7, 1.6, size=(6, 2)) * 2 * np.pi / n_instants
    phase = rng.uniform(0, 2 * np.pi, size=(6, 2))

    def pose(k: float) -> tuple[np.ndarray, np.ndarray]:
        s = np.sin(freq * k + phase).sum(axis=1) / 2.0  # six smooth coordinates in about [-1, 1]
        centre = np.array([reach * s[0], 0.6 * reach * s[1], 0.5 * reach * s[2]])
        tilt = np.array([0.55 * s[3], 0.55 * s[4], 0.3 * s[5]])
        # board +z (its normal) points away from the cameras, as in `board_poses`
        return rodrigues(np.array([np.pi, 0.0, 0.0])) @ rodrigues(tilt), centre

    return pose


def moving_board_session(rig: RigCalibration, board: BoardSpec, n_instants: int, shifts: dict[str, float] | None = None,
                         noise_px: float = 0.2, seed: int = 1, reach: float = 0.45, min_corners: int = 6, speed: float = 1.0) -> DetectionSet:
    """Free-running cameras filming a board carried through the volume: image k of every camera is
    named k (`f"{k:04d}"`), but a camera `shifts` names as s took each image at instant k + s: its
    frames are s instants out of step with the others', as the frames of a video started a frame early
    or late are. Corners as `observe` makes them (exact projections plus Gaussian noise)."""
    rng = np.random.default_rng(seed)
    shifts = shifts or {}
    path = board_path(n_instants + 8, reach, seed, speed)
    ids, obj = board.object_points()
    w_m, h_m = board.size_m
    centre_board = np.array([w_m / 2, h_m / 2, 0.0])
    corners: dict[str, dict[str, Corners]] = {c.name: {} for c in rig.cameras}
    for cam in rig.cameras:
        s = shifts.get(cam.name, 0.0)
        for k in range(n_instants):
            R, c = path(k + s + 4)  # the path runs a few instants either side, for cameras out of step
            world = (obj - centre_board) @ R.T + c
            view_dir = world.mean(axis=0) - cam.center
            if np.dot(R[:, 2], view_dir) / np.linalg.norm(view_dir) < 0.3:
                continue
            uv, z = cam.project(world)
            inside = (z > 0) & (uv[:, 0] > 2) & (uv[:, 1] > 2) & (uv[:, 0] < cam.width - 3) & (uv[:, 1] < cam.height - 3)
            if inside.sum() < min_corners:
                continue
            corners[cam.name][f"{k:04d}"] = Corners(ids[inside], uv[inside] + rng.normal(0, noise_px, size=(int(inside.sum()), 2)))
    sizes = {c.name: (c.width, c.height) for c in rig.cameras}
    return DetectionSet(sizes, corners, {c.name: n_instants for c in rig.cameras})


def image_share(rig: RigCalibration, det: DetectionSet) -> dict[str, float]:
    """The largest share of its image the board's outline (the hull of its corners) covers in any one
    view, per camera."""
    import cv2

    out = {}
    for cam in rig.cameras:
        areas = [cv2.contourArea(cv2.convexHull(c.points.astype(np.float32))) for c in det.corners[cam.name].values()]
        out[cam.name] = max(areas, default=0.0) / (cam.width * cam.height)
    return out
