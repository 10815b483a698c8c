"""`rig sim snapshot`: ground truth of every camera of a sim config, as a user runs it."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from calibration.camera import RigCalibration
from simulator.render import render
from simulator.scene import Scene

REPO = Path(__file__).resolve().parents[2]


def run_rig(*args, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=REPO)


def _one_line_error(proc, fragment):
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert fragment in lines[0], lines[0]


def test_snapshot_writes_images_depth_masks_and_exact_calibration(tmp_path):
    cfg = tmp_path / "rig.toml"
    proc = run_rig("config", "init", "--sim", "--cameras", "3", "--width", "192", "--height", "108", cfg)
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "snap"
    proc = run_rig("sim", "snapshot", "-c", cfg, "-t", "1.25", "-o", out, "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    names = [c["name"] for c in summary["cameras"]]
    assert names == ["left", "sup1", "right"] and summary["time_s"] == 1.25

    calib = RigCalibration.load(out / "cameras.json")
    raw = json.loads((out / "cameras.json").read_text())
    assert raw["version"] == 1 and set(raw["cameras"][0]) >= {"name", "width", "height", "K", "dist", "R", "t"}
    assert calib.names == names
    scene = Scene.from_options(summary["scene"])
    for cam in calib.cameras:
        rgb = cv2.cvtColor(cv2.imread(str(out / f"{cam.name}.png")), cv2.COLOR_BGR2RGB)
        depth = np.load(out / f"{cam.name}.depth.npy")
        mask = cv2.imread(str(out / f"{cam.name}.mask.png"), cv2.IMREAD_UNCHANGED)
        assert rgb.shape == (108, 192, 3) and depth.dtype == np.float32 and depth.shape == (108, 192)
        assert set(np.unique(mask)) <= {0, 255} and mask.any()
        # the files are the renderer's ground truth for the calibration they come with
        again = render(scene, cam, 1.25)
        assert np.array_equal(again.rgb, rgb) and np.array_equal(again.depth, depth)
        assert np.array_equal(again.mask, mask > 0)


def test_snapshot_bad_input_is_one_line(tmp_path):
    cfg = tmp_path / "rig.toml"
    assert run_rig("config", "init", "--sim", cfg).returncode == 0
    _one_line_error(run_rig("sim", "snapshot", "-c", cfg, "-t", "-2", "-o", tmp_path / "o"), "time must be")
    _one_line_error(run_rig("sim", "snapshot", "-c", tmp_path / "missing.toml", "-t", "0", "-o", tmp_path / "o"), "no such config file")
    bad = tmp_path / "bad.toml"
    bad.write_text(cfg.read_text().replace('people = 2', 'people = 2\nmotion = "fly"'))
    _one_line_error(run_rig("sim", "snapshot", "-c", bad, "-t", "0", "-o", tmp_path / "o"), "motion")
