"""The calibrated plane-sweep backbone: geometry of its point maps (scale-free, on each camera's rays)."""
from __future__ import annotations

import torch

from inference.config import BackboneConfig
from inference.model.geometry import invert_pose, pixel_rays, project, transform_points
from inference.model.stereo_backbone import StereoBackbone

W, H = 128, 64


def rig(baseline: float):
    """Two pinhole cameras 30 degrees apart (each turned 15 degrees towards the other), `baseline` metres apart."""
    K = torch.tensor([[[110.0, 0.0, 63.5], [0.0, 110.0, 31.5], [0.0, 0.0, 1.0]]])
    a = torch.deg2rad(torch.tensor(30.0))
    r2l = torch.eye(4)[None].clone()
    r2l[0, :3, :3] = torch.tensor([[torch.cos(a), 0.0, torch.sin(a)], [0.0, 1.0, 0.0], [-torch.sin(a), 0.0, torch.cos(a)]])
    r2l[0, 0, 3] = baseline
    return K, r2l


def backbone() -> StereoBackbone:
    torch.manual_seed(0)
    return StereoBackbone(BackboneConfig(kind="stereo"), (W, H)).eval()


def images():
    g = torch.Generator().manual_seed(1)
    return torch.rand(1, 3, H, W, generator=g), torch.rand(1, 3, H, W, generator=g)


def test_right_points_lie_on_the_right_cameras_rays_in_the_left_frame():
    net = backbone()
    K, r2l = rig(2.0)
    left, right = images()
    with torch.no_grad():
        pm = net(left, right, K, K, r2l)
    # Points are in baseline units: bring them back to metres, then into the right camera's frame.
    unit = r2l.clone()
    unit[:, :3, 3] /= 2.0
    in_right = transform_points(invert_pose(unit), pm.points_right)
    uv, z = project(in_right, K)
    grid = pixel_rays(torch.eye(3)[None], W, H)[:, :2]  # (u, v) of every pixel
    assert (uv - grid).abs().max() < 1e-3
    assert (z > 0).all()
    uv_l, _ = project(pm.points_left, K)
    assert (uv_l - grid).abs().max() < 1e-3


def test_point_maps_are_scale_free_and_within_the_swept_range():
    net = backbone()
    left, right = images()
    with torch.no_grad():
        K, r2l = rig(0.5)
        a = net(left, right, K, K, r2l)
        K, r2l = rig(4.0)
        b = net(left, right, K, K, r2l)
    torch.testing.assert_close(a.points_left, b.points_left, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(a.points_right, b.points_right, rtol=1e-4, atol=1e-5)
    z = a.points_left[:, 2]
    cfg = net.cfg
    assert z.min() >= cfg.stereo_near * (1 - 1e-4) and z.max() <= cfg.stereo_far * (1 + 1e-4)
    assert a.tokens_left.shape == (1, (H // 16) * (W // 16), net.token_dim)
    assert (a.conf_left >= 1).all()


def test_depth_follows_the_matching_features():
    """Swapping what the right camera sees changes the left depth (it comes from matching)."""
    net = backbone()
    K, r2l = rig(1.0)
    left, right = images()
    with torch.no_grad():
        a = net(left, right, K, K, r2l).points_left
        b = net(left, right.flip(-1), K, K, r2l).points_left
    assert (a - b).abs().max() > 1e-5  # untrained: small but not zero (measured 3e-4); ignoring the right view gives 0
