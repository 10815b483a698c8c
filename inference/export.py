"""ONNX export of the Splat-SAP pipeline (torch side).

One file holds the whole pipeline; the viewpoint (target intrinsics and pose) is an input, so it
changes per call without re-export. Sizes are fixed at export (they are in the metadata). The fp16
variant keeps inputs, outputs and all geometry in float32 and runs the learned layers (convolutions,
linear layers, activations) in float16.

Beside M.onnx the export writes the same graph cut in two (inference.runtime.split): M.stage1.onnx
(source inputs -> the stage-1 tensors, STAGE1_OUTPUT_NAMES: point_init and affine_transform, which
do not depend on the target) and M.view.onnx (those tensors + the source inputs the later stages
read + target_K, target_pose -> image, depth). The model is traced once, with the stage-1 tensors as
extra graph outputs; the three files are cut out of that one graph, so the parts compute exactly
what the whole file computes. A model with the scale search also gets M.stage1_unscaled.onnx: stage 1
without the search (a second trace with it off), for the live runtime to reuse the factor.

Constant folding materialises the constant tensors the model builds (zeros_like, full_like, pixel
grids) as initializers, which made a preview-size file nine times its weights. `slim_constants`
replaces each large one whose elements are all equal by a ConstantOfShape node, and each large
integer-step ramp (a pixel coordinate grid, or a few of them stacked) by Range, Reshape and Expand
(Concat for a stack), which compute the same values exactly; ONNX Runtime folds them again at load.

ONNX Runtime's CPU kernels add long reductions up in float32 one element at a time, several times
torch's rounding; the traced graph's ReduceSum, ReduceMean and GroupNorm statistics are computed in
float64 (inference.onnx_precision), which keeps a trained model's export within the parity bar.

Weights above 2 GB (the MASt3R backbone) cannot be one protobuf: the export keeps them out of the
graphs once traced and writes them to one external-data file beside the models
(inference.onnx_weights); smaller models stay one self-contained file each.

Metadata (`custom_metadata_map` in ONNX Runtime) lets the runtime and `rig model check` rebuild
everything they need without torch:
    splat_sap.format     "1"
    splat_sap.config     the ModelConfig as JSON
    splat_sap.inputs     comma-separated input names, in order
    splat_sap.outputs    comma-separated output names
    splat_sap.precision  fp32 | fp16
    splat_sap.weights    where the weights came from (JSON, see inference.model.checkpoint)
The parts have the same keys (with their own inputs and outputs) and also
    splat_sap.part       stage1 | view | stage1_unscaled   (the whole file has no part key)
"""
from __future__ import annotations

import contextlib
import io
import logging
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnx
import onnx.utils
import torch

from common.files import atomic_path
from inference.config import STAGES
from inference.errors import InferenceError, OutputError
from inference.model.checkpoint import seed_record
from inference.model.pipeline import INPUT_NAMES, OUTPUT_NAMES, STAGE1_OUTPUT_NAMES, SplatSAP
from inference import onnx_weights, onnx_precision
from inference.onnx_weights import WeightStore, detach, has_detached, is_detached, write_models
from inference.runtime.split import TARGET_INPUTS, UNSCALED_PART, part_path
from inference.runtime.synthetic import example_inputs

FORMAT_VERSION = "1"
OPSET = 18
# Op types that run in float16 in the fp16 variant, when they belong to a learned layer.
FP16_OPS = {"Conv", "Relu", "Gemm", "MatMul", "Add", "Mul", "Gelu", "Erf", "Sigmoid", "Tanh"}
# Stages of the stage1 part (everything before depth_init); the view part holds none of their nodes.
STAGE1_STAGES = ("point_init", "affine_transform")
# Initializers of at least this many elements are candidates for slim_constants.
SLIM_MIN_ELEMENTS = 1024
# Node metadata the exporter writes that is kept: the name scopes (stage_of: the benchmark's
# per-stage times) and the module classes (_learned_layer: the fp16 conversion). The rest (Python
# stack traces with the exporting machine's paths, FX node text, a namespace string repeating
# both) is debugging aid, and was more than the weights of a test-size model.
NODE_METADATA_KEPT = ("pkg.torch.onnx.name_scopes", "pkg.torch.onnx.class_hierarchy")


@dataclass
class ExportResult:
    path: Path
    fp16_path: Path | None
    inputs: tuple[str, ...]
    opset: int
    # The split files: M.stage1.onnx, M.view.onnx (then M.fp16.stage1.onnx, M.fp16.view.onnx with fp16;
    # last M.stage1_unscaled.onnx for a model with the scale search).
    parts: tuple[Path, ...] = ()
    # What the slimming did: {"replaced": initializers replaced, "bytes": their bytes,
    # "node_metadata_bytes": node metadata dropped}.
    slimmed: dict = field(default_factory=dict)
    # External-data files beside the models (weights above the limit: fp32, then fp16), else empty.
    data_files: tuple[Path, ...] = ()


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


def to_fp16(model: onnx.ModelProto, store: WeightStore | None = None) -> onnx.ModelProto:
    """Mixed precision: the learned layers' arithmetic (FP16_OPS inside torch.nn layers) in float16,
    everything else (geometry, splatting, normalisation, the inputs and outputs) in float32.

    A float tensor produced by a float16 node is float16; Casts are inserted where a float16 node
    reads a float32 tensor and where a float32 node reads a float16 one; weights are stored in
    float16 when only float16 nodes read them (detached weights, inference.onnx_weights, are
    converted in `store`).
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
            if is_detached(init):
                store.to_float16(init)
            else:
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
    if not has_detached(model):  # else the files are checked once written (inference.onnx_weights)
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
    external_data_limit: int | None = None,
    shared_data: bool = False,
) -> ExportResult:
    """Export `model` to `path` (and `<stem>.fp16.onnx` beside it when fp16). Raises InferenceError.

    `optimize` runs the exporter's full graph optimiser, whose pattern rewriter takes most of the
    export time; by default only constants are folded and dead nodes removed, and ONNX Runtime
    (or TensorRT) fuses what it can when it loads the model. A file set whose weights exceed
    `external_data_limit` bytes (default onnx_weights.EXTERNAL_DATA_LIMIT, 2 GB) keeps them in one data file beside it (inference.onnx_weights).
    `shared_data` keeps the weights of the fp32 file and all its parts once, in one data file beside
    M.onnx whatever their size (inference.onnx_weights.share_data): a quarter of the bytes of
    self-contained files, as the shipped models are stored.
    """
    if external_data_limit is None:
        external_data_limit = onnx_weights.EXTERNAL_DATA_LIMIT  # read at call time (tests lower it)
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
    traced, slimmed = _trace(model, arrays, opset, optimize)
    # From here the large initializers live in `store`, not in the protos (inference.onnx_weights):
    # a model over 2 GiB (the MASt3R backbone) cannot be one protobuf.
    store = detach(traced)
    whole, stage1, view = split_model(traced, names)
    meta = {
        "splat_sap.format": FORMAT_VERSION,
        "splat_sap.config": model.cfg.to_json(),
        "splat_sap.inputs": ",".join(names),
        "splat_sap.outputs": ",".join(OUTPUT_NAMES),
        "splat_sap.precision": "fp32",
        "splat_sap.weights": weights or seed_record(seed),
    }
    models = {None: whole, "stage1": stage1, "view": view}
    for part, proto in models.items():
        set_metadata(proto, _part_metadata(meta, part, proto))
    parts = [part_path(path, part) for part in ("stage1", "view")]
    data = [write_models([(whole, path), (stage1, parts[0]), (view, parts[1])], store, _save, external_data_limit)]
    fp16_path = None
    if fp16:
        # Each file converted on its own: a stage-1 tensor the learned layers compute in float16
        # leaves the stage1 part cast to float32 (as the whole file casts it for depth_init) and
        # enters the view part as float32, so the parts still compute what the whole file does.
        fp16_path = path.with_name(path.stem + ".fp16.onnx")
        halves = []
        for part, proto in models.items():
            half = to_fp16(proto, store)
            set_metadata(half, {**_part_metadata(meta, part, proto), "splat_sap.precision": "fp16"})
            halves.append((half, fp16_path if part is None else part_path(fp16_path, part)))
        data.append(write_models(halves, store, _save, external_data_limit))
        parts += [target for _, target in halves[1:]]
    if _has_scale_search(model):
        parts.append(_export_unscaled_stage1(model, arrays, opset, optimize, meta, path, external_data_limit))
    if shared_data:
        fp32 = [path] + [p for p in parts if fp16_path is None or not p.name.startswith(fp16_path.stem + ".")]
        data[0] = onnx_weights.share_data(fp32)
    return ExportResult(path, fp16_path, names, opset, tuple(parts), slimmed, tuple(d for d in data if d is not None))


def _trace(model: SplatSAP, arrays: dict[str, np.ndarray], opset: int, optimize: bool) -> tuple[onnx.ModelProto, dict]:
    """One trace of the whole pipeline with the stage-1 tensors as extra outputs (the whole file and
    both parts are cut out of this graph), constants folded and slimmed."""
    names = model.input_names
    args = tuple(torch.from_numpy(arrays[n]) for n in names)
    model.export_stage1 = True
    with torch.no_grad(), _quiet() as log:
        try:
            program = torch.onnx.export(
                model, args, dynamo=True, opset_version=opset, input_names=list(names), output_names=list(OUTPUT_NAMES + STAGE1_OUTPUT_NAMES),
                external_data=False, optimize=False,
            )
        except Exception as exc:  # the exporter raises many types; report one line with the cause
            raise InferenceError(f"ONNX export failed: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}\n{log.getvalue()[-2000:]}") from exc
        finally:
            model.export_stage1 = False
    if optimize:
        program.optimize()
    else:
        _fold_constants(program.model)
    traced = program.model_proto
    onnx_precision.rewrite(traced)
    slimmed = slim_constants(traced, keep={n for n, _ in model.named_parameters()})
    slimmed["node_metadata_bytes"] = strip_node_metadata(traced)
    return traced, slimmed


def _has_scale_search(model: SplatSAP) -> bool:
    cfg = model.cfg.stage1
    return cfg.affine == "learned" and bool(cfg.scale_search)


def _export_unscaled_stage1(model: SplatSAP, arrays: dict[str, np.ndarray], opset: int, optimize: bool, meta: dict[str, str],
                            path: Path, external_data_limit: int) -> Path:
    """M.stage1_unscaled.onnx: stage 1 without its last step, the scale search (the stage-1 tensors
    before the factor; docs/model.md, "Scale search"). The factor is the same on every frame set of
    a take, and the search is most of stage 1's time on a CPU: the live runtime finds it with the
    whole stage 1 on some sets and scales this part's points by it on the others
    (inference.runtime.split, `scale_every`). Its metadata is the model's own (the search is on in
    its config), with splat_sap.part = stage1_unscaled."""
    cfg = model.cfg.stage1
    searched = cfg.scale_search
    cfg.scale_search = 0  # AffineTransform reads it at every forward: the same weights, the search skipped
    try:
        traced, _ = _trace(model, arrays, opset, optimize)
    finally:
        cfg.scale_search = searched
    store = detach(traced)
    _, unscaled, _ = split_model(traced, model.input_names)
    set_metadata(unscaled, _part_metadata(meta, UNSCALED_PART, unscaled))
    target = part_path(path, UNSCALED_PART)
    write_models([(unscaled, target)], store, _save, external_data_limit)
    return target


def _part_metadata(meta: dict[str, str], part: str | None, proto: onnx.ModelProto) -> dict[str, str]:
    if part is None:
        return dict(meta)
    return {**meta, "splat_sap.inputs": ",".join(i.name for i in proto.graph.input), "splat_sap.outputs": ",".join(o.name for o in proto.graph.output),
            "splat_sap.part": part}


def split_model(graph: onnx.ModelProto, input_names: tuple[str, ...]) -> tuple[onnx.ModelProto, onnx.ModelProto, onnx.ModelProto]:
    """(whole, stage1, view) from the traced graph whose outputs are image, depth and the stage-1
    tensors. `graph` becomes the whole model (its extra outputs dropped: image and depth only).

    stage1: the source inputs (all of them, read or not) -> the stage-1 tensors. view: the stage-1
    tensors, then the source images, intrinsics and poses (and the depth maps if the later stages
    read them, which they do not), then target_K, target_pose -> image, depth. Raises
    InferenceError if the cut is not clean: stage 1 reading the target, or the view part holding
    point_init or affine_transform nodes.
    """
    outputs = [o.name for o in graph.graph.output]
    if outputs != list(OUTPUT_NAMES + STAGE1_OUTPUT_NAMES):
        raise InferenceError(f"internal: the traced graph's outputs are {outputs}, expected {list(OUTPUT_NAMES + STAGE1_OUTPUT_NAMES)}")
    stage1_reads = _reached_inputs(graph, STAGE1_OUTPUT_NAMES, ())
    if stage1_reads & set(TARGET_INPUTS):
        raise InferenceError(f"internal: the stage-1 tensors depend on the target ({', '.join(sorted(stage1_reads))})")
    # Every source input, also one a backbone does not read (the oracle's stage 1 reads no image):
    # the same interface for every model.
    stage1_inputs = [n for n in input_names if n not in TARGET_INPUTS]
    view_reads = _reached_inputs(graph, OUTPUT_NAMES, STAGE1_OUTPUT_NAMES)
    view_inputs = list(STAGE1_OUTPUT_NAMES) + [n for n in input_names if n in view_reads or n in INPUT_NAMES]
    extractor = onnx.utils.Extractor(graph)
    stage1 = _with_header(extractor.extract_model(stage1_inputs, list(STAGE1_OUTPUT_NAMES)), graph, "stage1")
    view = _with_header(extractor.extract_model(view_inputs, list(OUTPUT_NAMES)), graph, "view")
    leaked = {stage_of(n) for n in view.graph.node} & set(STAGE1_STAGES)
    if leaked:
        names = [n.name for n in view.graph.node if stage_of(n) in leaked][:4]
        raise InferenceError(f"internal: the view part holds nodes of {', '.join(sorted(leaked))} ({', '.join(names)})")
    del graph.graph.output[len(OUTPUT_NAMES):]
    return graph, stage1, view


def _reached_inputs(graph: onnx.ModelProto, outputs, stop) -> set[str]:
    """The graph inputs the given outputs are computed from, not looking behind the `stop` tensors."""
    producer = {o: n for n in graph.graph.node for o in n.output}
    inputs = {i.name for i in graph.graph.input}
    seen, todo, found = set(stop), list(outputs), set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        if name in inputs:
            found.add(name)
        elif name in producer:
            todo.extend(i for i in producer[name].input if i)
    return found


def _with_header(part: onnx.ModelProto, whole: onnx.ModelProto, name: str) -> onnx.ModelProto:
    """The extracted model with the whole model's producer and graph name (the extractor writes its own)."""
    part.producer_name = whole.producer_name
    part.producer_version = whole.producer_version
    part.graph.name = f"{whole.graph.name or 'main_graph'}.{name}"
    return part


def strip_node_metadata(model: onnx.ModelProto, kept: tuple[str, ...] = NODE_METADATA_KEPT) -> int:
    """Drop node metadata_props other than `kept`; returns the bytes removed."""
    removed = 0
    for node in model.graph.node:
        drop = [p for p in node.metadata_props if p.key not in kept]
        if drop:
            removed += sum(p.ByteSize() for p in drop)
            keep = [onnx.StringStringEntryProto(key=p.key, value=p.value) for p in node.metadata_props if p.key in kept]
            del node.metadata_props[:]
            node.metadata_props.extend(keep)
    return removed


def slim_constants(model: onnx.ModelProto, keep: set[str] = frozenset(), min_elements: int = SLIM_MIN_ELEMENTS) -> dict:
    """Replace large constant initializers by the few nodes that compute them, exactly.

    An initializer of at least `min_elements` elements (not named in `keep`, e.g. the model's
    parameters) whose elements are all equal becomes ConstantOfShape; one that varies along one axis
    only, as start + k step with integer start and step (a pixel coordinate), becomes Range ->
    Reshape -> Expand; one made of a few (at most 4) such slices along an axis becomes their Concat.
    Float ramps are exact: integers below 2^24 (2^11 for float16) whatever order Range adds in.
    Returns {"replaced": count, "bytes": bytes removed}.
    """
    from onnx import numpy_helper

    g = model.graph
    graph_inputs = {i.name for i in g.input}
    names = {i.name for i in g.initializer} | graph_inputs | {o for n in g.node for o in n.output}
    new_nodes: list[onnx.NodeProto] = []
    new_inits: list[onnx.TensorProto] = []
    kept: list[onnx.TensorProto] = []
    replaced = removed = 0
    for init in g.initializer:
        plan = None
        if init.name not in keep and init.name not in graph_inputs and _elements(init) >= min_elements:
            plan = _constant_plan(numpy_helper.to_array(init), init.name)
        added = set() if plan is None else {o for n in plan[0] for o in n.output if o != init.name} | {i.name for i in plan[1]}
        if plan is None or added & names:  # a name taken: never seen (the exporter's names have no "__")
            kept.append(init)
            continue
        names |= added
        nodes, inits = plan
        new_nodes.extend(nodes)
        new_inits.extend(inits)
        replaced += 1
        removed += init.ByteSize()
    if replaced:
        nodes = new_nodes + list(g.node)  # the new nodes read only initializers: first is topological
        del g.node[:]
        g.node.extend(nodes)
        del g.initializer[:]
        g.initializer.extend(kept + new_inits)
    return {"replaced": replaced, "bytes": removed}


def _elements(init: onnx.TensorProto) -> int:
    return int(np.prod(init.dims)) if len(init.dims) else 1


# Magnitudes below which Range's values are exact in each type (and the check below, in float64, too).
_RANGE_EXACT = {np.dtype(np.float32): 2**24, np.dtype(np.float64): 2**53, np.dtype(np.float16): 2**11,
                np.dtype(np.int32): 2**31, np.dtype(np.int64): 2**53}


def _constant_plan(a: np.ndarray, name: str):
    """(nodes, small initializers) computing `a` under `name`, or None."""
    from onnx import helper, numpy_helper

    if a.dtype.kind not in "fiub" or a.ndim == 0:
        return None
    def shape_init(tag: str, dims) -> onnx.TensorProto:
        return numpy_helper.from_array(np.asarray(dims, dtype=np.int64), f"{name}__{tag}")

    def piece(x: np.ndarray, out: str, tag: str):
        flat = x.reshape(-1)
        bits = flat.view(f"u{flat.itemsize}") if flat.dtype.kind == "f" else flat  # -0.0 is not 0.0 here
        if (bits == bits[0]).all():
            value = numpy_helper.from_array(flat[:1].copy(), "value")
            s = shape_init(f"{tag}shape", x.shape)
            return [helper.make_node("ConstantOfShape", [s.name], [out], name=f"{out}__fill", value=value)], [s]
        ramp = _ramp(x)
        if ramp is None:
            return None
        axis, start, step = ramp
        n = x.shape[axis]
        scalars = [numpy_helper.from_array(np.asarray(v, dtype=x.dtype), f"{name}__{tag}{k}") for k, v in (("start", start), ("limit", start + step * n), ("delta", step))]
        line = shape_init(f"{tag}lineshape", [n if k == axis else 1 for k in range(x.ndim)])
        full = shape_init(f"{tag}shape", x.shape)
        r, v = f"{out}__range", f"{out}__ramp"
        nodes = [helper.make_node("Range", [i.name for i in scalars], [r], name=r),
                 helper.make_node("Reshape", [r, line.name], [v], name=v),
                 helper.make_node("Expand", [v, full.name], [out], name=f"{out}__expand")]
        return nodes, scalars + [line, full]

    plan = piece(a, name, "")
    if plan is not None:
        return plan
    for axis in range(a.ndim):
        if 2 <= a.shape[axis] <= 4:
            pieces = [piece(np.take(a, [k], axis=axis), f"{name}__part{k}", f"part{k}_") for k in range(a.shape[axis])]
            if all(p is not None for p in pieces):
                nodes = [n for p in pieces for n in p[0]] + [helper.make_node("Concat", [f"{name}__part{k}" for k in range(len(pieces))], [name], name=f"{name}__concat", axis=axis)]
                return nodes, [i for p in pieces for i in p[1]]
    return None


def _ramp(x: np.ndarray):
    """(axis, start, step) if x varies along one axis only, as start + k step with integer start
    and step whose values Range computes exactly in x's type; else None."""
    if x.dtype.kind not in "fi" or x.dtype not in _RANGE_EXACT:
        return None
    if x.dtype.kind == "f" and (np.signbit(x) & (x == 0)).any():  # Range makes +0.0 only
        return None
    varying = [k for k in range(x.ndim) if x.shape[k] > 1 and not (np.diff(x, axis=k) == 0).all()]
    if len(varying) != 1:
        return None
    axis = varying[0]
    line = np.moveaxis(x, axis, -1).reshape(-1, x.shape[axis])[0].astype(np.float64)
    start, step = line[0], line[1] - line[0]
    n = line.size
    if start != np.round(start) or step != np.round(step):
        return None
    expected = start + step * np.arange(n, dtype=np.float64)
    if not np.array_equal(line, expected) or max(abs(start), abs(start + step * n)) >= _RANGE_EXACT[x.dtype]:
        return None
    return axis, start, step


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

    `proto` is written as it is: self-contained, or referring to an external-data file that
    inference.onnx_weights.write_models wrote beforehand (atomically, under a name given from the
    final model name, which onnx records relative to the model's folder; the rename keeps it). The
    temporary keeps the .onnx suffix, from which onnx.save_model picks the protobuf format.
    """
    try:
        with atomic_path(path) as tmp:
            onnx.save_model(proto, str(tmp), save_as_external_data=False)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
