"""The calibrated plane-sweep backbone: geometry of its point maps (scale-free, on each camera's rays)."""
from __future__ import annotations

import torch

from inference.config import BackboneConfig
from inference.model.geometry import invert_pose, pixel_rays, project, resize_intrinsics, transform_points
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


def facing(baseline: float):
    """rig(), each camera turned towards the other (rig()'s turn away: near its cameras they share no view)."""
    K, r2l = rig(baseline)
    r2l[0, :3, :3] = r2l[0, :3, :3].T.clone()
    return K, r2l


def cascaded(hypotheses: int = 8, log_range: float = 0.35, live: bool = True) -> StereoBackbone:
    """The backbone() with a cascade; `live`: its zero-initialised last layers drawn at random, so it moves depth."""
    torch.manual_seed(0)
    net = StereoBackbone(BackboneConfig(kind="stereo", stereo_cascade=hypotheses, stereo_cascade_range=log_range), (W, H))
    net.load_state_dict(backbone().state_dict(), strict=False)
    if live:
        g = torch.Generator().manual_seed(3)
        with torch.no_grad():
            for last in (net.cascade.regularise[-1], net.cascade.refine[-1], net.cascade.confidence[-1]):
                last.weight.copy_(torch.randn(last.weight.shape, generator=g) * 0.5)
    return net.eval()


def test_a_cascade_added_to_trained_weights_starts_computing_what_they_did():
    K, r2l = facing(1.0)
    left, right = images()
    with torch.no_grad():
        a = backbone()(left, right, K, K, r2l)
        b = cascaded(live=False)(left, right, K, K, r2l)
    for name in ("points_left", "points_right", "conf_left", "conf_right"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_the_cascade_moves_depth_along_the_rays_within_its_range():
    K, r2l = facing(1.0)
    left, right = images()
    with torch.no_grad():
        a = backbone()(left, right, K, K, r2l)
        b = cascaded(log_range=0.35)(left, right, K, K, r2l)
    ratio = b.points_left[:, 2] / a.points_left[:, 2]
    assert ratio.min() >= torch.exp(torch.tensor(-0.35)) - 1e-5 and ratio.max() <= torch.exp(torch.tensor(0.35)) + 1e-5
    assert (ratio - 1).abs().max() > 1e-3  # it moved
    uv_a, _ = project(a.points_left, K)
    uv_b, _ = project(b.points_left, K)
    assert (uv_a - uv_b).abs().max() < 1e-3  # on the same rays
    assert not torch.equal(a.conf_left, b.conf_left)


def test_the_cascade_follows_the_other_view():
    """Its sweep matches the views: what the right camera sees changes its depth shift."""
    net = cascaded()
    base = backbone()
    K, r2l = facing(1.0)
    left, right = images()
    with torch.no_grad():
        shift = lambda r: net(left, r, K, K, r2l).points_left[:, 2] / base(left, r, K, K, r2l).points_left[:, 2]  # noqa: E731
        a, b = shift(right), shift(right.flip(-1))
    assert (a - b).abs().max() > 1e-3


def test_the_cascade_exports_to_onnx_runtime_within_float_rounding():
    import numpy as np
    import onnxruntime as ort

    from inference.export import _quiet

    net = cascaded()
    K, r2l = facing(1.0)
    left, right = images()

    class Depth(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.net = net

        def forward(self, left, right, K, r2l):
            pm = self.net(left, right, K, K, r2l)
            return pm.points_left, pm.conf_left

    args = (left, right, K, r2l)
    with torch.no_grad(), _quiet():
        program = torch.onnx.export(Depth().eval(), args, dynamo=True, opset_version=18)
    sess = ort.InferenceSession(program.model_proto.SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run(None, {i.name: a.numpy() for i, a in zip(sess.get_inputs(), args)})
    with torch.no_grad():
        ref = Depth().eval()(*args)
    assert np.abs(got[0] - ref[0].numpy()).max() < 1e-4
    assert np.abs(got[1] - ref[1].numpy()).max() / ref[1].numpy().max() < 1e-4


def reading(scale: int, coarse: tuple[int, int]) -> StereoBackbone:
    """backbone()'s weights in a backbone that reads its images at `scale` times `coarse`."""
    net = StereoBackbone(BackboneConfig(kind="stereo", stereo_input_scale=scale), coarse)
    net.load_state_dict(backbone().state_dict())
    return net


def test_reading_twice_the_coarse_size_sweeps_a_volume_twice_as_fine_and_returns_coarse_point_maps():
    """At stereo_input_scale 2 the sweep is the one a backbone of twice the coarse size runs (the same
    plane probabilities); the point maps, confidences and token grid stay at the coarse size."""
    K, r2l = facing(1.0)
    K2 = resize_intrinsics(K, (W, H), (2 * W, 2 * H))
    g = torch.Generator().manual_seed(1)
    left, right = torch.rand(1, 3, 2 * H, 2 * W, generator=g), torch.rand(1, 3, 2 * H, 2 * W, generator=g)
    fine = reading(2, (W, H)).train()
    big = reading(1, (2 * W, 2 * H)).train()
    with torch.no_grad():
        a = fine(left, right, K2, K2, r2l)
        b = big(left, right, K2, K2, r2l)
    assert fine.volume_size == (W // 2, H // 2)
    torch.testing.assert_close(a.planes.prob_left, b.planes.prob_left)
    assert a.points_left.shape == (1, 3, H, W) and a.conf_left.shape == (1, 1, H, W)
    grid = pixel_rays(torch.eye(3)[None], W, H)[:, :2]
    uv, _ = project(a.points_left, K)
    assert (uv - grid).abs().max() < 1e-3  # on the coarse camera's rays
    assert a.token_grid == (H // 16, W // 16) and a.tokens_left.shape == (1, (H // 16) * (W // 16), fine.token_dim)
    # Its tokens pool the same features over twice the window: the big backbone's tokens, pooled 2x2.
    tb = b.tokens_left.transpose(1, 2).reshape(1, -1, H // 8, W // 8)
    pooled = torch.nn.functional.avg_pool2d(tb, 2).flatten(2).transpose(1, 2)
    torch.testing.assert_close(a.tokens_left, pooled)


def test_the_pipeline_hands_a_backbone_reading_twice_the_coarse_size_the_fine_images():
    from inference.config import ModelConfig, Sizes
    from inference.model.pipeline import build_model

    cfg = ModelConfig(sizes=Sizes(coarse=(W, H), fine=(2 * W, 2 * H), output=(2 * W, 2 * H)),
                      backbone=BackboneConfig(kind="stereo", stereo_input_scale=2))
    model = build_model(cfg)
    seen = []
    model.point_init.register_forward_hook(lambda m, args, out: seen.append((args[0].shape[-2:], out.points_left.shape[-2:])))
    K, r2l = facing(1.0)
    K2 = resize_intrinsics(K, (W, H), (2 * W, 2 * H))
    pose = torch.eye(4)[None]
    left, right = torch.rand(2, 1, 3, 2 * H, 2 * W)
    with torch.no_grad():
        model(left, right, K2, K2, pose, invert_pose(r2l), K2, pose)
    assert seen == [((2 * H, 2 * W), (H, W))]


def test_stereo_input_scale_is_checked():
    import pytest

    from inference.errors import InferenceError

    for bad in (0, 5, 1.5, True):
        with pytest.raises(InferenceError, match="stereo_input_scale"):
            BackboneConfig(kind="stereo", stereo_input_scale=bad)


def test_a_backbone_reading_the_fine_images_exports_and_splits_cleanly(tmp_path):
    """Depth refinement stacks and scales the same fine images: the exporter must not merge that into
    a backbone node that the live split's view part would then hold (export_onnx raises if it does)."""
    import onnx

    from inference.config import ModelConfig, Sizes
    from inference.export import export_onnx, stage_of
    from inference.model.pipeline import build_model
    from inference.runtime import part_path

    # The fine size twice the coarse one, as at the preview and paper presets: the backbone reads the fine images themselves.
    cfg = ModelConfig(sizes=Sizes(coarse=(128, 64), fine=(256, 128), output=(320, 160)), backbone=BackboneConfig(kind="stereo", stereo_input_scale=2))
    export_onnx(build_model(cfg), tmp_path / "m.onnx")
    view = {stage_of(n) for n in onnx.load(str(part_path(tmp_path / "m.onnx", "view"))).graph.node}
    assert "depth_refine" in view and not view & {"point_init", "affine_transform"}
