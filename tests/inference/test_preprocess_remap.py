"""The runtime's preprocessing through cv2.remap against the straightforward numpy computation it
replaced (bilinear in float64 coordinates after an integer box prefilter), on distorted simulator
cameras: the same images within the remap's fixed-point precision, the same anti-aliasing when
shrinking, and bit-identical nearest sampling of depth."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.camera import CameraModel
from inference.errors import InferenceError
from inference.runtime.preprocess import Resampler, source_coordinates


def reference_image(camera: CameraModel, size: tuple[int, int], image: np.ndarray) -> np.ndarray:
    """The previous implementation: box shrink by floor(min(W/w, H/h)) in float, then bilinear
    interpolation in float64 coordinates, clamped at the border."""
    img = image.astype(np.float32)
    if image.dtype == np.uint8:
        img *= 1.0 / 255.0
    w, h = size
    src_u, src_v = source_coordinates(camera, size)
    f = max(1, int(min(camera.width / w, camera.height / h)))
    if f > 1:
        hh, ww = img.shape[0] // f * f, img.shape[1] // f * f
        img = img[:hh, :ww].reshape(hh // f, f, ww // f, f, 3).mean(axis=(1, 3))
        src_u = (src_u + 0.5) / f - 0.5
        src_v = (src_v + 0.5) / f - 0.5
    sh, sw = img.shape[:2]
    su = np.clip(src_u, 0, sw - 1)
    sv = np.clip(src_v, 0, sh - 1)
    x0 = np.minimum(np.floor(su).astype(np.int64), sw - 2)
    y0 = np.minimum(np.floor(sv).astype(np.int64), sh - 2)
    fx = (su - x0)[..., None]
    fy = (sv - y0)[..., None]
    x1, y1 = np.minimum(x0 + 1, sw - 1), np.minimum(y0 + 1, sh - 1)
    out = (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x1] * fx * (1 - fy)
           + img[y1, x0] * (1 - fx) * fy + img[y1, x1] * fx * fy)
    return out.astype(np.float32)


def reference_depth(camera: CameraModel, size: tuple[int, int], depth: np.ndarray) -> np.ndarray:
    src_u, src_v = source_coordinates(camera, size)
    iv = np.clip(np.rint(src_v), 0, camera.height - 1).astype(np.int64)
    iu = np.clip(np.rint(src_u), 0, camera.width - 1).astype(np.int64)
    return depth[iv, iu]


# 640x360 sources: (256, 144) shrinks 2.5x (box prefilter 2), (512, 288) 1.25x (none), (640, 360)
# only undistorts, (1280, 720) enlarges.
SIZES = [(256, 144), (512, 288), (640, 360), (1280, 720)]


@pytest.mark.parametrize("size", SIZES)
def test_remap_matches_the_numpy_bilinear_result_on_a_simulator_frame(sim_frames, size):
    for name in ("left", "right"):
        cam = sim_frames.rig[name]
        assert cam.has_distortion
        frame = sim_frames.rgb[name]
        assert frame.dtype == np.uint8
        r = Resampler(cam, size)
        for image in (frame, frame.astype(np.float32) / 255.0):
            got = r.image(image)
            want = reference_image(cam, size, image)
            assert got.shape == (size[1], size[0], 3) and got.dtype == np.float32
            diff = np.abs(got - want)
            # bilinear weights at 1/32 pixel (OpenCV's remap), and for uint8 frames two roundings to 1/255
            assert diff.max() < 4 / 255, (name, size, image.dtype, float(diff.max()))
            assert diff.mean() < 2e-3, (name, size, image.dtype, float(diff.mean()))


@pytest.mark.parametrize("size", SIZES)
def test_depth_is_the_nearest_source_pixel_exactly(sim_frames, size):
    cam = sim_frames.rig["left"]
    depth = sim_frames.depth["left"].astype(np.float32)
    got = Resampler(cam, size).depth(depth)
    assert got.shape == (size[1], size[0]) and got.dtype == np.float32
    np.testing.assert_array_equal(got, reference_depth(cam, size, depth))
    assert np.isin(got, depth).all()  # never a blend of two source pixels


def test_shrinking_keeps_the_box_prefilter_against_aliasing(sim_frames):
    """A one-pixel checkerboard shrunk 2.5x is uniform grey (a plain bilinear resample would alias
    it into a pattern of black and white)."""
    cam = sim_frames.rig["left"]
    v, u = np.mgrid[: cam.height, : cam.width]
    board = np.where((u + v) % 2 == 0, 255, 0).astype(np.uint8)
    frame = np.repeat(board[..., None], 3, axis=2)
    r = Resampler(cam, (256, 144))
    assert r.prefilter == 2
    out = r.image(frame)
    assert np.abs(out - 0.5).max() < 2 / 255


def test_an_undistorted_camera_at_its_own_size_is_passed_through():
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 89.5], [0, 0, 1]])
    cam = CameraModel("c", 320, 180, K)
    frame = np.random.default_rng(0).integers(0, 256, (180, 320, 3), dtype=np.uint8)
    np.testing.assert_allclose(Resampler(cam, (320, 180)).image(frame), frame / 255.0, atol=1e-7)


def test_frames_of_the_wrong_size_or_shape_are_refused(sim_frames):
    cam = sim_frames.rig["left"]
    r = Resampler(cam, (256, 144))
    with pytest.raises(InferenceError, match="calibration is for 640x360"):
        r.image(np.zeros((360, 641, 3), np.uint8))
    with pytest.raises(InferenceError, match="H x W x 3"):
        r.image(np.zeros((360, 640), np.uint8))
    with pytest.raises(InferenceError, match="H x W"):
        r.depth(np.zeros((360, 640, 1), np.float32))
