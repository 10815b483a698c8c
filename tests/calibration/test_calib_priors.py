"""Given intrinsics as priors with a stated sigma (`rig calibrate run --intrinsics F --prior-sigma S`)."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.boards import CharucoSpec
from calibration.camera import CalibrationError
from calibration.compare import errors_against_truth
from calibration.known import KnownIntrinsics, parse_prior, prior_sigmas
from calibration.solve import Options, calibrate_rig
from calibration.synthetic import arc_rig, board_poses, observe

BOARD = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")


def _given(truth, focal_error: float) -> dict[str, KnownIntrinsics]:
    """The true intrinsics with every focal length off by `focal_error` (relative)."""
    out = {}
    for c in truth.cameras:
        K = c.K.copy()
        K[0, 0] *= 1 + focal_error
        K[1, 1] *= 1 + focal_error
        out[c.name] = KnownIntrinsics(c.name, (c.width, c.height), K, c.dist.copy())
    return out


def test_a_loose_prior_lets_good_data_correct_the_given_focal_length_and_says_how_far():
    truth = arc_rig(3)
    det = observe(truth, BOARD, board_poses(30), noise_px=0.2)
    given = _given(truth, 0.02)  # 2 % off: what a lens data sheet or another session may give
    held = calibrate_rig(det, BOARD, Options(known=given))
    loose = calibrate_rig(det, BOARD, Options(known=given, prior=parse_prior("f=5%")))
    for cam in loose.rig.cameras:
        assert abs(held.rig[cam.name].fx / truth[cam.name].fx - 1.02) < 1e-9  # held: the given value stays
        assert abs(cam.fx / truth[cam.name].fx - 1) < 0.002, (cam.name, cam.fx, truth[cam.name].fx)
        p = loose.rig.meta["report"]["cameras"][cam.name]["prior"]
        assert set(p) == {"fx", "fy"} and p["fx"]["sigma"] == pytest.approx(0.05 * given[cam.name].K[0, 0], rel=1e-3)
        assert p["fx"]["moved_sigma"] == pytest.approx(p["fx"]["moved"] / p["fx"]["sigma"], abs=1e-3) and -0.45 < p["fx"]["moved_sigma"] < -0.35
        assert np.array_equal(cam.dist, truth[cam.name].dist)  # terms not named stay held
    assert max(e["position_mm"] for e in errors_against_truth(loose.rig, truth).cameras.values()) < \
        max(e["position_mm"] for e in errors_against_truth(held.rig, truth).cameras.values())
    assert held.rig.meta["rms_px"]["left"] > 1.25 * loose.rig.meta["rms_px"]["left"]  # measured 0.37 against 0.27


def test_a_tight_prior_is_a_hold_and_a_prior_steadies_weak_data():
    truth = arc_rig(3)
    det = observe(truth, BOARD, board_poses(30), noise_px=0.2)
    given = _given(truth, 0.02)
    tight = calibrate_rig(det, BOARD, Options(known=given, prior=parse_prior("f=0.0001%,c=0.0001")))
    for cam in tight.rig.cameras:
        assert abs(cam.fx / given[cam.name].K[0, 0] - 1) < 1e-6
    # weak data: a small board kept in the middle; free intrinsics wander, the true ones as a 1 % prior do not
    small = CharucoSpec(7, 5, 0.05, 0.037, "DICT_5X5_100")
    rng = np.random.default_rng(3)
    from calibration.geometry import rodrigues

    poses = [(rodrigues(np.array([np.pi, 0.0, 0.0])) @ rodrigues(rng.normal(0, 0.2, size=3)),
              np.array([rng.uniform(-0.15, 0.15), rng.uniform(1.0, 1.2), rng.uniform(-0.1, 0.1)])) for _ in range(20)]
    weak = observe(truth, small, poses, noise_px=0.3)
    free = calibrate_rig(weak, small, Options())
    prior = calibrate_rig(weak, small, Options(known=_given(truth, 0.0), prior=parse_prior("f=1%,c=10,dist=0.05")))
    err_free = max(abs(c.fx / truth[c.name].fx - 1) for c in free.rig.cameras)
    err_prior = max(abs(c.fx / truth[c.name].fx - 1) for c in prior.rig.cameras)
    assert err_prior < 0.01 and err_prior < 0.5 * err_free, (err_prior, err_free)


def test_bad_prior_specs_say_what_is_wrong():
    with pytest.raises(CalibrationError, match="expected TERM=SIGMA"):
        parse_prior("focal=3")
    with pytest.raises(CalibrationError, match="positive"):
        parse_prior("f=-1")
    with pytest.raises(CalibrationError, match="only f and c"):
        parse_prior("k1=1%")
    with pytest.raises(CalibrationError, match="not a number"):
        parse_prior("c=abc")
    pinhole = KnownIntrinsics("cam", (640, 480), np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.zeros(5))
    with pytest.raises(CalibrationError, match="pinhole lens, whose terms are k1 k2 p1 p2 k3"):
        prior_sigmas(pinhole, parse_prior("k4=0.1"))
    assert prior_sigmas(pinhole, parse_prior("f=2%,dist=0.01")) == {"fx": 10.0, "fy": 10.0, **{t: 0.01 for t in ("k1", "k2", "p1", "p2", "k3")}}
