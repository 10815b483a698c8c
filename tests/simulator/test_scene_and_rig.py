"""The scene is a pure function of (seed, time); the virtual rig is the arc the design describes."""
from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.boards import ChessboardSpec
from simulator.errors import SimulatorError
from simulator.people import MOTIONS
from simulator.rig import virtual_rig
from simulator.scene import Scene


def _pose_summary(scene: Scene, t: float) -> list:
    out = []
    for p in scene.primitives(t):
        for attr in ("center", "a", "b", "t_bw"):
            if hasattr(p, attr):
                out.append(np.asarray(getattr(p, attr)).tolist())
    return out


def test_same_seed_same_scene_different_seed_different_scene():
    a, b, c = Scene(seed=5, people=2), Scene(seed=5, people=2), Scene(seed=6, people=2)
    assert _pose_summary(a, 1.25) == _pose_summary(b, 1.25)
    assert np.array_equal(a.atlas.image, b.atlas.image)
    assert _pose_summary(a, 1.25) != _pose_summary(c, 1.25)
    assert _pose_summary(a, 1.25) != _pose_summary(a, 1.5), "people move with time"


@pytest.mark.parametrize("motion", MOTIONS)
def test_every_motion_keeps_people_on_or_above_the_floor(motion):
    scene = Scene(seed=1, people=1, motion=motion, name="empty")
    for t in np.linspace(0.0, 3.0, 13):
        feet = [p for p in scene.primitives(t) if p.name.endswith(("foot_l", "foot_r"))]
        lowest = min(p.center[1] - p.radii[1] for p in feet)
        assert lowest > -0.02, f"{motion} at t={t}: a foot sinks {lowest:.3f} m into the floor"
        heads = [p for p in scene.primitives(t) if p.name.endswith(".head")]
        assert 1.2 < heads[0].center[1] < 2.3


def test_board_pose_is_a_rotation_and_corners_follow_it():
    board = ChessboardSpec(cols=7, rows=5, square_size=0.05)
    scene = Scene(seed=0, people=0, board=board)
    ids, obj = board.object_points()
    for t in (0.0, 3.3, 12.7):
        R, tb = scene.board_pose(t)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        got_ids, pts = scene.board_corners(t)
        assert np.array_equal(got_ids, ids)
        assert np.allclose(pts, obj @ R.T + tb)
        # the printed face (board -z) turns towards the rig on the +z side
        assert (-R[:, 2])[2] > 0.3
        assert 0.6 < pts[:, 1].min() and pts[:, 1].max() < 2.2


def test_bad_scene_input_is_a_clear_error():
    with pytest.raises(SimulatorError, match="unknown scene 'moon'"):
        Scene(name="moon")
    with pytest.raises(SimulatorError, match="unknown motion 'fly'.*walk"):
        Scene(motion="fly")
    with pytest.raises(SimulatorError, match="people"):
        Scene(people=4)
    with pytest.raises(SimulatorError, match="unknown board"):
        Scene(board="dartboard")
    scene = Scene(seed=0, people=1, name="empty")
    with pytest.raises(SimulatorError, match="time must be .*>= 0"):
        scene.primitives(-0.5)
    with pytest.raises(SimulatorError, match="no calibration board"):
        scene.board_pose(1.0)
    with pytest.raises(SimulatorError, match="sim.motion"):
        Scene.from_options({"motion": "fly"})


def test_virtual_rig_is_an_arc_of_cameras_facing_the_actors():
    rig = virtual_rig(6, 1280, 720)
    assert rig.names == ["left", "sup1", "sup2", "sup3", "sup4", "right"]
    centres = np.array([c.center for c in rig.cameras])
    left, right = rig["left"], rig["right"]
    a = centres[0] - [0, centres[0][1], 0]
    b = centres[-1] - [0, centres[-1][1], 0]
    angle = math.degrees(math.acos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
    assert angle == pytest.approx(60.0, abs=1.0)
    assert left.center[0] < 0 < right.center[0], "left is on the viewer's left (world -x, seen from +z)"
    for cam in rig.cameras:
        assert (cam.width, cam.height) == (1280, 720)
        uv, z = cam.project(np.array([[0.0, 1.0, 0.0]]))
        assert z[0] > 2.5 and 0.3 * cam.width < uv[0, 0] < 0.7 * cam.width and 0.2 * cam.height < uv[0, 1] < 0.8 * cam.height
        head, _ = cam.project(np.array([[0.0, 1.9, 0.0]]))
        assert head[0, 1] < uv[0, 1], "images are upright: a point above appears higher"
    two = virtual_rig(2, 640, 360)
    assert two.names == ["left", "right"]
    assert np.allclose(two["left"].center, left.center) and np.allclose(two["right"].center, right.center)


def test_virtual_rig_bad_input():
    with pytest.raises(SimulatorError, match="n_cameras"):
        virtual_rig(0)
    with pytest.raises(SimulatorError, match="image size"):
        virtual_rig(2, 0, 720)
    with pytest.raises(SimulatorError, match="must be an integer"):
        virtual_rig(2, 640.5, 360)
