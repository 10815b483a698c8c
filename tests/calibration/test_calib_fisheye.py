"""The fisheye lens model (OpenCV's, k1..k4) through calibration, files, exports and resampling."""
from __future__ import annotations

import json
import tomllib

import cv2
import numpy as np
import pytest

from calibration import bundle, lens
from calibration.boards import CharucoSpec
from calibration.camera import CalibrationError, CameraModel, RigCalibration, look_at
from calibration.compare import errors_against_truth
from calibration.export import export, rectification_maps
from calibration.geometry import rodrigues
from calibration.known import load_known
from calibration.solve import Options, _equidistant_start, _planar, calibrate_rig
from calibration.synthetic import observe
from tests.calibration.cli_helpers import run_json

BOARD = CharucoSpec(9, 6, 0.06, 0.045, "DICT_5X5_100")
K_WIDE = np.array([[420.0, 0.0, 483.0], [0.0, 420.5, 268.0], [0.0, 0.0, 1.0]])  # 960x540, 137 degrees across
D_WIDE = np.array([0.03, -0.01, 0.004, -0.001])


def wide(name: str = "gopro", R=np.eye(3), t=np.zeros(3), K=K_WIDE, D=D_WIDE) -> CameraModel:
    return CameraModel(name, 960, 540, K, D, R, t, "fisheye")


def test_the_lens_is_opencvs_fisheye_model():
    cam = wide()
    rng = np.random.default_rng(0)
    P = rng.uniform([-3, -2, 0.5], [3, 2, 4], (500, 3))
    uv, _ = cam.project(P)
    ref, _ = cv2.fisheye.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-9
    xy = cam.undistort_normalized(uv)
    assert np.abs(xy - P[:, :2] / P[:, 2:]).max() < 1e-12
    assert np.abs(xy - cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)).max() < 1e-9
    # every k at 0 is the equidistant projection, not a pinhole: still a distorting lens
    assert wide(D=np.zeros(4)).has_distortion
    # a pixel the lens maps from beyond 90 degrees has no ray in front of the camera
    assert np.isnan(cam.undistort_normalized(np.array([[483.0 + 420.0 * 1.7, 268.0]]))).all()


def test_the_bundle_jacobian_of_a_fisheye_camera_matches_finite_differences():
    rng = np.random.default_rng(1)
    C, V = 2, 3
    problem = bundle.Problem(np.repeat([0, 1], 30), np.tile(np.repeat([0, 1, 2], 10), 2),
                             rng.uniform(-0.3, 0.3, (60, 3)) * [1, 1, 0], rng.uniform(0, 100, (60, 2)), C, V, np.array([True, False]))
    intr = np.array([[600, 590, 640, 360, 0.05, -0.02, 0.01, -0.003, 0], [700, 700, 640, 360, -0.1, 0.02, 0.001, 0.002, 0.01]])
    state = bundle.State.from_vectors(intr, [[0, 0, 0, 0, 0, 0], [0.1, 0.2, 0.05, -0.5, 0.1, 0.2]],
                                      [[0.1, 0.2, 0.3, 0, 0, 2], [0.3, -0.2, 0.1, 0.2, 0.1, 3], [0, 0, 0, 0, 0, 1.5]])
    J, ref = bundle.jacobian(problem, state), bundle.numeric_jacobian(problem, state)
    assert np.abs(J - ref).max() < 1e-5 * np.abs(ref).max()
    on_axis = bundle.Problem(np.array([0]), np.array([2]), np.zeros((1, 3)), np.zeros((1, 2)), C, V, np.array([True, False]))
    assert np.abs(bundle.jacobian(on_axis, state) - bundle.numeric_jacobian(on_axis, state)).max() < 1e-5


def _wide_views(n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board-to-world (R, centre) spread over a wide field in front of cameras at the origin looking along +z."""
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(n):
        a, b = np.radians(rng.uniform(-50, 50)), np.radians(rng.uniform(-30, 30))
        d = rng.uniform(0.6, 1.3)
        centre = d * np.array([np.sin(a) * np.cos(b), np.sin(b), np.cos(a) * np.cos(b)])
        R = rodrigues(np.array([0.0, a, 0.0])) @ rodrigues(rng.normal(0, 0.3, 3))  # facing the pair, tilted
        poses.append((R, centre))
    return poses


def _pair_rig() -> RigCalibration:
    Rl, tl = look_at((-0.15, 0.0, 0.0), (-0.15, 0.0, 1.0), up=(0.0, -1.0, 0.0))
    Rr, tr = look_at((0.15, 0.01, 0.0), (0.12, 0.0, 1.0), up=(0.0, -1.0, 0.0))
    Rm, tm = look_at((0.0, -0.1, -0.05), (0.0, 0.0, 1.0), up=(0.0, -1.0, 0.0))
    K2 = np.array([[432.0, 0.0, 478.0], [0.0, 431.0, 272.0], [0.0, 0.0, 1.0]])
    return RigCalibration([
        wide("left", Rl, tl),
        CameraModel("mid", 960, 540, [[700.0, 0, 481.0], [0, 700.0, 270.0], [0, 0, 1]], [-0.1, 0.05, 0.0, 0.0, 0.0], Rm, tm),
        wide("right", Rr, tr, K2, np.array([0.02, -0.005, 0.002, 0.0])),
    ])


def _observe(rig, poses, noise):
    return observe(rig, BOARD, poses, noise_px=noise, seed=3)


def test_a_rig_of_fisheye_and_pinhole_cameras_is_solved():
    truth = _pair_rig()
    det = _observe(truth, _wide_views(40, 2), 0.0)
    exact = calibrate_rig(det, BOARD, Options(fisheye={"left", "right"}))
    assert [c.model for c in exact.rig.cameras] == ["fisheye", "pinhole", "fisheye"]
    errs = errors_against_truth(exact.rig, truth)
    for name, e in errs.cameras.items():
        assert e["focal_pct"] < 1e-6 and e["principal_px"] < 1e-5 and e["rotation_deg"] < 1e-6 and e["position_mm"] < 1e-5, (name, e)
    assert exact.stereo_init["rms_px"] < 1e-4  # the pair's start on undistorted coordinates, reprojected through each lens

    noisy = calibrate_rig(_observe(truth, _wide_views(40, 2), 0.2), BOARD, Options(fisheye={"left", "right"}))
    errs = errors_against_truth(noisy.rig, truth)
    for name, e in errs.cameras.items():
        assert e["focal_pct"] < 0.3 and e["principal_px"] < 2.0 and e["rotation_deg"] < 0.1 and e["position_mm"] < 2.0, (name, e)
    assert all(0.25 < v < 0.32 for v in noisy.rig.meta["rms_px"].values()), noisy.rig.meta["rms_px"]
    # the same corners under the pinhole model fit worse where the lens is wide
    pinhole = calibrate_rig(_observe(truth, _wide_views(40, 2), 0.2), BOARD, Options())
    assert pinhole.rig.meta["rms_px"]["left"] > 1.5 * noisy.rig.meta["rms_px"]["left"]


def test_held_fisheye_intrinsics_from_an_anipose_file_keep_their_model(tmp_path):
    truth = _pair_rig()
    export(truth, "anipose", tmp_path)
    doc = tomllib.loads((tmp_path / "calibration.toml").read_text())
    assert doc["cam_0"]["fisheye"] is True and len(doc["cam_0"]["distortions"]) == 4 and "fisheye" not in doc["cam_1"]
    known = load_known(tmp_path / "calibration.toml")
    assert known["left"].model == "fisheye" and known["mid"].model == "pinhole"
    result = calibrate_rig(_observe(truth, _wide_views(30, 4), 0.2), BOARD, Options(known=known))
    for cam in result.rig.cameras:
        assert cam.model == truth[cam.name].model and np.allclose(cam.dist, truth[cam.name].dist) and np.allclose(cam.K, truth[cam.name].K)
    errs = errors_against_truth(result.rig, truth)
    assert all(e["rotation_deg"] < 0.05 and e["position_mm"] < 1.0 for e in errs.cameras.values()), errs.cameras


def test_the_equidistant_start_reaches_the_same_fit_as_opencvs():
    """OpenCV's fisheye start fails outright on some view sets (an assertion on a near-degenerate
    view); the solver then starts from the best equidistant lens. From there it must reach the fit
    OpenCV's start reaches."""
    cam = wide()
    det = observe(RigCalibration([cam]), BOARD, _wide_views(25, 5), noise_px=0.2, seed=3)
    views = det.corners["gopro"]
    _, obj_pts = BOARD.object_points()
    obj = [_planar(obj_pts[c.ids])[0].reshape(1, -1, 3) for c in views.values()]
    img = [c.points.reshape(1, -1, 2) for c in views.values()]
    K, D, rvecs, tvecs = _equidistant_start("gopro", (960, 540), obj, img)
    assert abs(K[0, 0] / cam.fx - 1) < 0.1 and not D.any() and len(rvecs) == len(obj)
    from calibration.solve import _fisheye_fit

    opts = Options(fisheye=True)
    via_opencv = _fisheye_fit("gopro", (960, 540), views, list(views), obj_pts, opts, False, None)
    via_start = _fisheye_fit("gopro", (960, 540), views, list(views), obj_pts, opts, False, None, guess=(K, D))
    assert abs(via_start.K[0, 0] - via_opencv.K[0, 0]) < 1e-3 and abs(via_start.rms - via_opencv.rms) < 1e-6
    assert abs(via_opencv.K[0, 0] / cam.fx - 1) < 0.003


def test_rendered_fisheye_views_give_the_lens_through_the_cli(tmp_path):
    """A wide camera rendered by the simulator, its board found by the detector, fitted by `rig
    calibrate intrinsics --fisheye`: the lens maps rays to pixels as the true one does across the
    image width; the pinhole model on the same views does not."""
    from simulator.calibration_session import plan_stations
    from simulator.render import render
    from simulator.scene import Scene

    R, t = look_at((0.0, 1.5, 2.5), (0.0, 1.2, 0.0))
    cam = wide("gopro", R, t)
    stations = plan_stations(RigCalibration([cam]), BOARD)
    scene = Scene(seed=0, people=0, board=BOARD, name="empty",
                  board_path=lambda s: (stations[min(int(s), len(stations) - 1)].R, stations[min(int(s), len(stations) - 1)].t))
    (tmp_path / "views" / "gopro").mkdir(parents=True)
    for k in range(len(stations)):
        rgb = render(scene, cam, k + 0.5).rgb
        cv2.imwrite(str(tmp_path / "views" / "gopro" / f"{k:04d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    (tmp_path / "board.toml").write_text('type = "charuco"\nsquares_x = 9\nsquares_y = 6\nsquare_size = 0.06\n'
                                         'marker_size = 0.045\ndictionary = "DICT_5X5_100"\n')
    out = run_json("calibrate", "intrinsics", "--images", tmp_path / "views", "--board", tmp_path / "board.toml",
                   "-o", tmp_path / "fisheye.json", "--fisheye")
    pin = run_json("calibrate", "intrinsics", "--images", tmp_path / "views", "--board", tmp_path / "board.toml",
                   "-o", tmp_path / "pinhole.json")
    fe, ph = out["cameras"]["gopro"], pin["cameras"]["gopro"]
    assert fe["model"] == "fisheye" and len(fe["dist"]) == 4 and ph["model"] == "pinhole"
    assert fe["rms_px"] < 0.2 and fe["rms_px"] < ph["rms_px"], (fe["rms_px"], ph["rms_px"])
    u, v = np.meshgrid(np.arange(0, 960, 8.0), np.arange(0, 540, 8.0))
    uv = np.stack([u, v], -1).reshape(-1, 2)
    rays = np.c_[cam.undistort_normalized(uv), np.ones(len(uv))]
    across = np.abs(uv[:, 1] - cam.cy) < 60  # a band through the middle, from edge to edge of the image

    def error(c, model):
        fitted = CameraModel("g", 960, 540, [[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1]], c["dist"], model=model)
        return np.linalg.norm(fitted.project(rays)[0] - uv, axis=1)

    # measured: fisheye 0.61 px at most across the width, 3.3 px in the far corners; pinhole 32 px
    assert error(fe, "fisheye")[across].max() < 1.0
    assert error(ph, "pinhole")[across].max() > 10.0
    # the rig solve of the same views, k3 k4 held: the file and report say fisheye and what was held
    rig_out = run_json("calibrate", "run", "--images", tmp_path / "views", "--board", tmp_path / "board.toml",
                       "-o", tmp_path / "calib.json", "--fisheye", "gopro", "--k3", "hold")
    assert rig_out["per_camera"]["gopro"]["model"] == "fisheye" and rig_out["per_camera"]["gopro"]["dist"][2:] == [0.0, 0.0]
    assert abs(rig_out["per_camera"]["gopro"]["K"][0][0] / cam.fx - 1) < 0.005
    from calibration.report import format_report

    assert "held at 0 (not fitted): k3 k4 (every camera)" in format_report(RigCalibration.load(tmp_path / "calib.json"))
    # the intrinsics file's lens, held in a rig solve, stays fisheye
    held = run_json("calibrate", "run", "--images", tmp_path / "views", "--board", tmp_path / "board.toml",
                    "-o", tmp_path / "held.json", "--intrinsics", tmp_path / "fisheye.json")
    assert held["per_camera"]["gopro"]["model"] == "fisheye" and held["per_camera"]["gopro"]["dist"] == pytest.approx(fe["dist"], abs=1e-6)


def test_a_fisheye_calibration_file_round_trips_and_bad_ones_say_why(tmp_path):
    rig = _pair_rig()
    rig.save(tmp_path / "calib.json")
    doc = json.loads((tmp_path / "calib.json").read_text())
    assert doc["cameras"][0]["model"] == "fisheye" and "model" not in doc["cameras"][1]  # pinhole files are as before
    back = RigCalibration.load(tmp_path / "calib.json")
    assert back["left"].model == "fisheye" and np.array_equal(back["left"].dist, rig["left"].dist)
    bad = dict(doc["cameras"][0], model="omni")
    with pytest.raises(CalibrationError, match="unknown lens model 'omni'"):
        CameraModel.from_dict(bad)
    with pytest.raises(CalibrationError, match="a fisheye lens has 4 distortion terms"):
        CameraModel.from_dict(dict(doc["cameras"][0], dist=[0.1, 0.0, 0.0, 0.0, 0.2]))


def test_exports_name_the_fisheye_model(tmp_path):
    rig = _pair_rig()
    images = {c.name: np.zeros((c.height, c.width, 3), np.uint8) for c in rig.cameras}
    export(rig, "colmap", tmp_path / "colmap")
    lines = [line.split() for line in (tmp_path / "colmap" / "cameras.txt").read_text().splitlines() if not line.startswith("#")]
    assert [row[1] for row in lines] == ["OPENCV_FISHEYE", "FULL_OPENCV", "OPENCV_FISHEYE"]
    assert len(lines[0]) == 4 + 8 and float(lines[0][8]) == rig["left"].dist[0]
    with pytest.raises(CalibrationError, match="mixes pinhole and fisheye"):
        export(rig, "nerfstudio", tmp_path / "ns", images)
    pair = RigCalibration([rig["left"], rig["right"]])
    export(pair, "nerfstudio", tmp_path / "ns", {n: images[n] for n in ("left", "right")})
    ns = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    assert ns["camera_model"] == "OPENCV_FISHEYE" and ns["frames"][0]["k4"] == rig["left"].dist[3] and "p1" not in ns["frames"][0]
    with pytest.raises(CalibrationError, match="EasyMocap reads only OpenCV's pinhole"):
        export(rig, "easymocap", tmp_path / "em")
    export(pair, "opencv", tmp_path / "cv")
    fs = cv2.FileStorage(str(tmp_path / "cv" / "intrinsics.yml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("lens1").string() == "fisheye" and fs.getNode("D1").mat().size == 4
    maps = rectification_maps(pair["left"], pair["right"])
    mx, my = cv2.fisheye.initUndistortRectifyMap(pair["left"].K, pair["left"].dist, maps["R1"], maps["P1"], (960, 540), cv2.CV_32FC1)
    assert np.array_equal(mx, maps["left_map_x"]) and np.array_equal(my, maps["left_map_y"])


def test_the_model_input_of_a_fisheye_camera_is_its_undistorted_image():
    """The live and training paths resample a fisheye frame onto the pinhole image as OpenCV's
    fisheye undistortion does."""
    from inference.runtime.preprocess import Resampler, pinhole

    cam = wide()
    rng = np.random.default_rng(0)
    frame = cv2.resize(rng.integers(0, 256, (54, 96, 3), dtype=np.uint8), (960, 540), interpolation=cv2.INTER_CUBIC)
    ours = Resampler(cam, (960, 540)).image(frame)
    target = pinhole(cam, (960, 540))
    ref = cv2.fisheye.undistortImage(frame, cam.K, cam.dist, Knew=target.K).astype(np.float32) / 255.0
    inner = (slice(40, -40), slice(60, -60))  # OpenCV leaves black where the lens has no pixel; ours repeats the border
    assert np.abs(ours[inner] - ref[inner]).mean() < 2 / 255 and np.abs(ours[inner] - ref[inner]).max() < 0.1
