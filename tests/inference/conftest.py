"""Fixtures of the model tests: a simulator frame set with ground truth (the small exported models
they use, `tiny_onnx` and `oracle_onnx`, are in tests/conftest.py: the live tests use them too)."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

if not os.environ.get("PYTEST_XDIST_WORKER_COUNT"):  # under xdist, tests/conftest.py shares the cores out
    torch.set_num_threads(2)


@dataclass
class SimFrames:
    """A six-camera simulator frame set at one instant, rendered at `size`, with ground truth."""

    scene: object
    rig: object  # RigCalibration
    rgb: dict[str, np.ndarray]
    depth: dict[str, np.ndarray]

    def render(self, camera, t: float = 1.0):
        from simulator.render import render

        return render(self.scene, camera, t)


@pytest.fixture(scope="session")
def sim_frames() -> SimFrames:
    render_mod = pytest.importorskip("simulator.render", reason="the simulator's renderer is not available")
    from simulator.rig import virtual_rig
    from simulator.scene import Scene

    rig = virtual_rig(6, 640, 360)  # the preview output size; distortion as a real rig has
    scene = Scene(seed=0)
    rgb, depth = {}, {}
    for cam in rig.cameras:
        r = render_mod.render(scene, cam, 1.0)
        rgb[cam.name] = r.rgb
        depth[cam.name] = r.depth
    return SimFrames(scene, rig, rgb, depth)
