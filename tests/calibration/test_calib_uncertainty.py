"""The intrinsics' one-sigma uncertainty: measured where the views determine the intrinsics, and
'unknown' (null in the file, 'unknown' in print), never 0, where they do not."""
from __future__ import annotations

import json

import numpy as np
import pytest

from calibration import bundle
from calibration.boards import CharucoSpec
from calibration.camera import CameraModel, RigCalibration, intrinsics_from_fov
from calibration.detect import Corners
from calibration.geometry import rodrigues, rotation_vector
from calibration.images import DetectionSet
from calibration.report import format_report
from calibration.solve import calibrate_rig
from calibration.synthetic import arc_rig, board_poses, observe
from calibration.uncertainty import parameter_std

BOARD = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
CAMERA = CameraModel("left", 1280, 720, intrinsics_from_fov(1280, 720, 60.0), np.array([-0.08, 0.05, 0.0004, -0.0003, 0.0]))


def _board_views(n: int, tilt: float = 0.0, tilted_views: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board-to-camera poses: the board turned about the optical axis and moved, fronto-parallel
    (facing the camera squarely) unless `tilted_views` of them are tilted by `tilt` radians."""
    rng = np.random.default_rng(0)
    poses = []
    for v in range(n):
        R = rodrigues(np.array([0.0, 0.0, rng.uniform(-0.5, 0.5)]))
        if v < tilted_views:
            R = rodrigues(np.array([tilt, -tilt, 0.0])) @ R
        poses.append((R, np.array([rng.uniform(-0.4, 0.1), rng.uniform(-0.3, 0.1), rng.uniform(1.2, 2.5)])))
    return poses


def _exact_problem(poses):
    """A one-camera bundle problem whose observations are the exact projections, and the true state."""
    ids, obj = BOARD.object_points()
    uv = [CAMERA.project(obj @ R.T + t)[0] for R, t in poses]
    problem = bundle.Problem(np.zeros(len(ids) * len(poses), int), np.repeat(np.arange(len(poses)), len(ids)),
                             np.tile(obj, (len(poses), 1)), np.concatenate(uv), 1, len(poses))
    intr = np.array([[CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy, *CAMERA.dist]])
    views = np.array([np.concatenate([rotation_vector(R), t]) for R, t in poses])
    return problem, intr, np.zeros((1, 6)), views


def _noisy(problem, seed=1, sigma=0.1):
    rng = np.random.default_rng(seed)
    return bundle.Problem(problem.cam_idx, problem.view_idx, problem.board_xyz, problem.uv + rng.normal(0, sigma, problem.uv.shape),
                          problem.n_cameras, problem.n_views)


def test_the_uncertainty_is_measured_and_matches_the_actual_error():
    truth = arc_rig(6)
    result = calibrate_rig(observe(truth, BOARD, board_poses(50), noise_px=0.1), BOARD)
    report = result.rig.meta["report"]
    assert result.solution.std_unknown_reason is None
    for cam in result.rig.cameras:
        std = report["cameras"][cam.name]["std"]
        assert all(v is not None and 0 < v < 2.0 for v in std.values()), (cam.name, std)  # measured 0.25 to 0.86 px
        # The actual errors are within a few sigma (measured: at most 1.4): the figure means what it says.
        g = truth[cam.name]
        for k, est, true in (("fx", cam.fx, g.fx), ("fy", cam.fy, g.fy), ("cx", cam.cx, g.cx), ("cy", cam.cy, g.cy)):
            assert abs(est - true) < 4 * std[k], (cam.name, k, est - true, std[k])
    assert not any("uncertainty" in w or "poorly determined" in w for w in report["warnings"])


def test_fronto_parallel_views_leave_the_focal_length_unknown():
    # A board only ever facing the camera squarely cannot separate focal length from distance:
    # scaling both (and the distortion with them) gives the same image. Held at the truth, the
    # adjustment's normal matrix is exactly singular along that direction.
    problem, intr, cams, views = _exact_problem(_board_views(12))
    sol = bundle.solve(_noisy(problem), intr, cams, views, max_iterations=0)
    assert np.isnan(sol.intrinsics_std[0, 0]) and np.isnan(sol.intrinsics_std[0, 1])
    assert "singular" in sol.std_unknown_reason
    # Two tilted views break the tie: every uncertainty is then measured.
    problem, intr, cams, views = _exact_problem(_board_views(12, tilt=0.4, tilted_views=2))
    sol = bundle.solve(_noisy(problem), intr, cams, views, max_iterations=0)
    assert sol.std_unknown_reason is None and np.all(np.isfinite(sol.intrinsics_std)) and np.all(sol.intrinsics_std > 0)


def test_too_few_observations_leave_every_uncertainty_unknown():
    problem, intr, cams, views = _exact_problem(_board_views(1))
    few = bundle.Problem(problem.cam_idx[:5], problem.view_idx[:5], problem.board_xyz[:5], problem.uv[:5], 1, 1)
    sol = bundle.solve(_noisy(few), intr, cams, views)
    assert np.all(np.isnan(sol.intrinsics_std))
    assert "10 residuals for 15 unknowns" in sol.std_unknown_reason


def test_a_held_parameter_has_no_uncertainty_rather_than_zero():
    problem, intr, cams, views = _exact_problem(_board_views(12, tilt=0.4, tilted_views=6))
    fixed = np.zeros((1, bundle.N_INTR), bool)
    fixed[0, 8] = True  # k3 held, as the solver does with few views
    sol = bundle.solve(_noisy(problem), intr, cams, views, fixed_intrinsics=fixed)
    assert np.isnan(sol.intrinsics_std[0, 8]) and np.all(np.isfinite(sol.intrinsics_std[0, :8]))


def test_the_report_says_unknown_where_the_views_are_degenerate(tmp_path):
    ids, obj = BOARD.object_points()
    corners = {f"{v:04d}": Corners(ids, CAMERA.project(obj @ R.T + t)[0]) for v, (R, t) in enumerate(_board_views(12))}
    det = DetectionSet({"left": (1280, 720)}, {"left": corners}, {"left": 12})
    result = calibrate_rig(det, BOARD)
    path = tmp_path / "calib.json"
    result.rig.save(path)
    stored = json.loads(path.read_text())["report"]
    assert stored["cameras"]["left"]["std"]["fx"] is None and stored["cameras"]["left"]["std"]["fy"] is None
    assert any("uncertainty of fx, fy" in w and "unknown" in w for w in stored["warnings"])
    text = format_report(RigCalibration.load(path))
    line = next(line for line in text.splitlines() if line.strip().startswith("left") and "fx " in line and "fy " in line)
    assert "fx unknown" in line and "fy unknown" in line
    assert " 0.000" not in line and " 0 " not in line


def _block_jacobian(n_front=12, n_views=30, rows_per_view=20, seed=0):
    """A Jacobian shaped like the bundle adjustment's: every row depends on the front parameters and
    on the 6 pose parameters of its own view only."""
    rng = np.random.default_rng(seed)
    J = np.zeros((n_views * rows_per_view, n_front + 6 * n_views))
    for v in range(n_views):
        rows = slice(v * rows_per_view, (v + 1) * rows_per_view)
        J[rows, :n_front] = rng.normal(size=(rows_per_view, n_front))
        J[rows, n_front + 6 * v : n_front + 6 * v + 6] = rng.normal(size=(rows_per_view, 6))
    return J


def test_marginalising_the_board_poses_gives_the_full_inverse():
    J = _block_jacobian()
    H = J.T @ J
    cost, m = 3.0, len(J)
    std, why = parameter_std(H, cost, m, n_front=12)
    full = np.sqrt(np.diag(np.linalg.inv(H)) * cost / (m - len(H)))[:12]
    assert why is None and np.allclose(std, full, rtol=1e-9, atol=0)
    # A board pose the residuals do not determine (a view whose pose has a free direction) sends the
    # computation to the whole matrix; the front's uncertainty is still known and the same.
    J[:, 12 + 6 * 4] = 0.0
    std2, why2 = parameter_std(J.T @ J, cost, m, n_front=12)
    rest = np.delete(J, 12 + 6 * 4, axis=1)
    expected = np.sqrt(np.diag(np.linalg.inv(rest.T @ rest)) * cost / (m - len(H)))[:12]
    assert why2 is None and np.allclose(std2, expected, rtol=1e-9, atol=0)
    # A front parameter tied to another one (two identical columns) is unknown, the others are not.
    J = _block_jacobian()
    J[:, 1] = J[:, 0]
    std3, why3 = parameter_std(J.T @ J, cost, m, n_front=12)
    assert np.isnan(std3[0]) and np.isnan(std3[1]) and np.all(np.isfinite(std3[2:])) and "singular" in why3


@pytest.mark.parametrize("std, shown", [(None, "unknown"), (3.2e-05, "3.2e-05"), (0.0412, "0.0412")])
def test_a_small_known_uncertainty_is_printed_with_its_digits(std, shown):
    cam = CAMERA
    calib = RigCalibration([cam], {"report": {
        "cameras": {"left": {"std": {"fx": std, "fy": std, "cx": std, "cy": std}, "coverage": {"fraction": 1.0, "grid": ["#"], "never_seen": []}}},
        "views_total": 1, "views_multi_camera": 0,
    }})
    line = next(line for line in format_report(calib).splitlines() if line.strip().startswith("left") and "fx " in line)
    assert line.split() == ["left", "fx", shown, "fy", shown, "cx", shown, "cy", shown]
