"""The simulated calibration session: where the board is held, what each camera sees of it, and how
the scene and the loop cache treat a board moved by a session instead of its loop."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.boards import CharucoSpec
from calibration.report import coverage
from rig.sim.rig_config import sim_rig_config
from rig.config import parse_config
from simulator import loop_cache
from simulator.calibration_session import CalibrationSession, seen_fraction
from simulator.scene import ROOM_HI, ROOM_LO

A0 = CharucoSpec(squares_x=11, squares_y=8, square_size=0.105, marker_size=0.078, dictionary="DICT_5X5_100")


def _session(n: int, width: int = 640, height: int = 360, board=A0) -> CalibrationSession:
    return CalibrationSession(parse_config(sim_rig_config(n_cameras=n, width=width, height=height)), board)


@pytest.mark.parametrize("n", [2, 6])
def test_stations_are_rigid_poses_inside_the_room(n):
    s = _session(n)
    assert s.sets >= 12 * n
    _ids, obj = A0.object_points()
    for st in s.stations:
        assert np.allclose(st.R.T @ st.R, np.eye(3), atol=1e-12) and np.linalg.det(st.R) == pytest.approx(1.0)
        world = obj @ st.R.T + st.t
        assert np.all(world >= np.array(ROOM_LO)) and np.all(world <= np.array(ROOM_HI))


@pytest.mark.parametrize("n", [2, 6])
def test_the_board_covers_every_cameras_image_and_shared_stations_face_every_camera(n):
    s = _session(n)
    _ids, obj = A0.object_points()
    for cam in s.truth.cameras:
        hulls = []
        for st in s.stations:
            uv, z = cam.project(obj @ st.R.T + st.t)
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
            if inside.sum() >= 6 and seen_fraction(st, cam, A0, 60.0) > 0:
                hulls.append(uv[inside])
        cov = coverage((cam.width, cam.height), hulls)
        assert cov["fraction"] >= 0.8 and not cov["never_seen"], (cam.name, cov)
    shared = [st for st in s.stations if st.purpose == "shared"]
    assert len(shared) >= 10
    for st in shared:
        assert all(seen_fraction(st, cam, A0, 48.0) >= 0.9 for cam in s.truth.cameras)


def test_views_count_stations_and_the_scene_holds_the_board_there():
    s = _session(2)
    _ids, obj = A0.object_points()
    for k in (0, 5, s.sets - 1, s.sets + 10):  # past the end the board stays at the last station
        st = s.stations[min(k, s.sets - 1)]
        _ids2, corners = s.scene.board_corners(s.scene_time(k))
        assert np.allclose(corners, obj @ st.R.T + st.t)
    assert s.scene.persons == [] and s.sensor("left").loop_frames == 0


def test_a_session_scene_is_not_cached_as_a_loop():
    s = _session(2)
    assert loop_cache.scene_fingerprint(s.scene) is None


def test_the_session_shows_the_board_the_user_names():
    small = CharucoSpec(squares_x=5, squares_y=4, square_size=0.06, marker_size=0.045, dictionary="DICT_4X4_50")
    s = _session(2, board=small)
    assert s.scene.board == small
    # Held closer, so that it spans about the same share of each image as a large board does.
    cam = s.truth["left"]
    near = [np.linalg.norm(st.t - cam.center) for st in s.stations if st.purpose == "left"]
    assert max(near) < min(np.linalg.norm(st.t - cam.center) for st in _session(2).stations if st.purpose == "left")
