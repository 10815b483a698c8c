"""Exports: each file read back the way its tool reads it and checked against our camera model."""
from __future__ import annotations

import json
import tomllib

import cv2
import numpy as np
import pytest

from calibration.camera import CalibrationError
from calibration.export import export
from calibration.synthetic import arc_rig

POINTS = np.array([[0.1, 1.2, 0.2], [-0.4, 0.9, -0.3], [0.5, 1.6, 0.4], [0.0, 1.1, 0.0]])
# Numbers are written in full precision: what is read back equals what was written up to round-off
# (measured at most 1e-15), and projections through another tool's model agree to 6e-13 px.
EXACT = {"rtol": 0, "atol": 1e-12}
PROJECTED_PX = 1e-9


@pytest.fixture(scope="module")
def rig():
    r = arc_rig(6)  # world frame at the scene centre, so the test points lie in front of every camera
    r.meta["stereo_pair"] = {"left": "left", "right": "right"}
    r.meta["rms_px"] = {c: 0.2 for c in r.names}
    return r


def _read(fs, key):
    return fs.getNode(key).mat()


def test_opencv_yaml_and_rectification_maps(rig, tmp_path):
    files = export(rig, "opencv", tmp_path)
    assert sorted(f.name for f in files) == ["extrinsics.yml", "intrinsics.yml", "rectification_maps.npz"]
    left, right = rig["left"], rig["right"]
    fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_READ)
    assert np.allclose(_read(fs, "M1"), left.K, **EXACT) and np.allclose(_read(fs, "M2"), right.K, **EXACT)
    assert np.allclose(_read(fs, "D1").ravel(), left.dist, **EXACT) and np.allclose(_read(fs, "D2").ravel(), right.dist, **EXACT)
    fs = cv2.FileStorage(str(tmp_path / "extrinsics.yml"), cv2.FILE_STORAGE_READ)
    R, T = _read(fs, "R"), _read(fs, "T").ravel()
    # OpenCV's stereo convention: X_right = R X_left + T.
    X = POINTS
    assert np.allclose(left.world_to_camera(X) @ R.T + T, right.world_to_camera(X), **EXACT)
    R1, R2, P1, P2, Q = (_read(fs, k) for k in ("R1", "R2", "P1", "P2", "Q"))
    assert Q.shape == (4, 4)
    # Rectified, a world point has the same row in both images.
    uvl, _ = left.project(X)
    uvr, _ = right.project(X)
    rl = cv2.undistortPoints(uvl.reshape(-1, 1, 2), left.K, left.dist, R=R1, P=P1, criteria=(3, 100, 1e-12)).reshape(-1, 2)
    rr = cv2.undistortPoints(uvr.reshape(-1, 1, 2), right.K, right.dist, R=R2, P=P2, criteria=(3, 100, 1e-12)).reshape(-1, 2)
    assert np.allclose(rl[:, 1], rr[:, 1], rtol=0, atol=PROJECTED_PX)  # measured 3e-12 px
    # The maps send each rectified pixel back to its source pixel.
    maps = np.load(tmp_path / "rectification_maps.npz")
    assert maps["left_map_x"].shape == (left.height, left.width)
    checked = 0
    for (u, v), src in zip(rl, uvl):
        if 0 <= u < left.width - 1 and 0 <= v < left.height - 1:
            checked += 1
            x = cv2.getRectSubPix(maps["left_map_x"], (1, 1), (float(u), float(v)))[0, 0]
            y = cv2.getRectSubPix(maps["left_map_y"], (1, 1), (float(u), float(v)))[0, 0]
            assert np.hypot(x - src[0], y - src[1]) < 5e-4  # float32 maps: measured 7e-5 px
    assert checked >= 2


def test_easymocap_yaml(rig, tmp_path):
    export(rig, "easymocap", tmp_path)
    fi = cv2.FileStorage(str(tmp_path / "intri.yml"), cv2.FILE_STORAGE_READ)
    fe = cv2.FileStorage(str(tmp_path / "extri.yml"), cv2.FILE_STORAGE_READ)
    node = fi.getNode("names")
    names = [node.at(i).string() for i in range(node.size())]
    assert names == rig.names
    for cam in rig.cameras:
        # EasyMocap's read_camera: H = int(fs.getNode("H_<cam>").real()), likewise W: plain integers.
        for key, size in ((f"H_{cam.name}", cam.height), (f"W_{cam.name}", cam.width)):
            assert fi.getNode(key).isInt() and int(fi.getNode(key).real()) == size
        assert np.allclose(_read(fi, f"K_{cam.name}"), cam.K, **EXACT)
        assert _read(fi, f"dist_{cam.name}").shape == (1, 5)
        assert np.allclose(_read(fe, f"Rot_{cam.name}"), cam.R, **EXACT)
        assert np.allclose(cv2.Rodrigues(_read(fe, f"R_{cam.name}"))[0], cam.R, **EXACT)
        assert np.allclose(_read(fe, f"T_{cam.name}").ravel(), cam.t, **EXACT)


def test_anipose_toml_projects_like_our_model(rig, tmp_path):
    export(rig, "anipose", tmp_path)
    data = tomllib.loads((tmp_path / "calibration.toml").read_text())
    assert data["metadata"]["error"] == pytest.approx(0.2)
    for i, cam in enumerate(rig.cameras):
        c = data[f"cam_{i}"]
        assert c["name"] == cam.name and c["size"] == [cam.width, cam.height]
        uv, _ = cv2.projectPoints(POINTS, np.array(c["rotation"]), np.array(c["translation"]), np.array(c["matrix"]), np.array(c["distortions"]))
        assert np.allclose(uv.reshape(-1, 2), cam.project(POINTS)[0], rtol=0, atol=PROJECTED_PX)


def _gray_images(rig):
    return {c.name: np.full((c.height, c.width), 40 + 30 * i, np.uint8) for i, c in enumerate(rig.cameras)}


def test_nerfstudio_transforms_use_opengl_axes_and_pixel_corner_origin(rig, tmp_path):
    export(rig, "nerfstudio", tmp_path, images=_gray_images(rig))
    data = json.loads((tmp_path / "transforms.json").read_text())
    assert len(data["frames"]) == len(rig.cameras)
    for frame, cam in zip(data["frames"], rig.cameras):
        c2w = np.array(frame["transform_matrix"])
        w2c = np.linalg.inv(c2w)
        p = POINTS @ w2c[:3, :3].T + w2c[:3, 3]
        # OpenGL camera: looking down -z, y up; nerfstudio pixels have their centres at +0.5.
        u = frame["fl_x"] * p[:, 0] / -p[:, 2] + frame["cx"] - 0.5
        v = frame["fl_y"] * -p[:, 1] / -p[:, 2] + frame["cy"] - 0.5
        pinhole = cam.with_pose(cam.R, cam.t)
        pinhole.dist = np.zeros(5)
        assert np.allclose(np.stack([u, v], 1), pinhole.project(POINTS)[0], rtol=0, atol=PROJECTED_PX)
        assert frame["k1"] == pytest.approx(cam.dist[0]) and frame["w"] == cam.width


def test_colmap_text_model(rig, tmp_path):
    export(rig, "colmap", tmp_path)
    cams = [l.split() for l in (tmp_path / "cameras.txt").read_text().splitlines() if l and not l.startswith("#")]
    lines = [l for l in (tmp_path / "images.txt").read_text().splitlines() if not l.startswith("#")]
    images = [l.split() for l in lines[0::2]]
    assert lines[1::2] == [""] * len(rig.cameras)  # no 2D points
    assert (tmp_path / "points3D.txt").exists()
    for cline, iline, cam in zip(cams, images, rig.cameras):
        assert cline[1] == "FULL_OPENCV" and int(cline[2]) == cam.width
        fx, fy, cx, cy = map(float, cline[4:8])
        assert (fx, fy) == pytest.approx((cam.fx, cam.fy), rel=1e-15) and (cx, cy) == pytest.approx((cam.cx + 0.5, cam.cy + 0.5), rel=1e-15)
        qw, qx, qy, qz, tx, ty, tz = map(float, iline[1:8])
        R = np.array([
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
            [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
            [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
        ])
        assert np.allclose(R, cam.R, **EXACT) and np.allclose([tx, ty, tz], cam.t, **EXACT)
        assert iline[9] == f"{cam.name}.png"


def test_unknown_format_is_an_error(rig, tmp_path):
    with pytest.raises(CalibrationError, match="unknown export format"):
        export(rig, "blender", tmp_path)


def test_nerfstudio_writes_the_images_it_points_at(rig, tmp_path):
    images = _gray_images(rig)
    files = export(rig, "nerfstudio", tmp_path, images=images)
    data = json.loads((tmp_path / "transforms.json").read_text())
    for frame, cam in zip(data["frames"], rig.cameras):
        img = cv2.imread(str(tmp_path / frame["file_path"]), cv2.IMREAD_UNCHANGED)
        assert img is not None and (img.shape[1], img.shape[0]) == (frame["w"], frame["h"]) == (cam.width, cam.height)
        assert np.array_equal(img, images[cam.name]) and tmp_path / frame["file_path"] in files


def test_nerfstudio_without_images_or_at_another_size_is_refused(rig, tmp_path):
    with pytest.raises(CalibrationError, match="needs one image per camera"):
        export(rig, "nerfstudio", tmp_path)
    small = {c.name: np.zeros((10, 10), np.uint8) for c in rig.cameras}
    with pytest.raises(CalibrationError, match="10x10 but it was calibrated at 1280x720"):
        export(rig, "nerfstudio", tmp_path, images=small)
    assert not (tmp_path / "transforms.json").exists() and not (tmp_path / "images").exists()
