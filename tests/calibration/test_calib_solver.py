"""The rig solver on board observations computed from known cameras (no images involved)."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.synthetic import arc_rig, board_poses, in_frame_of, observe
from calibration.boards import CharucoSpec
from calibration.camera import CalibrationError
from calibration.detect import Corners
from calibration.geometry import rotation_angle_deg
from calibration.solve import calibrate_rig

BOARD = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")


@pytest.fixture(scope="module")
def truth():
    return arc_rig(6)


def errors(result, truth):
    gt = in_frame_of(truth, result.left)
    out = {}
    for cam in result.rig.cameras:
        g = gt[cam.name]
        out[cam.name] = {
            "f_pct": 100 * max(abs(cam.fx / g.fx - 1), abs(cam.fy / g.fy - 1)),
            "pp_px": float(np.hypot(cam.cx - g.cx, cam.cy - g.cy)),
            "rot_deg": rotation_angle_deg(cam.R, g.R),
            "pos_mm": 1000 * float(np.linalg.norm(cam.center - g.center)),
        }
    return out


def test_exact_observations_give_the_exact_rig(truth):
    det = observe(truth, BOARD, board_poses(25), noise_px=0.0)
    result = calibrate_rig(det, BOARD)
    assert result.rig.names == ["left", "sup1", "sup2", "sup3", "sup4", "right"]
    for name, e in errors(result, truth).items():
        assert e["f_pct"] < 1e-5 and e["pp_px"] < 1e-4 and e["rot_deg"] < 1e-6 and e["pos_mm"] < 1e-4, (name, e)
    gt = in_frame_of(truth, "left")
    for cam in result.rig.cameras:
        assert np.allclose(cam.dist, gt[cam.name].dist, atol=1e-6)


def test_noisy_observations_stay_within_tolerance(truth):
    det = observe(truth, BOARD, board_poses(50), noise_px=0.1)
    result = calibrate_rig(det, BOARD)
    errs = errors(result, truth)
    print()
    for name, e in errs.items():
        print(f"{name:>6}: focal {e['f_pct']:.4f}%  principal point {e['pp_px']:.3f} px  rotation {e['rot_deg']:.4f} deg  position {e['pos_mm']:.3f} mm")
    rms = result.rig.meta["rms_px"]
    # 0.1 px per axis of noise gives an RMS of about 0.14 px per corner.
    assert all(0.12 < v < 0.16 for v in rms.values()), rms
    for name, e in errs.items():
        assert e["f_pct"] < 0.2 and e["pp_px"] < 1.5 and e["rot_deg"] < 0.05 and e["pos_mm"] < 3, (name, e)


def test_a_bad_view_is_rejected_with_its_reason(truth):
    det = observe(truth, BOARD, board_poses(30), noise_px=0.1)
    # One camera's detection in one view is wrong by several pixels (a mis-detected board).
    view = sorted(det.corners["sup2"])[7]
    c = det.corners["sup2"][view]
    det.corners["sup2"][view] = Corners(c.ids, c.points + np.where(c.ids % 2 == 0, 6.0, -6.0)[:, None])
    result = calibrate_rig(det, BOARD)
    rejected = [(r.camera, r.view) for r in result.rejected]
    assert ("sup2", view) in rejected
    reason = next(r.reason for r in result.rejected if (r.camera, r.view) == ("sup2", view))
    assert "reprojection RMS" in reason and "px" in reason
    assert result.rig.meta["rms_px"]["sup2"] < 0.2
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
