"""Fixtures of the model tests: small exported models (made once per session, in a temp dir) and a
simulator frame set with ground truth."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

torch.set_num_threads(2)


@dataclass
class Exported:
    path: Path
    backbone: str


def _export(tmp_path_factory, backbone: str) -> Exported:
    """Export through the command line, as a user would; once per test run, also when pytest-xdist
    runs the tests in several processes (they share the parent of their temp folders, and the
    first to take the lock exports)."""
    import os

    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # pytest-N/popen-gwK under xdist
    folder = shared / f"exported-model-{backbone}"
    with FileLock(str(shared / f"exported-model-{backbone}.lock")):
        out = folder / f"{backbone}.onnx"
        if not out.is_file():
            folder.mkdir(exist_ok=True)
            _export_to(out, backbone)
    return Exported(out, backbone)


def _export_to(out: Path, backbone: str) -> None:
    import contextlib
    import io
    import json

    from rig.cli import main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        rc = main(["model", "export", "--backbone", backbone, "--size", "test", "--fp16", "-o", str(out), "--json"])
    assert rc == 0 and out.is_file()
    assert json.loads(printed.getvalue())["files"] == [str(out), str(out.with_name(f"{backbone}.fp16.onnx"))]


@pytest.fixture(scope="session")
def tiny_onnx(tmp_path_factory) -> Exported:
    return _export(tmp_path_factory, "tiny")


@pytest.fixture(scope="session")
def oracle_onnx(tmp_path_factory) -> Exported:
    return _export(tmp_path_factory, "oracle")


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
