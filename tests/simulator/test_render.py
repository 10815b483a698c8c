"""The renderer's ground truth is exact: depth agrees across cameras, board corners land where OpenCV
projects them and where OpenCV's detectors find them, and the same seed and time give the same image."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.boards import CharucoSpec
from calibration.camera import CameraModel
from simulator.errors import SimulatorError
from simulator.rays import camera_rays
from simulator.render import render
from simulator.rig import virtual_rig
from simulator.scene import Scene, default_board


def _bilinear(img: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear weights and the four integer neighbours of each point."""
    u0 = np.floor(uv[:, 0]).astype(int)
    v0 = np.floor(uv[:, 1]).astype(int)
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    w = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=1)
    us = np.stack([u0, u0 + 1, u0, u0 + 1], axis=1)
    vs = np.stack([v0, v0, v0 + 1, v0 + 1], axis=1)
    return w, us, vs


def test_depth_agrees_across_cameras_on_shared_unoccluded_surfaces(people_scene, small_rig):
    """Back-project one camera's depth, project into another: the other camera's depth agrees within
    1% wherever both see the same surface (same primitive, facing both cameras)."""
    checked = 0
    worst = 0.0
    for t in (0.7, 2.1):
        renders = {c.name: render(people_scene, c, t, normals=True) for c in small_rig.cameras[::2]}
        for a in small_rig.cameras[::2]:
            ra = renders[a.name]
            vv, uu = np.mgrid[1:a.height - 1:3, 1:a.width - 1:3]
            uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
            z = ra.depth[vv.ravel(), uu.ravel()].astype(np.float64)
            ida = ra.ids[vv.ravel(), uu.ravel()]
            keep = z > 0
            # independent back-projection: CameraModel's own undistortion, not the renderer's rays
            xy = a.undistort_normalized(uv[keep])
            pc = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) * z[keep, None]
            X = (pc - a.t) @ a.R  # camera -> world
            n_world = ra.normals[vv.ravel(), uu.ravel()][keep] @ a.R
            ida = ida[keep]
            for b in small_rig.cameras[::2]:
                if b.name == a.name:
                    continue
                rb = renders[b.name]
                uvb, zexp = b.project(X)
                inside = (uvb[:, 0] >= 0) & (uvb[:, 0] < b.width - 1) & (uvb[:, 1] >= 0) & (uvb[:, 1] < b.height - 1) & (zexp > 0)
                view = b.center - X
                facing = np.einsum("ij,ij->i", n_world, view) > 0.25 * np.linalg.norm(view, axis=1)
                sel = np.flatnonzero(inside & facing)
                w, us, vs = _bilinear(rb.depth, uvb[sel])
                same = np.all(rb.ids[vs, us] == ida[sel, None], axis=1)
                sel, w, us, vs = sel[same], w[same], us[same], vs[same]
                # 1/z is affine in the image for a plane: interpolate inverse depth
                zb = 1.0 / np.sum(w / rb.depth[vs, us], axis=1)
                rel = np.abs(zb - zexp[sel]) / zexp[sel]
                checked += rel.size
                worst = max(worst, float(rel.max()))
                assert rel.max() < 0.01, f"{a.name}->{b.name} at t={t}: depth disagrees by {rel.max():.2%}"
                people = np.isin(ida[sel], np.flatnonzero([lab.startswith("person") for lab in ra.labels]))
                assert people.sum() > 50, "the check must cover the people, not only the room"
    assert checked > 20000, checked


def test_board_corners_project_like_opencv():
    scene = Scene(seed=0, people=0, board=CharucoSpec(squares_x=7, squares_y=5, square_size=0.08, marker_size=0.06), name="empty")
    for cam in virtual_rig(6, 1280, 720).cameras:
        for t in (1.0, 7.0, 13.0):
            _ids, pts = scene.board_corners(t)
            uv, _ = cam.project(pts)
            rvec, _ = cv2.Rodrigues(cam.R)
            ref, _ = cv2.projectPoints(pts, rvec, cam.t, cam.K, cam.dist)
            assert np.abs(uv - ref.reshape(-1, 2)).max() < 0.05


def test_board_surface_lies_where_opencv_puts_it():
    """Every board pixel's depth is the intersection of OpenCV's undistorted ray with the board plane."""
    scene = Scene(seed=0, people=0, board="charuco", name="empty")
    for t, cam in ((2.0, virtual_rig(6, 960, 540)["left"]), (11.0, virtual_rig(6, 960, 540)["sup3"])):
        r = render(scene, cam, t)
        vv, uu = np.nonzero(r.ids == r.labels.index("board"))
        assert vv.size > 10000
        uv = np.stack([uu, vv], axis=1).astype(np.float64).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
        xy = cv2.undistortPoints(uv, cam.K, cam.dist, criteria=crit).reshape(-1, 2)
        R, tb = scene.board_pose(t)
        n, p = cam.R @ R[:, 2], cam.R @ tb + cam.t  # board plane in the camera frame
        z = (n @ p) / (xy @ n[:2] + n[2])
        assert np.abs(r.depth[vv, uu] - z).max() / z.min() < 1e-5


def _signed(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Detected minus true positions, in the detector's order or reversed (it may start from either end)."""
    if np.linalg.norm(found[::-1] - truth, axis=1).mean() < np.linalg.norm(found - truth, axis=1).mean():
        found = found[::-1]
    return found - truth


@pytest.fixture(scope="module")
def board_views():
    """Rendered views of each board along its path through the volume, as 8-bit grey images."""
    rig = virtual_rig(6, 1280, 720)
    views = {}
    for kind in ("chessboard", "charuco"):
        board = default_board(kind)
        scene = Scene(seed=0, people=0, board=board, name="empty")
        items = []
        # views along the path with the board 10 to 45 degrees off the camera's line of sight
        for t, cam in ((1.0, rig["sup2"]), (5.0, rig["sup3"]), (9.0, rig["left"]), (13.0, rig["sup1"]), (17.0, rig["sup4"]), (1.0, rig["sup4"])):
            R, _ = scene.board_pose(t)
            _ids, pts = scene.board_corners(t)
            sight = cam.center - pts.mean(axis=0)
            assert 5 < np.degrees(np.arccos(-R[:, 2] @ sight / np.linalg.norm(sight))) < 50
            r = render(scene, cam, t)
            uv, _ = cam.project(pts)
            items.append((cv2.cvtColor(r.rgb, cv2.COLOR_RGB2GRAY), uv))
        views[kind] = (board, items)
    return views


SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)


def test_opencv_finds_chessboard_corners_where_the_ground_truth_puts_them(board_views):
    board, items = board_views["chessboard"]
    errs = []
    for gray, uv in items:
        ok, corners = cv2.findChessboardCorners(gray, (board.cols, board.rows), flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        assert ok, "the detector must find the whole board"
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), SUBPIX).reshape(-1, 2)
        errs.append(_signed(corners, uv))
    d = np.concatenate(errs)
    assert np.linalg.norm(d.mean(axis=0)) < 0.02, f"corners are biased by {d.mean(axis=0)} px"
    e = np.linalg.norm(d, axis=1)
    assert np.sqrt(np.mean(e ** 2)) < 0.1 and np.median(e) < 0.1, f"rms {np.sqrt(np.mean(e ** 2)):.3f} px"
    assert np.percentile(e, 95) < 0.15 and e.max() < 0.25, f"p95 {np.percentile(e, 95):.3f} max {e.max():.3f} px"


def test_opencv_finds_charuco_corners_where_the_ground_truth_puts_them(board_views):
    board, items = board_views["charuco"]
    detector = cv2.aruco.CharucoDetector(board.cv_board())
    errs = []
    for gray, uv in items:
        corners, ids, _mc, _mi = detector.detectBoard(gray)
        assert ids is not None and len(ids) >= 0.7 * board.n_corners, "the detector must find most of the board"
        corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (2, 2), (-1, -1), SUBPIX).reshape(-1, 2)
        errs.append(corners - uv[ids.ravel()])
    d = np.concatenate(errs)
    assert np.linalg.norm(d.mean(axis=0)) < 0.02, f"corners are biased by {d.mean(axis=0)} px"
    e = np.linalg.norm(d, axis=1)
    assert np.sqrt(np.mean(e ** 2)) < 0.1 and np.median(e) < 0.1, f"rms {np.sqrt(np.mean(e ** 2)):.3f} px"
    assert np.percentile(e, 95) < 0.2, f"p95 {np.percentile(e, 95):.3f} px"


def test_same_seed_and_time_give_identical_images(small_rig):
    cam = small_rig["sup2"]
    a = render(Scene(seed=11, people=3), cam, 1.5)
    b = render(Scene(seed=11, people=3), cam, 1.5)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth) and np.array_equal(a.mask, b.mask)
    c = render(Scene(seed=12, people=3), cam, 1.5)
    d = render(Scene(seed=11, people=3), cam, 1.6)
    assert not np.array_equal(a.rgb, c.rgb) and not np.array_equal(a.rgb, d.rgb)


def test_outputs_shapes_and_person_mask(people_scene, small_rig):
    cam = small_rig["left"]
    r = render(people_scene, cam, 0.4)
    assert r.rgb.shape == (216, 384, 3) and r.rgb.dtype == np.uint8
    assert r.depth.shape == (216, 384) and r.depth.dtype == np.float32
    assert r.mask.dtype == bool and 0.01 < r.mask.mean() < 0.5
    labels = np.array(r.labels)
    assert all(lab.startswith("person") for lab in labels[np.unique(r.ids[r.mask])])
    assert not any(lab.startswith("person") for lab in labels[np.unique(r.ids[~r.mask & (r.ids >= 0)])])
    assert r.depth[r.mask].max() < r.depth[~r.mask].max(), "people stand in front of the walls"
    assert np.all(r.depth > 0), "the room closes the scene: every pixel hits something"


def test_depth_is_z_along_the_optical_axis_through_the_exact_distorted_pixel(small_rig):
    """Every pixel's ray, at the rendered depth, projects back to that pixel's centre."""
    scene = Scene(seed=0, people=1, name="empty")
    cam = small_rig["right"]
    assert cam.has_distortion
    r = render(scene, cam, 0.0)
    rays = camera_rays(cam)
    pc = np.stack([rays.X * r.depth, rays.Y * r.depth, r.depth], axis=-1).reshape(-1, 3).astype(np.float64)
    uv, z = cam.project((pc - cam.t) @ cam.R)
    vv, uu = np.mgrid[0:cam.height, 0:cam.width]
    assert np.abs(uv - np.stack([uu.ravel(), vv.ravel()], axis=1)).max() < 1e-3
    assert np.allclose(z, r.depth.ravel(), rtol=1e-6)


def test_antialiasing_approaches_a_supersampled_reference(small_rig):
    scene = Scene(seed=2, people=2, name="empty")
    cam = small_rig["sup3"]
    ref = cv2.resize(render(scene, cam.scaled(cam.width * 4, cam.height * 4), 1.0, antialias=1, psf=0).radiance,
                     (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    plain = render(scene, cam, 1.0, antialias=1, psf=0)
    smooth = render(scene, cam, 1.0, antialias=3, psf=0)
    edges = cv2.dilate((np.abs(np.diff(plain.ids.astype(int), axis=1, prepend=0)) > 0).astype(np.uint8), np.ones((3, 3))) > 0
    err_plain = np.abs(plain.radiance - ref)[edges].mean()
    err_smooth = np.abs(smooth.radiance - ref)[edges].mean()
    assert err_smooth < 0.6 * err_plain, (err_plain, err_smooth)


def test_bad_camera_and_time_are_clear_errors(people_scene, small_rig):
    cam = small_rig["left"]
    K = cam.K.copy()
    K[0, 0] = 0.0
    with pytest.raises(SimulatorError, match="focal lengths must be positive"):
        render(people_scene, CameraModel("bad", 64, 48, K), 0.0)
    with pytest.raises(SimulatorError, match="image size must be positive"):
        render(people_scene, CameraModel("empty", 0, 48, cam.K), 0.0)
    with pytest.raises(SimulatorError, match="time must be"):
        render(people_scene, cam, -1.0)
    with pytest.raises(SimulatorError, match="antialias"):
        render(people_scene, cam, 0.0, antialias=0)
    folded = CameraModel("fisheye-ish", 640, 360, cam.scaled(640, 360).K, [-0.9, 0, 0, 0, 0])
    with pytest.raises(SimulatorError, match="distortion cannot be inverted"):
        render(people_scene, folded, 0.0)


def test_cameras_rendering_from_threads_get_the_same_images():
    """sim:// cameras render from their own threads; sharing one scene must not change a pixel."""
    import threading

    rig = virtual_rig(3, 192, 108)
    alone = Scene(seed=5, people=3)
    shared = Scene(seed=5, people=3)
    expected = {(c.name, t): render(alone, c, t).rgb for c in rig.cameras for t in (0.1, 0.2)}
    got = {}

    def camera_thread(cam):
        for t in (0.1, 0.2):
            got[(cam.name, t)] = render(shared, cam, t).rgb

    threads = [threading.Thread(target=camera_thread, args=(c,)) for c in rig.cameras]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert got.keys() == expected.keys()
    assert all(np.array_equal(got[k], expected[k]) for k in expected)
