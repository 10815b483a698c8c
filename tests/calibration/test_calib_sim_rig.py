"""Acceptance against simulator ground truth: a six-camera 1280x720 rig, a ChArUco board carried
through the volume, images from the simulator's renderer and sensor model, calibrated with
`rig calibrate run` exactly as real images would be."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.boards import CharucoSpec
from calibration.camera import RigCalibration
from calibration.compare import describe, errors_against_truth
from rig.cli import main
from tests.calibration.cli_helpers import run_json

pytestmark = pytest.mark.slow

# An A0-size board (1.155 x 0.84 m), what a rig whose cameras stand 3.6 m from the volume needs:
# squares of ~30 px in every view, corners over a quarter of each image.
BOARD = CharucoSpec(squares_x=11, squares_y=8, square_size=0.105, marker_size=0.078, dictionary="DICT_5X5_100")
TIME_STEPS = 40
# Measured worst: focal 0.011 %, principal point 0.46 px, rotation 0.018 deg, position 0.53 mm, baseline 0.00037 %.
TOLERANCE = {"focal_pct": 0.05, "principal_px": 1.0, "baseline_pct": 0.002, "rotation_deg": 0.05, "position_mm": 2.0}


@pytest.fixture(scope="session")
def sim_sequence(tmp_path_factory):
    """DIR/CAMNAME/NNNN.png of the board moving through the volume, the board file and the true rig."""
    sensor_mod = pytest.importorskip("simulator.sensor")
    from simulator.rig import virtual_rig
    from simulator.scene import Scene

    root = tmp_path_factory.mktemp("sim-charuco")
    truth = virtual_rig(6, 1280, 720)
    scene = Scene(seed=0, people=0, board=BOARD)
    exposure = sensor_mod.NOMINAL_EXPOSURE_S
    for cam in truth.cameras:
        (root / "images" / cam.name).mkdir(parents=True)
        sensor = sensor_mod.SensorModel(scene, cam, {"motion_blur": False})
        for k in range(TIME_STEPS):
            t = scene.board_period * k / TIME_STEPS
            rgb = sensor.expose(t, exposure, sensor.frame_rng(k))  # rendered, then shot and read noise
            cv2.imwrite(str(root / "images" / cam.name / f"{k:04d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    board_file = root / "board.toml"
    board_file.write_text("".join(f"{k} = {json.dumps(v)}\n" for k, v in BOARD.to_dict().items()))
    return root / "images", board_file, truth


@pytest.fixture(scope="session")
def sim_calibration(sim_sequence, tmp_path_factory):
    images, board_file, truth = sim_sequence
    out = tmp_path_factory.mktemp("sim-calib") / "calib.json"
    summary = run_json("calibrate", "run", "--images", images, "--board", board_file, "-o", out)
    return summary, RigCalibration.load(out), truth


def test_six_camera_rig_matches_the_ground_truth(sim_calibration):
    summary, calib, truth = sim_calibration
    assert calib.names == ["left", "sup1", "sup2", "sup3", "sup4", "right"]
    errs = errors_against_truth(calib, truth)  # compared in the calibration's frame: the left camera's
    print(f"\nsimulated ChArUco, 6 x 1280x720 cameras, {TIME_STEPS} time steps; errors against the ground truth:")
    for name, e in errs.cameras.items():
        print(f"  {name:>5}: {describe(e)}  (views {summary['views_used'][name]}, RMS {summary['rms_px'][name]:.3f} px)")
    print(f"  baseline {summary['baseline_m'] * 1000:.2f} mm, stereo RMS {summary['stereo_rms_px']:.3f} px, "
          f"epipolar {summary['epipolar_rms_px']:.3f} px")
    worst = errs.worst
    print("  worst: " + ", ".join(f"{k} {v:.4g} (limit {TOLERANCE[k]})" for k, v in worst.items()))
    for k, limit in TOLERANCE.items():
        assert worst[k] <= limit, (k, worst[k], limit)


def test_every_camera_used_most_views_and_fits_tightly(sim_calibration):
    summary, calib, _ = sim_calibration
    assert all(n >= 0.8 * TIME_STEPS for n in summary["views_used"].values()), summary["views_used"]
    assert all(r < 0.2 for r in summary["rms_px"].values()), summary["rms_px"]
    assert summary["stereo_rms_px"] < 0.2 and summary["epipolar_rms_px"] < 0.3
    # The file carries the measurements the report needs.
    rep = calib.meta["report"]
    assert rep["views_multi_camera"] >= 0.8 * TIME_STEPS
    assert set(rep["cameras"]) == set(calib.names)


def test_the_json_answer_carries_every_camera_with_its_pose_and_verdict(sim_calibration):
    summary, calib, _ = sim_calibration
    per = summary["per_camera"]
    assert list(per) == calib.names
    for name, c in per.items():
        cam = calib[name]
        assert np.allclose(c["R"], cam.R) and np.allclose(c["t"], cam.t) and np.allclose(c["K"], cam.K) and np.allclose(c["dist"], cam.dist)
        assert c["rms_px"] == summary["rms_px"][name]
        assert c["verdict"] in ("good", "weak") and (c["verdict"] == "good") == (not c["reasons"]), c
        assert c["focal_spread_pct"] is not None and c["focal_spread_pct"] < 1.0, c
    assert summary["stereo_pair"] == {"left": "left", "right": "right"}


def test_exports_of_the_six_camera_rig(sim_calibration, tmp_path, capsys):
    _, calib, _ = sim_calibration
    path = tmp_path / "calib.json"
    calib.save(path)
    for fmt in ("opencv", "easymocap", "anipose", "nerfstudio", "colmap"):
        assert main(["calibrate", "export", str(path), "--format", fmt, "-o", str(tmp_path / fmt), "--json"]) == 0
        files = json.loads(capsys.readouterr().out)["files"]
        assert files and all(Path(f).is_file() and Path(f).is_relative_to(tmp_path / fmt) for f in files)
    data = json.loads((tmp_path / "nerfstudio" / "transforms.json").read_text())
    assert len(data["frames"]) == 6
    # The images it points at are written: by default, a view of the images the calibration was made from.
    assert all((tmp_path / "nerfstudio" / f["file_path"]).is_file() for f in data["frames"])
