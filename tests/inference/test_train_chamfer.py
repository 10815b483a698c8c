"""The stage-1 6-D Chamfer regulariser that scales to the coarse size, against brute force."""
from __future__ import annotations

import time

import pytest
import torch

from inference.model.geometry import transform_points, unproject_depth
from inference.train import losses
from inference.train.chamfer import chamfer_6d, chamfer_reference, kd_leaves, nearest_indices
from simulator.render import render
from simulator.rig import virtual_rig
from simulator.scene import Scene


def _sets(seed: int, n: int, m: int, kind: str, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    if kind == "uniform":
        a = torch.rand(2, n, 6, generator=g, dtype=dtype)
        b = torch.rand(2, m, 6, generator=g, dtype=dtype)
    elif kind == "surface":  # two noisy samplings of one coloured surface, as two views' point maps
        def sample(k):
            uv = torch.rand(2, k, 2, generator=g, dtype=dtype) * 3.0
            xyz = torch.stack([uv[..., 0], uv[..., 1], 4.0 + 0.3 * torch.sin(2 * uv[..., 0])], -1)
            rgb = torch.stack([0.5 + 0.4 * torch.sin(5 * uv[..., 0]), 0.5 + 0.4 * torch.cos(3 * uv[..., 1]), 0.3 + 0.0 * uv[..., 0]], -1)
            return torch.cat([xyz, rgb], -1) + 0.01 * torch.randn(2, k, 6, generator=g, dtype=dtype)
        a, b = sample(n), sample(m)
    else:  # far apart: every query's neighbour lies across the gap
        a = torch.rand(2, n, 6, generator=g, dtype=dtype)
        b = torch.rand(2, m, 6, generator=g, dtype=dtype) + torch.tensor([5.0, 0, 0, 0, 0, 0], dtype=dtype)
    return a, b


@pytest.mark.parametrize("kind", ["uniform", "surface", "apart"])
@pytest.mark.parametrize("n,m,leaf", [(5, 7, 32), (300, 257, 8), (1000, 1500, 32)])
def test_equals_brute_force_in_value_and_gradient(kind, n, m, leaf):
    a, b = _sets(n + m, n, m, kind)
    g = torch.Generator().manual_seed(1)
    wa = (torch.rand(2, n, generator=g) > 0.2).double()
    wb = (torch.rand(2, m, generator=g) > 0.3).double()
    for weights in ((None, None), (wa, wb)):
        fa, fb = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
        ra, rb = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
        fast = chamfer_6d(fa, fb, *weights, leaf=leaf)
        ref = chamfer_reference(ra, rb, *weights)
        torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
        fast.backward()
        ref.backward()
        assert rb.grad.abs().sum() > 0
        torch.testing.assert_close(fa.grad, ra.grad, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(fb.grad, rb.grad, rtol=1e-10, atol=1e-12)


def test_nearest_indices_are_the_argmin_of_all_distances():
    a, b = _sets(3, 2000, 1800, "surface", torch.float32)
    idx = nearest_indices(a[0], b[0], leaf=16)
    brute = torch.cdist(a[0].double(), b[0].double()).argmin(1)
    assert torch.equal(idx, brute)


def test_leaves_partition_the_set_spatially():
    x = torch.rand(1000, 6, dtype=torch.float64)
    leaves = kd_leaves(x, 32)
    assert leaves.shape == (32, 32)
    assert set(leaves.reshape(-1).tolist()) == set(range(1000))  # every point, 24 of them twice
    # the leaves' boxes tile the unit cube (volumes sum to less than 1; 32 random groups of 32
    # points would each span most of it)
    boxes = x[leaves].amax(1) - x[leaves].amin(1)
    assert boxes.prod(-1).sum() < 1.0
    shuffled = x[torch.randperm(1024) % 1000].reshape(32, 32, 6)
    assert (shuffled.amax(1) - shuffled.amin(1)).prod(-1).sum() > 5.0


def test_identical_sets_give_zero_with_finite_gradients():
    a, _ = _sets(5, 200, 1, "uniform")
    x = a.clone().requires_grad_(True)
    y = a.clone().requires_grad_(True)
    value = chamfer_6d(x, y)
    value.backward()
    assert value.item() == 0.0
    assert torch.isfinite(x.grad).all() and x.grad.abs().max() == 0


def test_a_set_with_no_valid_point_contributes_nothing():
    a, b = _sets(6, 50, 60, "uniform")
    wb = torch.zeros(2, 60, dtype=torch.float64)
    torch.testing.assert_close(chamfer_6d(a, b, None, wb), chamfer_reference(a, b, None, wb))
    assert torch.isfinite(chamfer_6d(a, b, None, wb))


@pytest.fixture(scope="module")
def coarse_point_maps():
    """Both sources' exact point maps at the preview coarse size (256x144, 36,864 points each), in the
    left camera's frame, with their colours: stage 1's two 6-D point sets once it is trained."""
    scene = Scene(seed=3, people=3)
    rig = virtual_rig(6, 256, 144, distortion=False)

    def pose(c):
        m = torch.eye(4)
        m[:3, :3] = torch.tensor(c.R, dtype=torch.float32)
        m[:3, 3] = torch.tensor(c.t, dtype=torch.float32)
        return m[None]

    sets = []
    for name in ("left", "right"):
        cam = rig[name]
        r = render(scene, cam, 1.0)
        pts = unproject_depth(torch.tensor(r.depth)[None, None], torch.tensor(cam.K, dtype=torch.float32)[None])
        pts = transform_points(pose(rig["left"]) @ torch.linalg.inv(pose(cam)), pts)
        sets.append(losses.point_colour_set(pts, torch.tensor(r.rgb).permute(2, 0, 1)[None].float() / 255.0))
    return sets


def test_scales_to_the_coarse_size(coarse_point_maps):
    a, b = coarse_point_maps
    assert a.shape == (1, 36864, 6)
    a, b = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
    start = time.perf_counter()
    value = chamfer_6d(a, b)
    value.backward()
    elapsed = time.perf_counter() - start
    # Measured about 1.2 s forward and backward on one CPU core, 2-3 s on a loaded 2-core box; brute
    # force takes several times longer and keeps 5.4 GB per direction for its backward pass.
    assert elapsed < 20.0, elapsed
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0
    # exact: a sample of queries against every point, brute force
    g = torch.Generator().manual_seed(0)
    for x, y in ((a, b), (b, a)):
        q = torch.randint(0, x.shape[1], (400,), generator=g)
        idx = nearest_indices(x[0].detach(), y[0].detach())[q]
        brute = torch.cdist(x[0, q].detach().double(), y[0].detach().double(), compute_mode="donot_use_mm_for_euclid_dist").amin(1)
        got = (x[0, q].detach().double() - y[0, idx].detach().double()).norm(dim=1)
        torch.testing.assert_close(got, brute, rtol=1e-6, atol=1e-7)
