"""ONNX Runtime's long reductions rewritten to float64 (inference.onnx_precision): they round as torch does."""
from __future__ import annotations

import io
import warnings

import numpy as np
import onnx
import onnxruntime as ort
import torch

from inference import onnx_precision


class Reductions(torch.nn.Module):
    """A GroupNorm over groups as long as stage 1's at the coarse size, and a sum over a whole map."""

    def __init__(self):
        super().__init__()
        self.norm = torch.nn.GroupNorm(4, 32)
        with torch.no_grad():
            self.norm.weight.uniform_(0.5, 2.0)
            self.norm.bias.uniform_(-1.0, 1.0)

    def forward(self, x):
        return self.norm(x), x.mean(dim=(2, 3)), x.sum()


def _export(module, x) -> onnx.ModelProto:
    f = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, (x,), f, dynamo=False, opset_version=18)
    return onnx.load_from_string(f.getvalue())


def _run(model: onnx.ModelProto, x: np.ndarray) -> list[np.ndarray]:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    session = ort.InferenceSession(model.SerializeToString(), so, providers=["CPUExecutionProvider"])
    return session.run(None, {session.get_inputs()[0].name: x})


def _errors(outputs, refs) -> list[float]:
    return [float(np.abs(o.astype(np.float64) - r).max() / np.abs(r).max()) for o, r in zip(outputs, refs)]


def test_rewritten_reductions_round_no_worse_than_torch():
    torch.manual_seed(0)
    module = Reductions().eval()
    x = torch.randn(2, 32, 72, 128) * 2 + 1
    with torch.no_grad():
        refs = [t.numpy() for t in module.double()(x.double())]
        module.float()
        torch_err = _errors([t.numpy() for t in module(x)], refs)
    plain = _export(module, x)
    rewritten = onnx.ModelProto()
    rewritten.CopyFrom(plain)
    assert onnx_precision.rewrite(rewritten) == 3  # the InstanceNormalization, the ReduceMean, the ReduceSum
    onnx.checker.check_model(rewritten)
    assert "InstanceNormalization" not in {n.op_type for n in rewritten.graph.node}
    plain_err = _errors(_run(plain, x.numpy()), refs)
    new_err = _errors(_run(rewritten, x.numpy()), refs)
    for name, t, p, n in zip(("group norm", "mean", "sum"), torch_err, plain_err, new_err):
        assert n <= 2 * t + 1e-9, f"{name}: rewritten {n:.2e} against torch {t:.2e} (as exported {p:.2e})"
        assert n < p, f"{name}: rewritten {n:.2e} is no better than as exported ({p:.2e})"


def test_the_exported_model_reduces_in_float64(tiny_onnx):
    m = onnx.load(str(tiny_onnx.path))
    producer = {o: n for n in m.graph.node for o in n.output}
    reductions = [n for n in m.graph.node if n.op_type in onnx_precision.REDUCTIONS]
    assert reductions
    for n in reductions:
        cast = producer.get(n.input[0])
        assert cast is not None and cast.op_type == "Cast" and cast.attribute[0].i == onnx.TensorProto.DOUBLE, n.name
    assert "InstanceNormalization" not in {n.op_type for n in m.graph.node}
