"""A ray exactly parallel to a room wall (a camera looking along an axis: its principal ray) leaves the
room where it really does: before the fix its exit through those walls came out at -inf (0 divided
into a negative distance), the nearest, so the pixel showed depth 0 and a wrong colour."""
from __future__ import annotations

import warnings

import numpy as np

from calibration.camera import CameraModel, look_at
from simulator.render import render
from simulator.scene import Scene


def test_the_principal_ray_of_an_axis_aligned_camera_hits_the_far_wall():
    R, t = look_at((0.0, 1.5, 2.5), (0.0, 1.5, 0.0))  # optical axis along -z, the ray through (cx, cy) has x = y = 0
    cam = CameraModel("c", 64, 48, [[40.0, 0, 32.0], [0, 40.0, 24.0], [0, 0, 1]], np.zeros(5), R, t)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # inf * 0 in the floor points warned before
        r = render(Scene(seed=0, people=0, name="empty"), cam, 0.5)
    centre = float(r.depth[24, 32])
    assert centre > 1.0 and abs(centre - float(r.depth[24, 31])) < 1e-3 and abs(centre - float(r.depth[23, 32])) < 1e-3
    assert np.abs(r.rgb[24, 32].astype(int) - r.rgb[24, 31].astype(int)).max() < 20
