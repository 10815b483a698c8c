"""A double-sided ChArUco board links cameras that face each other: one sees its front while the
other sees its back, in the same instant."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.boards import CharucoSpec, load_board
from calibration.camera import CalibrationError, CameraModel, RigCalibration, intrinsics_from_fov, look_at
from calibration.detect import Corners, detect
from calibration.geometry import rodrigues
from calibration.images import DetectionSet
from calibration.solve import Options, calibrate_rig
from calibration.synthetic import warp_board

BOARD = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100", back_first_marker=17, thickness=0.004)
QUAD = [[400, 150], [900, 200], [880, 560], [420, 600]]


def test_the_board_file_describes_the_back_face(tmp_path):
    path = tmp_path / "board.toml"
    path.write_text('type = "charuco"\nsquares_x = 7\nsquares_y = 5\nsquare_size = 0.08\nmarker_size = 0.06\n'
                    '[back]\nfirst_marker = 17\nthickness = 0.004\n')
    board = load_board(path)
    assert board == BOARD and board.to_dict()["back"] == {"first_marker": 17, "thickness": 0.004}
    ids, pts = board.object_points()
    n = board.n_corners
    assert len(ids) == 2 * n
    # back corner k lies behind the front, mirrored across the board's vertical centre line
    assert np.allclose(pts[n:, 0], board.size_m[0] - pts[:n, 0]) and np.allclose(pts[n:, 1], pts[:n, 1]) and np.all(pts[n:, 2] == 0.004)
    for back, words in (("first_marker = 10", "overlap the front's"), ("first_marker = 90", "back.first_marker must be"),
                        ("first_marker = 17\nthickness = 2.0", "back.thickness")):
        path.write_text(path.read_text().split("[back]")[0] + "[back]\n" + back + "\n")
        with pytest.raises(CalibrationError, match=words):
            load_board(path)


def test_the_back_face_is_detected_with_its_own_corner_ids():
    image, H = warp_board(BOARD.back_face(), QUAD)
    corners = detect(BOARD, image)
    n = BOARD.n_corners
    assert corners is not None and len(corners) == n and corners.ids.min() == n
    _, own = BOARD.back_face().object_points()
    truth = cv2.perspectiveTransform(own[corners.ids - n, :2].reshape(-1, 1, 2), H).reshape(-1, 2)
    assert np.sqrt(np.mean(np.sum((corners.points - truth) ** 2, axis=1))) < 0.15
    front, _ = warp_board(BOARD, QUAD)
    assert detect(BOARD, front).ids.max() < n


def _facing_rig() -> RigCalibration:
    """Two cameras side by side in front of the board's area, one behind it facing them."""
    cams = []
    for name, eye in (("left", (-0.4, 1.3, 2.5)), ("right", (0.4, 1.3, 2.5)), ("behind", (0.2, 1.2, -2.5))):
        R, t = look_at(eye, (0.0, 1.1, 0.0))
        cams.append(CameraModel(name, 1280, 720, intrinsics_from_fov(1280, 720, 60.0), np.array([-0.05, 0.02, 0, 0, 0]), R, t))
    return RigCalibration(cams)


def _observe(rig: RigCalibration, board: CharucoSpec, n_views: int, seed: int = 0) -> DetectionSet:
    rng = np.random.default_rng(seed)
    ids, obj = board.object_points()
    n = board.n_corners
    centre_board = np.array([board.size_m[0] / 2, board.size_m[1] / 2, 0.0])
    corners: dict = {c.name: {} for c in rig.cameras}
    for v in range(n_views):
        R = rodrigues(np.array([np.pi, 0.0, 0.0])) @ rodrigues(rng.normal(0, 0.3, size=3))
        c = np.array([rng.uniform(-0.5, 0.5), rng.uniform(0.8, 1.4), rng.uniform(-0.4, 0.4)])
        world = (obj - centre_board) @ R.T + c
        normal = R[:, 2]  # from the front face into the board
        for cam in rig.cameras:
            facing = np.dot(normal, world[:n].mean(axis=0) - cam.center)
            side = slice(0, n) if facing > 0 else slice(n, 2 * n)  # the face this camera looks at
            uv, z = cam.project(world[side])
            inside = (z > 0) & (uv[:, 0] > 2) & (uv[:, 1] > 2) & (uv[:, 0] < cam.width - 3) & (uv[:, 1] < cam.height - 3)
            if inside.sum() >= 8:
                corners[cam.name][f"{v:04d}"] = Corners(ids[side][inside], uv[inside] + rng.normal(0, 0.1, (int(inside.sum()), 2)))
    return DetectionSet({c.name: (c.width, c.height) for c in rig.cameras}, corners, {c.name: n_views for c in rig.cameras})


def test_a_camera_facing_the_others_is_placed_through_the_back_face():
    truth = _facing_rig()
    det = _observe(truth, BOARD, 30)
    n = BOARD.n_corners
    assert all(c.ids.min() >= n for c in det.corners["behind"].values())  # it only ever sees the back
    assert all(c.ids.max() < n for c in det.corners["left"].values())
    result = calibrate_rig(det, BOARD, Options(left="left", right="right"))
    got, want = result.rig, truth
    rel = got["behind"].R @ got["left"].R.T
    rel_true = want["behind"].R @ want["left"].R.T
    angle = np.degrees(np.arccos(np.clip((np.trace(rel @ rel_true.T) - 1) / 2, -1, 1)))
    centre = got["left"].R @ (got["behind"].center - got["left"].center)
    centre_true = want["left"].R @ (want["behind"].center - want["left"].center)
    # 5 m away through a 4 mm thick board: within a quarter degree and 2 cm (0.4 %)
    assert angle < 0.25 and np.linalg.norm(centre - centre_true) < 0.02, (angle, centre, centre_true)
    assert max(result.rig.meta["rms_px"].values()) < 0.2
