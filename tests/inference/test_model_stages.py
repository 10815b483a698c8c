"""The networks stage by stage: backbones, the affine transform, depth refinement, colour, Gaussian plane."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from plane_scene import camera, view_of_plane

from inference.config import BackboneConfig, Stage1Config, Stage2Config
from inference.model.backbone import OracleBackbone, TinyBackbone
from inference.model.geometry import (
    invert_pose,
    pixel_rays,
    project,
    relative_pose,
    transform_points,
)
from inference.model.stage1 import AffineTransform
from inference.model.stage2 import (
    ColourInit,
    DepthRefine,
    GaussianPlane,
    RefinedDepth,
    warp_candidates,
)

COARSE = (64, 32)


def t(a) -> torch.Tensor:
    return torch.tensor(np.asarray(a), dtype=torch.float32)[None]


def rig():
    left = camera("left", (-1.5, 1.2, -3.0), COARSE)
    right = camera("right", (1.5, 1.2, -3.0), COARSE)
    return left, right


def oracle_maps(scale="metric"):
    left, right = rig()
    img_l, d_l = view_of_plane(left)
    img_r, d_r = view_of_plane(right)
    right_to_left = relative_pose(t(left.extrinsic), t(right.extrinsic))
    bb = OracleBackbone(BackboneConfig(kind="oracle", oracle_scale=scale, patch=16), COARSE)
    pm = bb(t(img_l).permute(0, 3, 1, 2), t(img_r).permute(0, 3, 1, 2), t(left.K), t(right.K), right_to_left, t(d_l)[:, None], t(d_r)[:, None])
    return pm, left, right, right_to_left


def test_oracle_point_maps_are_the_scene_in_the_left_frame():
    pm, left, right, _ = oracle_maps()
    # Both views' points lie on the world plane z = 0 once taken back to the world frame.
    for pts in (pm.points_left, pm.points_right):
        world = transform_points(invert_pose(t(left.extrinsic)), pts)
        assert world[:, 2].abs().max() < 1e-5  # measured 7.2e-7
    assert pm.tokens_left.shape == (1, (32 // 16) * (64 // 16), 3 * 16 * 16)


def test_canonical_oracle_has_unit_mean_distance():
    metric, *_ = oracle_maps("metric")
    canon, *_ = oracle_maps("canonical")
    d = torch.cat([canon.points_left.norm(dim=1).flatten(), canon.points_right.norm(dim=1).flatten()]).mean()
    assert abs(d.item() - 1.0) < 1e-6  # measured 1.2e-7
    ratio = metric.points_left / canon.points_left
    assert torch.allclose(ratio, ratio.flatten()[0].expand_as(ratio), rtol=1e-6)  # measured 6.6e-8


def test_tiny_backbone_is_a_few_million_parameters_and_starts_smooth():
    bb = TinyBackbone(BackboneConfig(), (256, 144))
    n = sum(p.numel() for p in bb.parameters())
    assert 1e6 < n < 1e7
    x = torch.rand(1, 3, 144, 256)
    pm = bb(x, x)
    assert pm.points_left.shape == (1, 3, 144, 256) and pm.tokens_left.shape == (1, 9 * 16, 192)
    # Untrained: points on nominal rays one unit ahead.
    assert torch.allclose(pm.points_left[:, 2], torch.ones(1, 144, 256))
    assert (pm.conf_left >= 1).all()


def test_bypassed_affine_transform_is_the_identity():
    pm, left, right, r2l = oracle_maps()
    out = AffineTransform(Stage1Config(affine="bypass"), pm.tokens_left.shape[-1], COARSE)(pm, t(left.K), t(right.K), r2l)
    assert torch.equal(out.points_left, pm.points_left) and torch.equal(out.points_right, pm.points_right)


def test_untrained_affine_transform_scales_by_the_baseline_and_learns():
    pm, left, right, r2l = oracle_maps("canonical")
    torch.manual_seed(0)
    layer = AffineTransform(Stage1Config(iterations=2), pm.tokens_left.shape[-1], COARSE)
    out = layer(pm, t(left.K), t(right.K), r2l)
    baseline = np.linalg.norm(left.center - right.center)
    assert torch.allclose(out.scale, torch.full((1, 3), float(baseline)), rtol=1e-6)  # measured 7.9e-8
    assert out.translation_left.abs().max() == 0
    # Gradients reach both the scale MLP and the ConvGRU's output layer.
    loss = (out.points_left - 2.0).abs().mean() + (out.points_right - 2.0).abs().mean()
    loss.backward()
    assert layer.scale_head.mlp[-1].weight.grad.abs().sum() > 0
    assert layer.translation.delta[-1].weight.grad.abs().sum() > 0


def test_translation_reads_the_other_view():
    """Once trained (here: output layer perturbed), T depends on the other view's features."""
    pm, left, right, r2l = oracle_maps("canonical")
    torch.manual_seed(0)
    layer = AffineTransform(Stage1Config(iterations=2), pm.tokens_left.shape[-1], COARSE)
    torch.nn.init.normal_(layer.translation.delta[-1].weight, std=0.2)  # tanh-bounded steps of 0.05 baselines
    a = layer(pm, t(left.K), t(right.K), r2l).translation_left
    pm.tokens_right = pm.tokens_right.flip(1)
    b = layer(pm, t(left.K), t(right.K), r2l).translation_left
    assert (a - b).abs().max() > 1e-4


def test_the_translation_gate_scales_t_by_each_points_opacity():
    """translation_gate p: T times opacity ** p, so unsure points keep their place along their ray."""
    pm, left, right, r2l = oracle_maps("canonical")
    torch.manual_seed(0)
    pm.conf_left = 1.0 + 9.0 * torch.rand_like(pm.conf_left)  # opacities 0 to 0.9
    outs = {}
    for gate in (0.0, 1.0, 2.0):
        torch.manual_seed(1)
        layer = AffineTransform(Stage1Config(iterations=2, translation_gate=gate), pm.tokens_left.shape[-1], COARSE)
        torch.nn.init.normal_(layer.translation.delta[-1].weight, std=0.2)
        with torch.no_grad():
            outs[gate] = layer(pm, t(left.K), t(right.K), r2l)
    opacity = 1.0 - 1.0 / pm.conf_left
    t0 = outs[0.0].translation_left
    assert t0.abs().max() > 1e-3
    for gate in (1.0, 2.0):
        assert torch.allclose(outs[gate].translation_left, t0 * opacity ** gate, atol=1e-6)
        s = outs[gate].scale.reshape(1, 3, 1, 1)
        assert torch.allclose(outs[gate].points_left, s * pm.points_left + t0 * opacity ** gate, atol=1e-5)
    with pytest.raises(Exception, match="translation_gate"):
        Stage1Config(translation_gate=-1.0)


def off_ray_pixels(out, left, right, r2l) -> float:
    """How far (pixels, the worst point of either view) stage 1's points project from the pixel
    they came from in their own camera."""
    cw, ch = COARSE
    grid = pixel_rays(torch.eye(3)[None], cw, ch)[:, :2]
    uv_l, _ = project(out.points_left, t(left.K))
    uv_r, _ = project(transform_points(invert_pose(r2l), out.points_right), t(right.K))
    return max(float((uv_l - grid).abs().max()), float((uv_r - grid).abs().max()))


def test_translation_along_rays_keeps_every_point_on_its_pixels_ray():
    """translation_along_rays: T keeps its part along each pixel's ray, so a point projects back
    onto the pixel it came from in its own camera, the right view's too."""
    pm, left, right, r2l = oracle_maps("metric")
    outs = {}
    for along in (False, True):
        torch.manual_seed(1)
        layer = AffineTransform(Stage1Config(iterations=2, translation_along_rays=along, scale_reference="one"), pm.tokens_left.shape[-1], COARSE)
        torch.nn.init.normal_(layer.translation.delta[-1].weight, std=0.2)
        with torch.no_grad():
            outs[along] = layer(pm, t(left.K), t(right.K), r2l)
    for along, out in outs.items():
        off = off_ray_pixels(out, left, right, r2l)
        assert (off < 1e-2) if along else (off > 0.5), (along, off)
    # What is left of T is its projection: no longer than T, and along the ray.
    assert (outs[True].translation_left.norm(dim=1) <= outs[False].translation_left.norm(dim=1) + 1e-6).all()
    assert outs[True].translation_left.abs().max() > 1e-3


def test_an_isotropic_scale_keeps_points_on_their_rays_where_three_factors_move_them_off():
    """A trained S with three different factors (people41-f: 4.08, 2.83, 3.69 baselines) scales x
    and y apart from depth: every point leaves its pixel's ray in proportion to its distance from
    the optical axis, even with T along the rays. isotropic_scale keeps S's depth factor for all
    three axes: the depth is the same, the points stay on their rays."""
    pm, left, right, r2l = oracle_maps("metric")
    outs = {}
    for iso in (False, True):
        torch.manual_seed(1)
        layer = AffineTransform(Stage1Config(iterations=2, translation_along_rays=True, scale_reference="one", isotropic_scale=iso),
                                pm.tokens_left.shape[-1], COARSE)
        torch.nn.init.normal_(layer.translation.delta[-1].weight, std=0.2)
        with torch.no_grad():
            layer.scale_head.mlp[-1].bias.copy_(torch.tensor([0.1, -0.25, 0.0]))  # x 1.1, y 0.78, z 1 times
            outs[iso] = layer(pm, t(left.K), t(right.K), r2l)
    for iso, out in outs.items():
        off = off_ray_pixels(out, left, right, r2l)
        assert (off < 1e-2) if iso else (off > 2.0), (iso, off)
    # The same depth in the left camera either way (within what T, which reads the scaled points,
    # changes): only x and y differ.
    assert torch.allclose(outs[True].points_left[:, 2], outs[False].points_left[:, 2], rtol=1e-3)
    assert torch.allclose(outs[True].scale, outs[False].scale[:, 2:3].expand(-1, 3))
    with pytest.raises(Exception, match="isotropic_scale"):
        Stage1Config(isotropic_scale="yes")


def test_translation_and_scale_stay_bounded_whatever_the_weights():
    """An unbounded update once sent T to tens of metres in training (every point behind the
    cameras, no gradient back): T moves at most translation_step baselines per iteration and axis,
    S stays within baseline * exp(+-scale_log_range)."""
    pm, left, right, r2l = oracle_maps("canonical")
    cfg = Stage1Config(iterations=3)
    layer = AffineTransform(cfg, pm.tokens_left.shape[-1], COARSE)
    with torch.no_grad():
        layer.translation.delta[-1].bias.fill_(1e4)
        layer.scale_head.mlp[-1].bias.copy_(torch.tensor([1e4, -1e4, 0.0]))
    out = layer(pm, t(left.K), t(right.K), r2l)
    baseline = float(np.linalg.norm(left.center - right.center))
    bound = cfg.iterations * cfg.translation_step * baseline
    assert out.translation_left.abs().max() <= bound * (1 + 1e-5)
    assert out.translation_left.abs().max() >= 0.99 * bound  # saturated, not clipped elsewhere
    s = out.scale[0] / baseline
    assert torch.allclose(torch.log(s), torch.tensor([cfg.scale_log_range, -cfg.scale_log_range, 0.0]), atol=1e-4)


def two_views_of_a_plane(size=(96, 64)):
    left = camera("left", (-1.0, 1.2, -3.0), size)
    right = camera("right", (1.0, 1.2, -3.0), size)
    target = camera("target", (0.2, 1.1, -3.0), size)
    return left, right, target


def test_cost_volume_warps_agree_at_the_true_depth():
    """Warping both sources at each candidate: they agree best at the candidate on the surface."""
    left, right, target = two_views_of_a_plane()
    img_l, _ = view_of_plane(left)
    img_r, _ = view_of_plane(right)
    _, d_t = view_of_plane(target)
    w, h = target.width, target.height
    offsets = torch.linspace(-0.1, 0.1, 9)
    for shift in (-0.05, 0.0, 0.075):
        init = t(d_t)[:, None] * (1 + shift)
        cand = init / (1 + shift) * 0 + init * (1 + offsets.reshape(1, 9, 1, 1))
        rays = pixel_rays(t(target.K), w, h)
        tl = relative_pose(t(left.extrinsic), t(target.extrinsic))
        tr = relative_pose(t(right.extrinsic), t(target.extrinsic))
        fl, vl = warp_candidates(t(img_l).permute(0, 3, 1, 2), t(left.K), tl, rays, cand)
        fr, vr = warp_candidates(t(img_r).permute(0, 3, 1, 2), t(right.K), tr, rays, cand)
        cost = ((fl - fr) ** 2).sum(1) * vl[:, 0] * vr[:, 0] + (1 - vl[:, 0] * vr[:, 0]) * 1e3
        best = cost.median(dim=-1).values.median(dim=-1).values.argmin().item()
        truth = (1.0 / (1 + shift) - 1)  # the candidate offset that lands on the surface
        assert abs(offsets[best].item() - truth) <= 0.0126  # half the 0.025 spacing: the nearest candidate (measured 0.0026, 0, 0.0052)


def test_uniform_depth_probabilities_keep_the_initial_depth():
    left, right, target = two_views_of_a_plane((64, 48))
    cfg = Stage2Config()
    layer = DepthRefine(cfg, (64, 48))
    torch.nn.init.zeros_(layer.probability.weight)
    torch.nn.init.zeros_(layer.probability.bias)
    img = torch.rand(1, 3, 48, 64)
    init = torch.full((1, 1, 48, 64), 3.0) + torch.rand(1, 1, 48, 64)
    out = layer(img, img, t(left.K), t(right.K), torch.eye(4)[None], torch.eye(4)[None], t(target.K), init)
    assert torch.allclose(out.depth, init, rtol=1e-5)
    assert torch.allclose(out.probabilities.sum(1), torch.ones(1, 12, 16))


def test_colour_comes_from_the_source_that_sees_the_point():
    left, right, target = two_views_of_a_plane((64, 48))
    cfg = Stage2Config(visibility_ramp=8.0)  # the default's 16 px fade covers most of a 64x48 image
    img_l, _ = view_of_plane(left)
    _, d_t = view_of_plane(target)
    refine = DepthRefine(cfg, (64, 48))
    colour = ColourInit(cfg, (64, 48))
    tl = relative_pose(t(left.extrinsic), t(target.extrinsic))
    # The right camera is turned around (same centre, looking back): it sees nothing of the plane.
    turn = t(np.diag([-1.0, 1.0, -1.0, 1.0]))
    away = turn @ t(right.extrinsic)
    tr = away @ invert_pose(t(target.extrinsic))
    L = t(img_l).permute(0, 3, 1, 2)
    Rimg = torch.zeros_like(L)
    d = t(d_t)[:, None]
    ref = refine(L, Rimg, t(left.K), t(right.K), tl, tr, t(target.K), d)
    fixed = RefinedDepth(d, ref.probabilities, ref.phi, ref.features_left, ref.features_right)
    out = colour(L, Rimg, t(left.K), t(right.K), tl, tr, t(target.K), fixed)
    assert out.visible_right.max() == 0
    seen = (out.visible_left == 1).expand(1, 3, 48, 64)
    # fully visible from 8 px inside the border (visibility_ramp): measured 0.62 (0.90 with a 1 px ramp)
    assert seen.float().mean() > 0.55
    assert torch.allclose(out.colour[seen], out.colour_left[seen], atol=1e-6)
    plane = GaussianPlane(cfg, (64, 48))(out, d, t(target.K))
    # Untrained heads: P_c = C, unit quaternions, Gaussians about 0.6 px wide.
    assert torch.allclose(plane.colours, out.colour, atol=1e-6)
    assert torch.allclose(plane.rotations.norm(dim=1), torch.ones(1, 48, 64))
    px = plane.scales[:, 0] / (d[:, 0] / target.K[0, 0])
    assert torch.allclose(px, torch.full_like(px, 0.6), rtol=1e-6)  # measured 9.9e-8
