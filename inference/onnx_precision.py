"""Long float32 reductions in an ONNX graph computed in float64, so ONNX Runtime rounds as torch does.

ONNX Runtime's CPU kernels sum a reduced axis in float32 one element after another, where torch
sums in vectorised blocks: against float64, GroupNorm over a 73,728-element group (stage 1's at the
coarse size) is off by 7.6 times torch's error, a mean over a 72x128 map 2.6 times, a sum of 590k
elements 7.3 times (benchmarks/onnx_op_precision.py measures each kernel). Stage 1 normalises and reduces at every layer, and depth init
turns a point's shift of micrometres into millimetres of depth where a person stands in front of a
far wall, so these roundings reached the rendered image as differences above the 1e-3 parity bar
between an exported model and its checkpoint.

Rewritten (in place, before the graph is split into its parts):
- ReduceSum and ReduceMean of a float32 tensor: cast to float64, reduced, cast back;
- InstanceNormalization (how the exporter writes GroupNorm): its mean and variance in float64
  over the spatial axes, then the float32 scale and bias as before.
The arithmetic is the same function; only the rounding changes. Each new node keeps the metadata
of the node it replaces (its stage and layer, read by the exporter's split and its float16 pass).
Float64 costs little here: `rig model bench` at the preview size, two threads, measured the trained
model's ONNX Runtime total at 345 and 346 ms with these rewrites and 347 and 329 ms without (point
init, where the GroupNorms are, 57-58 against 46-51 ms). TensorRT has no float64: under ONNX
Runtime's TensorRT provider these nodes fall to its CUDA or CPU provider.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

REDUCTIONS = ("ReduceSum", "ReduceMean")


def rewrite(model: onnx.ModelProto) -> int:
    """Rewrite `model`'s main graph in place; returns the number of nodes rewritten."""
    g = model.graph
    types, ranks = _float_types(model)
    consts: dict[tuple, str] = {}

    def const(value, dtype) -> str:
        key = (repr(value), np.dtype(dtype).str)
        if key not in consts:
            name = f"onnx_precision_const_{len(consts)}"
            g.initializer.append(numpy_helper.from_array(np.array(value, dtype=dtype), name))
            consts[key] = name
        return consts[key]

    out_nodes, count = [], 0
    for k, node in enumerate(g.node):
        x = node.input[0] if node.input else ""
        plain = node.domain in ("", "ai.onnx") and types.get(x) == TensorProto.FLOAT
        if plain and node.op_type in REDUCTIONS:
            steps = _reduction(node, f"{node.name or node.op_type}_{k}_f64")
        elif plain and node.op_type == "InstanceNormalization" and ranks.get(x, 0) >= 3:
            steps = _instance_norm(node, f"{node.name or 'instance_norm'}_{k}_f64", ranks[x], const)
        else:
            out_nodes.append(node)
            continue
        count += 1
        for new in steps:
            new.metadata_props.extend(node.metadata_props)
            out_nodes.append(new)
    if count:
        del g.node[:]
        g.node.extend(out_nodes)
    return count


def _float_types(model: onnx.ModelProto) -> tuple[dict[str, int], dict[str, int]]:
    inferred = onnx.shape_inference.infer_shapes(model)
    g = inferred.graph
    types, ranks = {}, {}
    for v in list(g.value_info) + list(g.input) + list(g.output):
        t = v.type.tensor_type
        types[v.name] = t.elem_type
        if t.HasField("shape"):
            ranks[v.name] = len(t.shape.dim)
    for init in g.initializer:
        types[init.name] = init.data_type
        ranks[init.name] = len(init.dims)
    return types, ranks


def _reduction(node: onnx.NodeProto, p: str) -> list[onnx.NodeProto]:
    wide = helper.make_node("Cast", [node.input[0]], [f"{p}_in"], name=f"{p}_cast_in", to=TensorProto.DOUBLE)
    reduced = helper.make_node(node.op_type, [f"{p}_in", *node.input[1:]], [f"{p}_out"], name=f"{p}_reduce")
    reduced.attribute.extend(node.attribute)
    narrow = helper.make_node("Cast", [f"{p}_out"], [node.output[0]], name=f"{p}_cast_out", to=TensorProto.FLOAT)
    return [wide, reduced, narrow]


def _instance_norm(node: onnx.NodeProto, p: str, rank: int, const) -> list[onnx.NodeProto]:
    x, scale, bias = node.input[:3]
    eps = next((a.f for a in node.attribute if a.name == "epsilon"), 1e-5)
    axes = const(list(range(2, rank)), np.int64)
    shape = const([-1] + [1] * (rank - 2), np.int64)  # (C,) -> (C, 1, ...), broadcast against (N, C, ...)
    make = helper.make_node
    return [
        make("Cast", [x], [f"{p}_x"], name=f"{p}_cast_in", to=TensorProto.DOUBLE),
        make("ReduceMean", [f"{p}_x", axes], [f"{p}_mean"], name=f"{p}_mean", keepdims=1),
        make("Sub", [f"{p}_x", f"{p}_mean"], [f"{p}_centred"], name=f"{p}_centre"),
        make("Mul", [f"{p}_centred", f"{p}_centred"], [f"{p}_sq"], name=f"{p}_square"),
        make("ReduceMean", [f"{p}_sq", axes], [f"{p}_var"], name=f"{p}_var", keepdims=1),
        make("Add", [f"{p}_var", const(eps, np.float64)], [f"{p}_var_eps"], name=f"{p}_eps"),
        make("Sqrt", [f"{p}_var_eps"], [f"{p}_std"], name=f"{p}_std"),
        make("Div", [f"{p}_centred", f"{p}_std"], [f"{p}_norm64"], name=f"{p}_normalise"),
        make("Cast", [f"{p}_norm64"], [f"{p}_norm"], name=f"{p}_cast_out", to=TensorProto.FLOAT),
        make("Reshape", [scale, shape], [f"{p}_scale"], name=f"{p}_scale_shape"),
        make("Reshape", [bias, shape], [f"{p}_bias"], name=f"{p}_bias_shape"),
        make("Mul", [f"{p}_norm", f"{p}_scale"], [f"{p}_scaled"], name=f"{p}_scale"),
        make("Add", [f"{p}_scaled", f"{p}_bias"], [node.output[0]], name=f"{p}_bias"),
    ]
