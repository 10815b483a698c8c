"""The training-time point splatter (stage 1's renders into supervision cameras) against its
straightforward reference, and against the simulator's own renders."""
from __future__ import annotations

import math

import pytest
import torch

from inference.model.geometry import transform_points, unproject_depth
from inference.train.point_splat import PointSplatConfig, point_splat_reference, splat_points
from simulator.render import render
from simulator.rig import virtual_rig
from simulator.scene import Scene

W, H = 24, 16


def random_scene(seed: int, b: int = 2, n: int = 80, dtype=torch.float64):
    """Points 2-4 m in front of a small camera, most of them landing in its image, some outside
    and some behind it; random colours, opacities and a small random target pose."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[18.0, 0.0, 11.7], [0.0, 17.5, 7.4], [0.0, 0.0, 1.0]], dtype=dtype).expand(b, 3, 3).clone()
    z = 2.0 + 2.0 * torch.rand(b, 1, n, generator=g, dtype=dtype)
    u = -3.0 + (W + 6.0) * torch.rand(b, 1, n, generator=g, dtype=dtype)
    v = -3.0 + (H + 6.0) * torch.rand(b, 1, n, generator=g, dtype=dtype)
    pts = torch.cat([(u - 11.7) / 18.0 * z, (v - 7.4) / 17.5 * z, z], 1)
    pts[:, 2, :3] = -1.0  # behind the camera
    cols = torch.rand(b, 3, n, generator=g, dtype=dtype)
    op = 0.3 + 0.7 * torch.rand(b, 1, n, generator=g, dtype=dtype)
    a = 0.05 * torch.randn(b, 3, generator=g, dtype=dtype)  # a small rotation vector
    skew = torch.zeros(b, 3, 3, dtype=dtype)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
    skew = skew - skew.transpose(1, 2)
    T = torch.eye(4, dtype=dtype).repeat(b, 1, 1)
    T[:, :3, :3] = torch.linalg.matrix_exp(skew)
    T[:, :3, 3] = 0.1 * torch.randn(b, 3, generator=g, dtype=dtype)
    return pts, cols, op, T, K


@pytest.mark.parametrize("cfg", [PointSplatConfig(), PointSplatConfig(radius=2, background=(0.2, 0.5, 0.9)), PointSplatConfig(footprint=1.0, max_alpha=0.9)])
def test_fast_splatter_equals_reference_in_values_and_gradients(cfg):
    for seed in range(3):
        pts, cols, op, T, K = random_scene(seed)
        leaves = [x.clone().requires_grad_(True) for x in (pts, cols, op)]
        refs = [x.clone().requires_grad_(True) for x in (pts, cols, op)]
        fast = splat_points(*leaves, T, K, (W, H), cfg)
        ref = point_splat_reference(*refs, T, K, (W, H), cfg)
        assert ref.alpha.max() > 0.8 and (ref.alpha > 0).float().mean() > 0.25, "the points cover much of the image"
        for name in ("image", "depth", "alpha"):
            torch.testing.assert_close(getattr(fast, name), getattr(ref, name), rtol=1e-9, atol=1e-9)
        # one random linear functional of all outputs, so every output's gradient is compared
        g = torch.Generator().manual_seed(100 + seed)
        probe = [torch.randn(getattr(ref, k).shape, generator=g, dtype=torch.float64) for k in ("image", "depth", "alpha")]
        sum((getattr(fast, k) * p).sum() for k, p in zip(("image", "depth", "alpha"), probe)).backward()
        sum((getattr(ref, k) * p).sum() for k, p in zip(("image", "depth", "alpha"), probe)).backward()
        for a, b in zip(leaves, refs):
            assert b.grad.abs().max() > 0
            torch.testing.assert_close(a.grad, b.grad, rtol=1e-8, atol=1e-9)


def test_float32_agrees_with_the_double_reference():
    pts, cols, op, T, K = random_scene(7, dtype=torch.float32)
    fast = splat_points(pts, cols, op, T, K, (W, H))
    ref = point_splat_reference(pts, cols, op, T, K, (W, H))
    torch.testing.assert_close(fast.image, ref.image, rtol=1e-4, atol=1e-4)


def test_compositing_is_front_to_back():
    """Two opaque points on one pixel: the nearer one's colour, whichever comes first in the input."""
    K = torch.tensor([[[10.0, 0.0, 2.0], [0.0, 10.0, 2.0], [0.0, 0.0, 1.0]]])
    for order in ((2.0, 3.0), (3.0, 2.0)):
        pts = torch.tensor([[[0.0, 0.0], [0.0, 0.0], list(order)]])
        cols = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]])
        out = splat_points(pts, cols, None, torch.eye(4)[None], K, (5, 5), PointSplatConfig(max_alpha=0.99))
        near = 0 if order[0] < order[1] else 1
        expect = torch.zeros(3)
        expect[near] = 0.99
        expect[1 - near] = 0.01 * 0.99
        torch.testing.assert_close(out.image[0, :, 2, 2], expect)
        assert out.depth[0, 0, 2, 2].item() == pytest.approx((0.99 * 2.0 + 0.0099 * 3.0) / 0.9999)


# ---- against the simulator ---------------------------------------------------------------------

SW, SH = 128, 72


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    d = (a - b) ** 2
    if mask is not None:
        d = d[..., mask]
    return 10.0 * math.log10(1.0 / d.mean().item())


@pytest.fixture(scope="module")
def sim():
    scene = Scene(seed=3, people=3)
    rig = virtual_rig(6, SW, SH, distortion=False)  # the splatter's cameras are pinholes
    views = {c.name: render(scene, c, 1.0) for c in rig.cameras}
    return rig, views


def _pose(cam) -> torch.Tensor:
    m = torch.eye(4)
    m[:3, :3] = torch.tensor(cam.R, dtype=torch.float32)
    m[:3, 3] = torch.tensor(cam.t, dtype=torch.float32)
    return m[None]


def _image(view) -> torch.Tensor:
    return torch.tensor(view.rgb).permute(2, 0, 1)[None].float() / 255.0


def _points(cam, view) -> torch.Tensor:
    """The view's depth map as points in its own camera frame."""
    return unproject_depth(torch.tensor(view.depth)[None, None], torch.tensor(cam.K, dtype=torch.float32)[None])


def test_a_depth_map_splatted_into_its_own_camera_gives_back_its_image(sim):
    rig, views = sim
    cam, view = rig["left"], views["left"]
    out = splat_points(_points(cam, view), _image(view), None, torch.eye(4)[None], torch.tensor(cam.K, dtype=torch.float32)[None], (SW, SH))
    assert psnr(out.image, _image(view)) > 30.0  # measured 35.0 dB (the kernel's rim blurs a little)
    assert out.alpha.min() > 0.98
    rel = (out.depth[0, 0] - torch.tensor(view.depth)).abs() / torch.tensor(view.depth)
    # within 2 % but at silhouettes, where the expected depth blends both sides of the edge
    # (measured: 93.9 % of the pixels; at this small size many pixels lie on an edge)
    assert (rel < 0.02).float().mean() > 0.9 and rel.median() < 0.005  # measured 0.34 %


def test_both_sources_splatted_into_a_supervision_camera_look_like_its_render(sim):
    rig, views = sim
    left, right = rig["left"], rig["right"]
    right_to_left = _pose(left) @ torch.linalg.inv(_pose(right))
    pts = torch.cat([_points(left, views["left"]).reshape(1, 3, -1),
                     transform_points(right_to_left, _points(right, views["right"])).reshape(1, 3, -1)], 2)
    cols = torch.cat([_image(views["left"]).reshape(1, 3, -1), _image(views["right"]).reshape(1, 3, -1)], 2)
    for name in ("sup1", "sup2", "sup4"):
        cam = rig[name]
        truth = _image(views[name])
        out = splat_points(pts, cols, None, _pose(cam) @ torch.linalg.inv(_pose(left)), torch.tensor(cam.K, dtype=torch.float32)[None], (SW, SH))
        covered = out.alpha[0, 0] > 0.5
        depth_truth = torch.tensor(views[name].depth)
        rel = ((out.depth[0, 0] - depth_truth).abs() / depth_truth)[covered]
        # what the two sources see covers most of the view (the rest: disocclusions behind people)
        assert covered.float().mean() > 0.8
        # measured 26.7 / 25.3 / 26.0 dB on covered pixels (16-18 dB full image, holes black)
        assert psnr(out.image, truth, covered) > 23.0
        # a control: the nearer source image itself, unwarped, is far worse on the same pixels
        # (measured 20.0 / 18.5 / 20.4 dB)
        nearer = views["left"] if name in ("sup1", "sup2") else views["right"]
        assert psnr(_image(nearer), truth, covered) < psnr(out.image, truth, covered) - 4.0
        assert rel.median() < 0.01
