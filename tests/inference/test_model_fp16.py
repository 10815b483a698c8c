"""The fp16 variant: learned layers in float16, geometry and interface in float32."""
from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from inference.export import _quiet, to_fp16


class LearnedThenGeometry(torch.nn.Module):
    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.net = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, padding=1), torch.nn.ReLU(), torch.nn.Conv2d(8, 1, 3, padding=1))

    def forward(self, image, u):
        # A pixel coordinate around 1000 needs float32: float16 would round it to 0.5 px.
        return self.net(image), u * 1.001 + 0.123


def test_fp16_conversion_halves_learned_layers_only(tmp_path):
    m = LearnedThenGeometry().eval()
    image = torch.rand(1, 3, 16, 16)
    u = torch.full((1, 4), 1000.25)
    with torch.no_grad(), _quiet():
        proto = torch.onnx.export(m, (image, u), dynamo=True, opset_version=18, input_names=["image", "u"]).model_proto
    half = to_fp16(proto)
    conv_weights = [i for i in half.graph.initializer if i.dims and len(i.dims) == 4]
    assert conv_weights and all(i.data_type == onnx.TensorProto.FLOAT16 for i in conv_weights)
    assert all(v.type.tensor_type.elem_type == onnx.TensorProto.FLOAT for v in list(half.graph.input) + list(half.graph.output))
    path = tmp_path / "half.onnx"
    onnx.save(half, path)
    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        net, geo = sess.run(None, {"image": image.numpy(), "u": u.numpy()})
    except Exception as exc:  # an ONNX Runtime build without float16 CPU kernels
        pytest.skip(f"this ONNX Runtime cannot run float16 on the CPU: {exc}")
    ref_net, ref_geo = m(image, u)
    assert np.abs(geo - ref_geo.detach().numpy()).max() < 1e-4  # float32 path
    err = np.abs(net - ref_net.detach().numpy()).max()
    assert 0 < err < 1e-2  # float16 arithmetic: close, not bit-equal
