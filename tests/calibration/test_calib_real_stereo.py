"""Acceptance on real images: the XIMEA stereo pair, 25 chessboard pairs (9x6 inner corners, 24 mm)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from rig.cli import main
from tests.calibration.cli_helpers import run_json

FX_REFERENCE = 519.4
BASELINE_REFERENCE_M = 0.092


@pytest.fixture(scope="module")
def xi_images(shared_data):
    return shared_data / "xi-stereo-chessboard"


@pytest.fixture(scope="module")
def chessboard_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("board") / "board.toml"
    path.write_text('type = "chessboard"\ncols = 9\nrows = 6\nsquare_size = 0.024\n')
    return path


@pytest.fixture(scope="module")
def xi_run(xi_images, chessboard_file, tmp_path_factory):
    """`rig calibrate run --json` on the folder of leftNN/rightNN pairs."""
    out = tmp_path_factory.mktemp("calib") / "xi.json"
    return run_json("calibrate", "run", "--images", xi_images, "--board", chessboard_file, "-o", out), out


def test_board_is_found_in_all_25_pairs(xi_run):
    summary, _ = xi_run
    assert summary["images"] == {"left": 25, "right": 25}
    assert summary["views_found"] == {"left": 25, "right": 25}
    assert summary["views_used"] == {"left": 25, "right": 25}


def test_focal_lengths_stereo_rms_and_baseline(xi_run):
    summary, _ = xi_run
    fx = {c: v["fx"] for c, v in summary["intrinsics"].items()}
    fx_err = {c: 100 * abs(f / FX_REFERENCE - 1) for c, f in fx.items()}
    base_err = 100 * abs(summary["baseline_m"] / BASELINE_REFERENCE_M - 1)
    print(
        f"\nxi stereo: fx left {fx['left']:.2f} px ({fx_err['left']:.2f}% from {FX_REFERENCE}), "
        f"fx right {fx['right']:.2f} px ({fx_err['right']:.2f}%), RMS {summary['rms_px']}, "
        f"stereo RMS {summary['stereo_rms_px']:.3f} px, baseline {summary['baseline_m'] * 1000:.2f} mm ({base_err:.2f}% from 92 mm), "
        f"epipolar {summary['epipolar_rms_px']:.3f} px RMS"
    )
    assert fx_err["left"] < 1.0 and fx_err["right"] < 1.0
    assert summary["stereo_rms_px"] <= 0.25
    assert base_err < 1.0  # measured 0.18 % from the nominal 92 mm
    assert summary["epipolar_rms_px"] < 0.3


def test_calibration_file_has_the_versioned_schema_and_metadata(xi_run):
    from calibration.camera import RigCalibration

    _, path = xi_run
    data = json.loads(path.read_text())
    assert data["version"] == 1
    assert [c["name"] for c in data["cameras"]] == ["left", "right"]
    for key in ("board", "date", "rms_px", "stereo_rms_px", "baseline_m", "views_used", "report"):
        assert key in data
    rig = RigCalibration.load(path)
    assert np.allclose(rig["left"].R, np.eye(3)) and np.allclose(rig["left"].t, 0)
    assert data["board"] == {"type": "chessboard", "cols": 9, "rows": 6, "square_size": 0.024}


def test_report_reprints_the_stored_measurements(xi_run, capsys):
    _, path = xi_run
    assert main(["calibrate", "report", str(path)]) == 0
    text = capsys.readouterr().out
    assert "stereo pair left-right" in text and "board coverage" in text
    assert main(["calibrate", "report", str(path), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["report"]["stereo"]["common_views"] == 25
    assert len(rep["report"]["per_view"]) == 25
    grid = rep["report"]["cameras"]["left"]["coverage"]["grid"]
    assert len(grid) == 6 and all(len(row) == 8 for row in grid)
