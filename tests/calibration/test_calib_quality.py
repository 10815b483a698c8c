"""A calibration from weak data says so: a small board kept near the middle of the volume."""
from __future__ import annotations

import numpy as np

from calibration.boards import CharucoSpec
from calibration.geometry import rodrigues
from calibration.quality import focal_spread
from calibration.solve import Options, calibrate_rig
from calibration.synthetic import arc_rig, observe


def test_a_small_board_in_one_place_and_no_prior_intrinsics_is_weak_not_silently_wrong():
    truth = arc_rig(4)
    board = CharucoSpec(7, 5, 0.05, 0.037, "DICT_5X5_100")  # 0.35 x 0.25 m at 3 m: a tenth of the image across
    rng = np.random.default_rng(3)
    poses = []
    for _ in range(20):
        centre = np.array([rng.uniform(-0.15, 0.15), rng.uniform(1.0, 1.2), rng.uniform(-0.1, 0.1)])
        poses.append((rodrigues(np.array([np.pi, 0.0, 0.0])) @ rodrigues(rng.normal(0, 0.2, size=3)), centre))
    result = calibrate_rig(observe(truth, board, poses, noise_px=0.3), board, Options())
    rep = result.rig.meta["report"]
    for cam in result.rig.cameras:
        c = rep["cameras"][cam.name]
        assert c["verdict"] == "weak", (cam.name, c["verdict"])
        assert c["focal_spread_pct"] > 1.0 and any("between subsets of the views" in r for r in c["reasons"]), c["reasons"]
        assert any("covered only" in r for r in c["reasons"])


def test_the_spread_is_the_jackknife_standard_deviation():
    # fx of each leave-one-out fit: 100 + the left-out view's number; jackknife sd = sqrt((n-1)/n * sum(d^2))
    views = [str(i) for i in range(6)]
    fx = {str(i): 100.0 + i for i in range(6)}
    spread = focal_spread(views, lambda subset: fx[next(v for v in views if v not in subset)])
    d = np.array([100.0 + i for i in range(6)])
    expected = np.sqrt(5 / 6 * np.sum((d - d.mean()) ** 2)) / d.mean()
    assert abs(spread - expected) < 1e-12
    assert focal_spread(views[:4], lambda s: 1.0) is None  # too few views to resample


def test_square_pixels_and_a_centred_principal_point_hold_through_the_joint_fit():
    from calibration.synthetic import board_poses

    truth = arc_rig(3)
    board = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
    det = observe(truth, board, board_poses(20), noise_px=0.2)
    result = calibrate_rig(det, board, Options(square_pixels=True, centred=True))
    for cam in result.rig.cameras:
        assert cam.fx == cam.fy and abs(cam.fx / truth[cam.name].fx - 1) < 0.01, (cam.name, cam.fx, cam.fy, truth[cam.name].fx)
        assert (cam.cx, cam.cy) == ((cam.width - 1) / 2, (cam.height - 1) / 2)
        assert result.intrinsics[cam.name].K[0, 0] == result.intrinsics[cam.name].K[1, 1]
    free = calibrate_rig(det, board, Options())
    assert all(c.fx != c.fy for c in free.rig.cameras)
