"""Whether this ONNX Runtime can run a model's float16 operators on the CPU (test helper).

Some ONNX Runtime builds have no float16 CPU kernel for some operators and refuse such a node
with NOT_IMPLEMENTED ("Could not find an implementation for Conv(11) node ..."); newer ones have
the kernels, or fall back to float32 through inserted Casts. The fp16 tests skip on exactly that
condition, found beforehand by running a one-node float16 model of each operator the model runs
in float16. Any other error, in the probe or in the test after it, is a failure.
"""
from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper
from onnxruntime.capi.onnxruntime_pybind11_state import NotImplemented as OrtNotImplemented

F16, F32 = TensorProto.FLOAT16, TensorProto.FLOAT
UNARY = {"Relu", "Sigmoid", "Tanh", "Erf", "Gelu"}
BINARY = {"Add", "Mul", "MatMul", "Gemm"}
# Inputs (name, type, shape) of the one-node models of the other operators.
SHAPES = {"Conv": [("x", F16, [1, 1, 3, 3]), ("w", F16, [1, 1, 1, 1])], "Cast": [("x", F32, [1, 4])]}


def float16_op_types(model: onnx.ModelProto) -> set[str]:
    """The operators that read or write a float16 tensor in `model`."""
    inferred = onnx.shape_inference.infer_shapes(model)
    g = inferred.graph
    types = {v.name: v.type.tensor_type.elem_type for v in list(g.value_info) + list(g.input) + list(g.output)}
    types.update({i.name: i.data_type for i in g.initializer})
    return {n.op_type for n in g.node if any(types.get(x) == F16 for x in list(n.input) + list(n.output))}


def _one_node_model(op: str, opset: int) -> tuple[onnx.ModelProto, dict[str, np.ndarray]]:
    if op in UNARY:
        inputs = [("x", F16, [1, 4])]
    elif op in BINARY:
        inputs = [("a", F16, [2, 2]), ("b", F16, [2, 2])]
    elif op in SHAPES:
        inputs = SHAPES[op]
    else:
        raise AssertionError(f"no float16 probe for {op}: add one to {__name__}")
    attrs = {"to": F16} if op == "Cast" else {}
    node = helper.make_node(op, [n for n, _, _ in inputs], ["y"], **attrs)
    graph = helper.make_graph([node], "probe", [helper.make_tensor_value_info(n, t, s) for n, t, s in inputs],
                              [helper.make_tensor_value_info("y", F16, None)])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], ir_version=9)
    feeds = {n: np.ones(s, np.float16 if t == F16 else np.float32) for n, t, s in inputs}
    return model, feeds


def missing_float16_cpu_kernels(op_types: set[str], opset: int = 18) -> list[str]:
    """The operators among `op_types` that this ONNX Runtime refuses in float16 on the CPU."""
    missing = []
    for op in sorted(op_types):
        model, feeds = _one_node_model(op, opset)
        try:
            ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, feeds)
        except OrtNotImplemented as exc:
            if "Could not find an implementation" not in str(exc):
                raise
            missing.append(op)
    return missing


def skip_without_float16_cpu_kernels(model: onnx.ModelProto) -> None:
    """Skip the calling test if, and only if, this ONNX Runtime lacks a float16 CPU kernel that
    `model` needs."""
    opset = max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))
    missing = missing_float16_cpu_kernels(float16_op_types(model), opset)
    if missing:
        pytest.skip(f"ONNX Runtime {ort.__version__} has no float16 CPU kernel for {', '.join(missing)}")
