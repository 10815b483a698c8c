"""ONNX export of the Splat-SAP pipeline (torch side).

One file holds the whole pipeline; the viewpoint (target intrinsics and pose) is an input, so it
changes per call without re-export. Sizes are fixed at export (they are in the metadata). The fp16
variant keeps inputs, outputs and all geometry in float32 and runs the learned layers (convolutions,
linear layers, activations) in float16.

Metadata (`custom_metadata_map` in ONNX Runtime) lets the runtime and `rig model check` rebuild
everything they need without torch:
    splat_sap.format     "1"
    splat_sap.config     the ModelConfig as JSON
    splat_sap.inputs     comma-separated input names, in order
    splat_sap.outputs    comma-separated output names
    splat_sap.precision  fp32 | fp16
    splat_sap.weights    where the weights came from (JSON, see inference.model.checkpoint)
"""
from __future__ import annotations

import contextlib
import io
import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import torch

from common.files import atomic_path
from inference.config import STAGES
from inference.errors import InferenceError, OutputError
from inference.model.checkpoint import seed_record
from inference.model.pipeline import OUTPUT_NAMES, SplatSAP
from inference.runtime.synthetic import example_inputs

FORMAT_VERSION = "1"
OPSET = 18
# Op types that run in float16 in the fp16 variant, when they belong to a learned layer.
FP16_OPS = {"Conv", "Relu", "Gemm", "MatMul", "Add", "Mul", "Gelu", "Erf", "Sigmoid", "Tanh"}


@dataclass
class ExportResult:
    path: Path
    fp16_path: Path | None
    inputs: tuple[str, ...]
    opset: int


def example_arrays(model: SplatSAP, seed: int = 0) -> dict[str, np.ndarray]:
    return example_inputs(model.cfg.sizes, model.needs_depth, seed).arrays


@contextlib.contextmanager
def _quiet():
    """The exporter narrates every step on stdout/stderr; keep the command's own output clean."""
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "torch.export", "torch._dynamo", "torch.fx", "torch.__trace", "torch._subclasses")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    sink = io.StringIO()
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            warnings.simplefilter("ignore")
            yield sink
    finally:
        for lg, lv in zip(loggers, levels):
            lg.setLevel(lv)


def stage_of(node: onnx.NodeProto) -> str | None:
    """The pipeline stage a node belongs to, from the exporter's name-scope metadata."""
    for prop in node.metadata_props:
        if prop.key == "pkg.torch.onnx.name_scopes":
            for scope in eval_list(prop.value):
                head = scope.split(".")[0]
                if head in STAGES:
                    return head
    return None


def eval_list(text: str) -> list[str]:
    """Parse the exporter's "['', 'a', 'a.b']" strings without eval."""
    text = text.strip()
    if not (text.startswith("[") and text.endswith("]")):
        return []
    return [item.strip().strip("'\"") for item in text[1:-1].split(",") if item.strip()]


def _learned_layer(node: onnx.NodeProto) -> bool:
    for prop in node.metadata_props:
        if prop.key == "pkg.torch.onnx.class_hierarchy":
            return "torch.nn.modules." in prop.value and "LayerNorm" not in prop.value
    return False


def to_fp16(model: onnx.ModelProto) -> onnx.ModelProto:
    """Mixed precision: the learned layers' arithmetic (FP16_OPS inside torch.nn layers) in float16,
    everything else (geometry, splatting, normalisation, the inputs and outputs) in float32.

    A float tensor produced by a float16 node is float16; Casts are inserted where a float16 node
    reads a float32 tensor and where a float32 node reads a float16 one; weights are stored in
    float16 when only float16 nodes read them.
    """
    from onnx import TensorProto, helper, numpy_helper

    model = onnx.shape_inference.infer_shapes(model)
    g = model.graph
    types = {v.name: v.type.tensor_type.elem_type for v in list(g.value_info) + list(g.input) + list(g.output)}
    inits = {i.name: i for i in g.initializer}
    for name, init in inits.items():
        types[name] = init.data_type
    nodes = list(g.node)  # index-based: protobuf wrappers have no stable identity
    half_nodes = {k for k, n in enumerate(nodes) if n.op_type in FP16_OPS and _learned_layer(n)}
    is_float = lambda name: types.get(name) == TensorProto.FLOAT  # noqa: E731
    half_values = {o for k in half_nodes for o in nodes[k].output if is_float(o)}
    readers: dict[str, list[int]] = {}
    for k, n in enumerate(nodes):
        for i in n.input:
            readers.setdefault(i, []).append(k)
    casts: dict[tuple[str, int], str] = {}
    new_nodes = []

    def cast(name: str, to: int) -> str:
        key = (name, to)
        if key not in casts:
            out = f"{name}__as_{'fp16' if to == TensorProto.FLOAT16 else 'fp32'}"
            new_nodes.append(helper.make_node("Cast", [name], [out], name=f"cast_{out}", to=to))
            casts[key] = out
        return casts[key]

    for name, init in inits.items():
        if init.data_type == TensorProto.FLOAT and readers.get(name) and all(r in half_nodes for r in readers[name]):
            arr = numpy_helper.to_array(init).astype("float16")
            init.CopyFrom(numpy_helper.from_array(arr, name))
            half_values.add(name)
    for k, n in enumerate(nodes):
        half = k in half_nodes
        for k, i in enumerate(n.input):
            if not i or not is_float(i) and i not in half_values:
                continue
            if half and i not in half_values:
                n.input[k] = cast(i, TensorProto.FLOAT16)
            elif not half and i in half_values:
                n.input[k] = cast(i, TensorProto.FLOAT)
        new_nodes.append(n)
    # A graph output computed in float16 is renamed and cast back under its own name.
    for name in [o.name for o in g.output if o.name in half_values]:
        inner = f"{name}__fp16"
        for n in new_nodes:
            n.output[:] = [inner if o == name else o for o in n.output]
            n.input[:] = [inner if i == name else i for i in n.input]
        new_nodes.append(helper.make_node("Cast", [inner], [name], name=f"cast_{name}_to_fp32", to=TensorProto.FLOAT))
    del g.node[:]
    g.node.extend(new_nodes)
    del g.value_info[:]  # types changed; ONNX Runtime infers them again
    onnx.checker.check_model(model)
    return model


def set_metadata(model: onnx.ModelProto, entries: dict[str, str]) -> None:
    existing = {p.key: p for p in model.metadata_props}
    for key, value in entries.items():
        if key in existing:
            existing[key].value = value
        else:
            p = model.metadata_props.add()
            p.key = key
            p.value = value


def export_onnx(
    model: SplatSAP,
    path: str | os.PathLike,
    *,
    fp16: bool = False,
    weights: str | None = None,
    opset: int = OPSET,
    seed: int = 0,
    optimize: bool = False,
) -> ExportResult:
    """Export `model` to `path` (and `<stem>.fp16.onnx` beside it when fp16). Raises InferenceError.

    `optimize` runs the exporter's full graph optimiser, whose pattern rewriter takes most of the
    export time; by default only constants are folded and dead nodes removed, and ONNX Runtime
    (or TensorRT) fuses what it can when it loads the model.
    """
    if opset < 18:
        raise InferenceError(f"opset {opset} is too old: the pipeline needs ScatterElements with min reduction (opset 18 or later)")
    path = Path(path)
    if path.suffix != ".onnx":
        raise InferenceError(f"{path}: the output file name must end in .onnx")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # checked before the export, which takes a while
        raise InferenceError(f"{path.parent}: cannot create the output folder ({exc.strerror or exc})") from None
    model = model.eval()
    arrays = example_arrays(model, seed)
    names = model.input_names
    args = tuple(torch.from_numpy(arrays[n]) for n in names)
    with torch.no_grad(), _quiet() as log:
        try:
            program = torch.onnx.export(
                model, args, dynamo=True, opset_version=opset, input_names=list(names), output_names=list(OUTPUT_NAMES), external_data=False, optimize=False
            )
        except Exception as exc:  # the exporter raises many types; report one line with the cause
            raise InferenceError(f"ONNX export failed: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}\n{log.getvalue()[-2000:]}") from exc
    if optimize:
        program.optimize()
    else:
        _fold_constants(program.model)
    proto = program.model_proto
    meta = {
        "splat_sap.format": FORMAT_VERSION,
        "splat_sap.config": model.cfg.to_json(),
        "splat_sap.inputs": ",".join(names),
        "splat_sap.outputs": ",".join(OUTPUT_NAMES),
        "splat_sap.precision": "fp32",
        "splat_sap.weights": weights or seed_record(seed),
    }
    set_metadata(proto, meta)
    _save(proto, path)
    fp16_path = None
    if fp16:
        half = to_fp16(proto)
        set_metadata(half, {**meta, "splat_sap.precision": "fp16"})
        fp16_path = path.with_name(path.stem + ".fp16.onnx")
        _save(half, fp16_path)
    return ExportResult(path, fp16_path, names, opset)


def _fold_constants(model) -> None:
    """The exporter's optimiser without its pattern rewriter: constant folding, dead-node removal,
    constants lifted to initializers, common subexpressions merged."""
    import onnx_ir as ir
    import onnx_ir.passes.common as common
    from onnxscript.optimizer import _constant_folding

    passes = ir.passes.Sequential(
        common.InlinePass(),
        ir.passes.PassManager([_constant_folding.FoldConstantsPass(shape_inference=True, input_size_limit=8192, output_size_limit=1 << 20), common.RemoveUnusedNodesPass()], steps=2, early_stop=True),
        common.RemoveUnusedNodesPass(),
        common.LiftConstantsToInitializersPass(lift_all_constants=True, size_limit=0),
        common.DeduplicateInitializersPass(),
        common.CommonSubexpressionEliminationPass(),
        common.NameFixPass(),
    )
    passes(model)


def _save(proto: onnx.ModelProto, path: Path) -> None:
    """Write atomically so that a failed export never leaves a torn model behind.

    The model is one self-contained file (the exporter runs with external_data=False, and none is
    written here). Were external data ever needed, its file name would have to be given from the
    final name (location=path.name + ".data"): onnx records it relative to the model's folder,
    which the rename keeps, but a name derived from the temporary would dangle after the rename,
    and the data file itself would not be written atomically. The temporary keeps the .onnx
    suffix, from which onnx.save_model picks the protobuf format.
    """
    try:
        with atomic_path(path) as tmp:
            onnx.save_model(proto, str(tmp), save_as_external_data=False)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
