"""The rig solver on board observations computed from known cameras (no images involved)."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.boards import CharucoSpec
from calibration.camera import CalibrationError
from calibration.compare import describe, errors_against_truth
from calibration.detect import Corners
from calibration.solve import calibrate_rig
from calibration.synthetic import arc_rig, board_poses, observe

BOARD = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")


@pytest.fixture(scope="module")
def truth():
    return arc_rig(6)


def test_exact_observations_give_the_exact_rig(truth):
    det = observe(truth, BOARD, board_poses(25), noise_px=0.0)
    result = calibrate_rig(det, BOARD)
    assert result.rig.names == ["left", "sup1", "sup2", "sup3", "sup4", "right"]
    # Exact observations are fitted to round-off: measured up to focal 1e-13 %, principal point 8e-12 px,
    # rotation 3e-13 deg, position 2e-11 mm, baseline 6e-14 %, distortion 7e-13 (varying about tenfold
    # with the BLAS thread count); the bounds leave a hundredfold margin for other machines' round-off.
    errs = errors_against_truth(result.rig, truth)
    for name, e in errs.cameras.items():
        assert e["focal_pct"] < 1e-11 and e["principal_px"] < 1e-9 and e["rotation_deg"] < 3e-11 and e["position_mm"] < 2e-9, (name, e)
    assert errs.baseline_pct < 1e-11
    for cam in result.rig.cameras:
        assert np.allclose(cam.dist, truth[cam.name].dist, rtol=0, atol=1e-10)


def test_noisy_observations_stay_within_tolerance(truth):
    det = observe(truth, BOARD, board_poses(50), noise_px=0.1)
    result = calibrate_rig(det, BOARD)
    errs = errors_against_truth(result.rig, truth)
    print()
    for name, e in errs.cameras.items():
        print(f"{name:>6}: {describe(e)}")
    print(f" worst: {describe(errs.worst)}")
    rms = result.rig.meta["rms_px"]
    # 0.1 px per axis of noise gives an RMS of about 0.14 px per corner (measured 0.137 to 0.141).
    assert all(0.13 < v < 0.15 for v in rms.values()), rms
    # Measured worst: focal 0.040 %, principal point 0.77 px, rotation 0.025 deg, position 0.92 mm, baseline 0.016 %.
    for name, e in errs.cameras.items():
        assert e["focal_pct"] < 0.2 and e["principal_px"] < 1.5 and e["rotation_deg"] < 0.05 and e["position_mm"] < 3, (name, e)
    assert errs.baseline_pct < 0.1


def test_a_bad_view_is_rejected_with_its_reason(truth):
    det = observe(truth, BOARD, board_poses(30), noise_px=0.1)
    # One camera's detection in one view is wrong by several pixels (a mis-detected board).
    view = sorted(det.corners["sup2"])[7]
    c = det.corners["sup2"][view]
    det.corners["sup2"][view] = Corners(c.ids, c.points + np.where(c.ids % 2 == 0, 6.0, -6.0)[:, None])
    result = calibrate_rig(det, BOARD)
    rejected = [(r.camera, r.view) for r in result.rejected]
    assert rejected == [("sup2", view)]  # that view, and no good one with it
    reason = next(r.reason for r in result.rejected if (r.camera, r.view) == ("sup2", view))
    assert "reprojection RMS" in reason and "px" in reason
    assert result.rig.meta["rms_px"]["sup2"] < 0.15  # the noise's 0.14 px (measured 0.137), not the bad view's 6 px
    assert any(r["view"] == view for r in result.rig.meta["rejected"])


def test_a_camera_that_never_sees_the_board_with_the_others_is_an_error(truth):
    det = observe(truth, BOARD, board_poses(30), noise_px=0.1)
    # sup4's views are renamed so that none coincides with another camera's view.
    det.corners["sup4"] = {f"x{v}": c for v, c in det.corners["sup4"].items()}
    with pytest.raises(CalibrationError, match="sup4"):
        calibrate_rig(det, BOARD)


def test_too_few_views_is_an_error(truth):
    det = observe(truth, BOARD, board_poses(30), noise_px=0.1)
    det.corners["sup3"] = dict(list(det.corners["sup3"].items())[:2])
    with pytest.raises(CalibrationError, match="sup3.*only 2"):
        calibrate_rig(det, BOARD)
