"""The MASt3R backbone's equations and outputs: RoPE, forward shapes and ranges, its place in the
pipeline (S starts at 1), and ONNX Runtime against torch on a reduced-depth network of the same
architecture (2 encoder + 2 decoder blocks, every width the checkpoint's)."""
from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from mast3r_support import official_layout, random_state

from inference.config import BackboneConfig, ModelConfig, Sizes
from inference.export import _quiet
from inference.model.mast3r import MASt3RBackbone
from inference.model.mast3r_vit import apply_rope, rope_tables
from inference.model.mast3r_weights import load_into
from inference.model.backbone import PointMaps
from inference.model.stage1 import AffineTransform

pytestmark = pytest.mark.slow


def test_rope_scores_depend_on_relative_positions_only():
    # The rotary embedding's point: q.k after rotation depends on the positions' difference.
    torch.manual_seed(0)
    cos, sin = rope_tables(6, 7, 64, 100.0)  # tokens row-major: index = row * 7 + col
    q, k = torch.randn(64), torch.randn(64)
    rot = lambda v, i: apply_rope(v.expand(1, 1, 42, 64), cos, sin)[0, 0, i]  # noqa: E731
    idx = lambda r, c: r * 7 + c  # noqa: E731
    a = rot(q, idx(1, 2)) @ rot(k, idx(3, 5))
    b = rot(q, idx(2, 1)) @ rot(k, idx(4, 4))  # same offset (2, 3)
    c = rot(q, idx(1, 2)) @ rot(k, idx(3, 4))  # another offset
    assert abs(float(a - b)) < 1e-4 and abs(float(a - c)) > 1e-2
    # Position (0, 0) is the identity; rows turn the first half of the channels, columns the second.
    assert torch.allclose(rot(q, 0), q, atol=1e-6)
    row_only, col_only = rot(q, idx(1, 0)), rot(q, idx(0, 1))
    assert torch.equal(row_only[32:], q[32:]) and not torch.allclose(row_only[:32], q[:32])
    assert torch.equal(col_only[:32], q[:32]) and not torch.allclose(col_only[32:], q[32:])


@pytest.fixture(scope="module")
def reduced_backbone():
    """2 encoder + 2 decoder blocks at 64x48 (a 3x4 token grid: the DPT's odd-height crop)."""
    cfg = BackboneConfig(kind="mast3r", mast3r_encoder_blocks=2, mast3r_decoder_blocks=2)
    with torch.device("meta"):
        bb = MASt3RBackbone(cfg, (64, 48), descriptors=True)
    load_into(bb.net, random_state(official_layout(2, 2), seed=4), "random", assign=True)
    return bb.eval()


def _images(seed: int, b: int = 1, size=(48, 64)):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, *size, generator=g), torch.rand(b, 3, *size, generator=g)


def test_forward_shapes_and_ranges(reduced_backbone):
    left, right = _images(0, b=2)
    with torch.no_grad():
        pm = reduced_backbone(left, right)
    assert pm.points_left.shape == pm.points_right.shape == (2, 3, 48, 64)
    assert pm.conf_left.shape == pm.conf_right.shape == (2, 1, 48, 64)
    assert pm.tokens_left.shape == pm.tokens_right.shape == (2, 12, 768) and pm.token_grid == (3, 4)
    assert pm.descriptors_left.shape == pm.descriptors_right.shape == (2, 24, 48, 64)
    assert (pm.conf_left >= 1).all() and (pm.conf_right >= 1).all()
    assert torch.allclose(pm.descriptors_left.norm(dim=1), torch.ones(2, 48, 64), atol=1e-5)
    assert torch.isfinite(pm.points_left).all() and not torch.equal(pm.points_left, pm.points_right)
    # The batch items are independent, and the two decoders differ: swapping the views changes both maps.
    with torch.no_grad():
        one = reduced_backbone(left[1:], right[1:])
        swapped = reduced_backbone(right, left)
    assert torch.allclose(one.points_left[0], pm.points_left[1], atol=1e-4)
    assert not torch.allclose(swapped.points_left, pm.points_right, atol=1e-3)
    # Without descriptors (the pipeline's setting) the rest is the same.
    reduced_backbone.descriptors = False
    try:
        with torch.no_grad():
            plain = reduced_backbone(left, right)
    finally:
        reduced_backbone.descriptors = True
    assert plain.descriptors_left is None and torch.equal(plain.points_left, pm.points_left)


def test_stage_1_scaling_starts_at_one_for_mast3r_and_reads_its_768_d_tokens():
    cfg = ModelConfig.for_backbone("mast3r", Sizes.preset("test"))
    assert cfg.stage1.scale_reference == "one" and ModelConfig.for_backbone("tiny").stage1.scale_reference == "baseline"
    assert cfg.backbone.mast3r_encoder_blocks == 24 and cfg.backbone.mast3r_decoder_blocks == 12
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(1, 3, 64, 128, generator=g) + torch.tensor([0.0, 0.0, 2.0]).reshape(1, 3, 1, 1)
    pm = PointMaps(pts, pts + 0.1, 1 + torch.rand(1, 1, 64, 128, generator=g), 1 + torch.rand(1, 1, 64, 128, generator=g),
                   torch.randn(1, 32, 768, generator=g), torch.randn(1, 32, 768, generator=g), (4, 8))
    K = torch.tensor([[[100.0, 0, 64], [0, 100.0, 32], [0, 0, 1]]])
    r2l = torch.eye(4)[None].clone()
    r2l[0, 0, 3] = -0.7  # a 0.7 m baseline
    scales = {}
    for kind in ("mast3r", "tiny"):
        stage1 = ModelConfig.for_backbone(kind).stage1
        torch.manual_seed(0)
        affine = AffineTransform(stage1, 768, (128, 64)).eval()
        with torch.no_grad():
            scales[kind] = affine(pm, K, K, r2l)
    assert torch.allclose(scales["mast3r"].scale, torch.ones(1, 3))  # metric points: S = 1 at the start
    assert torch.allclose(scales["tiny"].scale, torch.full((1, 3), 0.7))  # canonical points: the baseline
    assert torch.equal(scales["mast3r"].points_left, pts)  # and T = 0


class _Outputs(torch.nn.Module):
    def __init__(self, bb):
        super().__init__()
        self.bb = bb

    def forward(self, left, right):
        pm = self.bb(left, right)
        return pm.points_left, pm.points_right, pm.conf_left, pm.conf_right, pm.tokens_left, pm.descriptors_right


def test_onnx_runtime_matches_torch_on_a_reduced_depth_network(reduced_backbone, tmp_path):
    left, right = _images(1)
    module = _Outputs(reduced_backbone).eval()
    with torch.no_grad(), _quiet():
        program = torch.onnx.export(module, (left, right), dynamo=True, opset_version=18, input_names=["left", "right"])
    proto = program.model_proto
    ops = {n.op_type for n in proto.graph.node}
    assert "GridSample" not in ops and "Inverse" not in ops
    path = tmp_path / "mast3r.onnx"
    onnx.save(proto, path)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"left": left.numpy(), "right": right.numpy()})
    with torch.no_grad():
        ref = module(left, right)
    names = ("points_left", "points_right", "conf_left", "conf_right", "tokens_left", "descriptors_right")
    diffs = {n: float(np.abs(g - r.numpy()).max()) for n, g, r in zip(names, got, ref)}
    print("ORT vs torch, max abs:", diffs)
    assert max(diffs.values()) < 1e-3, diffs
    assert float(ref[0].abs().max()) > 1.0  # points about 2 m ahead: the comparison is not of zeros
