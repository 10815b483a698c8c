"""Camera geometry in torch agrees with calibration.camera (the numpy reference) and exports."""
from __future__ import annotations

import numpy as np
import torch

from calibration.camera import CameraModel, intrinsics_from_fov, look_at
from inference.model.geometry import (
    inverse_3x3,
    invert_pose,
    pixel_rays,
    project,
    relative_pose,
    resize_intrinsics,
    transform_points,
    unproject_depth,
    warp_from_source,
)


def camera(name="cam", eye=(1.0, 1.5, -3.0), size=(64, 48)) -> CameraModel:
    R, t = look_at(eye, (0.0, 1.0, 0.0))
    return CameraModel(name, size[0], size[1], intrinsics_from_fov(size[0], size[1], 60.0), np.zeros(5), R, t)


def tensor(a) -> torch.Tensor:
    return torch.tensor(np.asarray(a), dtype=torch.float64)[None]


def test_closed_form_inverse_matches_numpy():
    rng = np.random.default_rng(1)
    m = rng.normal(size=(5, 3, 3)) + 3 * np.eye(3)
    inv = inverse_3x3(torch.tensor(m)).numpy()
    np.testing.assert_allclose(inv, np.linalg.inv(m), rtol=1e-10, atol=1e-12)


def test_rigid_inverse_and_relative_pose():
    a, b = camera("a"), camera("b", eye=(-2.0, 1.2, -2.5))
    pa, pb = tensor(a.extrinsic), tensor(b.extrinsic)
    np.testing.assert_allclose((invert_pose(pa) @ pa)[0].numpy(), np.eye(4), atol=1e-12)
    x_world = np.array([0.3, 1.1, 0.2])
    x_a = a.world_to_camera(x_world)
    x_b = transform_points(relative_pose(pb, pa), torch.tensor(x_a)[None, :, None])[0, :, 0].numpy()
    np.testing.assert_allclose(x_b, b.world_to_camera(x_world), atol=1e-12)


def test_projection_and_unprojection_match_the_camera_model():
    cam = camera()
    K = tensor(cam.K)
    depth = torch.full((1, 1, cam.height, cam.width), 2.5, dtype=torch.float64)
    pts = unproject_depth(depth, K)  # camera frame
    np.testing.assert_allclose(pts[0].permute(1, 2, 0).numpy(), cam.pixel_rays() * 2.5, atol=1e-12)
    uv, z = project(pts, K)
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    np.testing.assert_allclose(uv[0, 0].numpy(), u, atol=1e-9)
    np.testing.assert_allclose(uv[0, 1].numpy(), v, atol=1e-9)
    np.testing.assert_allclose(z[0, 0].numpy(), 2.5)


def test_resized_intrinsics_follow_the_pixel_centre_convention():
    cam = camera(size=(640, 360))
    small = cam.scaled(256, 144)
    K = resize_intrinsics(tensor(cam.K), (640, 360), (256, 144))
    np.testing.assert_allclose(K[0].numpy(), small.K, atol=1e-12)
    np.testing.assert_allclose(pixel_rays(K, 256, 144)[0].permute(1, 2, 0).numpy(), small.pixel_rays(), atol=1e-12)


def test_resizing_intrinsics_makes_no_tensor_from_host_values():
    """On a GPU a tensor built from Python numbers is a blocking host copy on every frame, and a
    CUDA graph cannot capture one: the per-frame geometry computes from K alone."""
    from torch.overrides import TorchFunctionMode

    made = []

    class Factories(TorchFunctionMode):
        def __torch_function__(self, func, types, args=(), kwargs=None):
            if func in (torch.tensor, torch.as_tensor, torch.zeros, torch.ones, torch.full, torch.eye, torch.arange):
                made.append(func.__name__)
            return func(*args, **(kwargs or {}))

    K = tensor(camera(size=(640, 360)).K)
    with Factories():
        resize_intrinsics(K, (640, 360), (256, 144))
    assert made == []


def test_warping_a_source_with_true_depth_reproduces_the_target():
    """A fronto-parallel textured plane seen by two cameras: warping the source image with the
    target's depth gives the target image (nearly exactly, away from the borders)."""
    src, tgt = camera("src", eye=(0.4, 1.0, -3.0)), camera("tgt", eye=(0.0, 1.0, -3.0))
    # The plane z = 0 (world); its texture a smooth function of world x, y.
    def texture(x, y):
        return np.stack([0.5 + 0.4 * np.sin(3 * x), 0.5 + 0.4 * np.cos(2 * y), 0.5 + 0.3 * np.sin(x + y)], -1)

    def image_and_depth(cam):
        rays = cam.pixel_rays()  # camera frame
        d_world = rays @ cam.R  # R^T r
        c = cam.center
        s = -c[2] / d_world[..., 2]
        hit = c + d_world * s[..., None]
        return texture(hit[..., 0], hit[..., 1]), (rays * s[..., None])[..., 2]

    src_img, _ = image_and_depth(src)
    tgt_img, tgt_depth = image_and_depth(tgt)
    pts = unproject_depth(torch.tensor(tgt_depth)[None, None], tensor(tgt.K))
    warped, visible = warp_from_source(
        torch.tensor(src_img).permute(2, 0, 1)[None], tensor(src.K), relative_pose(tensor(src.extrinsic), tensor(tgt.extrinsic)), pts
    )
    err = np.abs(warped[0].permute(1, 2, 0).numpy() - tgt_img)[4:-4, 4:-4]
    assert visible[0, 0, 4:-4, 4:-4].all()
    assert err.max() < 5e-3  # measured 1.5e-3 (bilinear sampling of a smooth texture)
