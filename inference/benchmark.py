"""Per-stage timing of the pipeline: torch eager against ONNX Runtime, on the same inputs.

Stages are the paper's breakdown (inference.config.STAGES). Torch times each stage with a wall
clock around its module (synchronising CUDA). ONNX Runtime runs one graph: its total is the wall
time of plain runs, and its per-stage figures come from separate profiled runs, each node's kernel
time attributed to the stage whose name scope the exporter recorded on it (nodes ONNX Runtime
fused or inserted are matched by their original names; what matches nothing is 'other'), then
scaled so that the stages add up to the plain total.
Torch and ONNX Runtime runs alternate, so a busy machine slows both alike; figures are medians.
"""
from __future__ import annotations

import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import torch

from inference.config import SIZE_PRESETS, STAGES, ModelConfig, Sizes
from inference.device import describe
from inference.errors import InferenceError
from inference.export import export_onnx, stage_of
from inference.model.pipeline import build_model
from inference.runtime import available_providers, open_session
from inference.runtime.synthetic import example_inputs

# The paper's Table "Time cost of our pipeline" (RTX 3090, PyTorch, paper sizes).
PAPER_MS = {
    "point_init": 97.0,
    "affine_transform": 34.0,
    "depth_init": 5.0,
    "depth_refine": 119.0,
    "colour_init": 5.0,
    "gaussian_plane": 18.0,
    "splatting": 2.0,
    "total": 280.0,
}


def node_stages(model_path: str | os.PathLike) -> dict[str, str]:
    model = onnx.load(str(model_path), load_external_data=False)
    return {n.name: stage_of(n) or "other" for n in model.graph.node}


def _stage_for(name: str, stages: dict[str, str]) -> str:
    """Find the stage of a node name as ONNX Runtime reports it after its graph rewrites."""
    candidates = [name, name.split("/")[0]]
    for c in list(candidates):
        for suffix in ("_nchwc", "_token"):
            if suffix in c:
                candidates.append(c[: c.index(suffix)])
    for c in list(candidates):
        candidates.append("node_" + c)
    for c in candidates:
        if c in stages:
            return stages[c]
    return "other"


def ort_stage_profile(model_path: Path, feeds: dict, providers: list[str], threads: int | None, runs: int) -> dict[str, float]:
    """Milliseconds per stage from ONNX Runtime's profiler (median over `runs` profiled runs)."""
    stages = node_stages(model_path)
    with tempfile.TemporaryDirectory() as tmp:
        session = open_session(model_path, providers, threads, profile=str(Path(tmp) / "ort_profile"))
        session.run(None, feeds)  # warm-up, excluded below by run index
        for _ in range(runs):
            session.run(None, feeds)
        trace = session.end_profiling()
        events = json.loads(Path(trace).read_text())
    runs_ms = _regroup(events, stages)[1:]  # the first run was the warm-up
    keys = list(STAGES) + ["other"]
    return {k: statistics.median(r.get(k, 0.0) for r in runs_ms) for k in keys}


def _regroup(events: list[dict], stages: dict[str, str]) -> list[dict[str, float]]:
    """Split node events into runs by their timestamps against the model_run spans."""
    spans = sorted((e["ts"], e["ts"] + e["dur"]) for e in events if e.get("cat") == "Session" and e.get("name") == "model_run")
    runs: list[dict[str, float]] = [{} for _ in spans]
    for e in events:
        if e.get("cat") != "Node" or not e.get("name", "").endswith("_kernel_time"):
            continue
        for i, (a, b) in enumerate(spans):
            if a <= e["ts"] <= b:
                stage = _stage_for(e["name"][: -len("_kernel_time")], stages)
                runs[i][stage] = runs[i].get(stage, 0.0) + e["dur"] / 1000.0
                break
    return runs


def run_benchmark(
    size: str = "preview",
    backbone: str = "tiny",
    providers: list[str] | None = None,
    repeat: int = 5,
    threads: int | None = None,
    device: str = "cpu",
    checkpoint: str | None = None,
    model_path: str | os.PathLike | None = None,
    workdir: str | os.PathLike | None = None,
    progress=None,
    weights: str | os.PathLike | None = None,
    mast3r_blocks: tuple[int, int] | None = None,
) -> dict:
    """Time torch and ONNX Runtime on the same inputs and return the figures.

    Either export a model at `size` (a preset name) with `backbone` (untrained) or `checkpoint`,
    or benchmark an exported `model_path` against the torch model it records it was made from.
    With backbone "mast3r": its weights from `weights` (a MASt3R checkpoint), else random (seeded),
    at the checkpoint's depths or `mast3r_blocks` (encoder, decoder).
    """
    if repeat < 1:
        raise InferenceError("repeat must be at least 1")
    say = progress or (lambda text: None)
    if threads:
        torch.set_num_threads(threads)
    chosen = available_providers(providers)
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        if model_path is not None:
            model, path, preset = _recorded_model(Path(model_path), checkpoint)
        else:
            if size not in SIZE_PRESETS:
                raise InferenceError(f"unknown size '{size}' (allowed: {', '.join(SIZE_PRESETS)})")
            model, record = _model_for(size, backbone, checkpoint, weights, mast3r_blocks)
            path = Path(tmp) / "model.onnx"
            say(f"exporting the {size} model")
            export_onnx(model, path, weights=record)
            preset = size
        sizes = model.cfg.sizes
        arrays = example_inputs(sizes, model.needs_depth).arrays
        feeds = {n: arrays[n] for n in model.input_names}
        dev = torch.device(device)
        model = model.to(dev)
        inputs = [torch.from_numpy(feeds[n]).to(dev) for n in model.input_names]
        session = open_session(path, chosen, threads)
        torch_runs, ort_runs = _alternate_runs(model, inputs, session, feeds, repeat, say)
        del session
        say("profiling ONNX Runtime per stage")
        ort_ms = ort_stage_profile(path, feeds, chosen, threads, runs=min(repeat, 3))
    torch_ms = {k: statistics.median(r[k] for r in torch_runs) for k in list(STAGES) + ["total"]}
    # The profiled runs are slower than plain ones (and this machine's load varies): keep the
    # profiler's proportions and scale them to the median plain wall time.
    profile_ms = dict(ort_ms)
    ort_total = statistics.median(ort_runs)
    scale = ort_total / max(sum(profile_ms.values()), 1e-9)
    ort_ms = {k: v * scale for k, v in profile_ms.items()}
    ort_ms["total"] = ort_total
    return {
        "size": sizes.describe(),
        "preset": preset,
        "backbone": model.cfg.backbone.kind,
        **({"mast3r_blocks": [model.cfg.backbone.mast3r_encoder_blocks, model.cfg.backbone.mast3r_decoder_blocks],
            "mast3r_weights": str(weights) if weights else "random"} if model.cfg.backbone.kind == "mast3r" else {}),
        "torch_device": device,
        "device": describe(torch.device(device)),
        "providers": chosen,
        "threads": threads or torch.get_num_threads(),
        "repeat": repeat,
        "torch_ms": {k: round(v, 2) for k, v in torch_ms.items()},
        "ort_ms": {k: round(v, 2) for k, v in ort_ms.items()},
        "ort_profile_ms": {k: round(v, 2) for k, v in profile_ms.items()},
        "ort_total_runs_ms": [round(v, 2) for v in ort_runs],
        "torch_total_runs_ms": [round(r["total"], 2) for r in torch_runs],
        "speedup": round(torch_ms["total"] / ort_ms["total"], 3),
        "paper_ms_rtx3090": PAPER_MS,
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(), "cpus": os.cpu_count()},
        "note": "ort_ms.total is wall time; ort_ms stages are the profiler's kernel times (ort_profile_ms) scaled to sum to it",
    }


def _recorded_model(path: Path, checkpoint: str | None):
    """An exported model, the torch model it records it was made from and its size preset's name."""
    from inference.model.checkpoint import model_from_record
    from inference.runtime import read_model_info

    info = read_model_info(open_session(path, ["CPUExecutionProvider"]), path)
    model = model_from_record(info.config, info.weights, checkpoint)
    preset = next((k for k in SIZE_PRESETS if Sizes.preset(k) == info.config.sizes), "custom")
    return model, path, preset


def _alternate_runs(model, inputs: list, session, feeds: dict, repeat: int, say) -> tuple[list[dict[str, float]], list[float]]:
    """Torch (per-stage ms) and ONNX Runtime (wall ms) in turn, after one warm-up run of each."""
    torch_runs: list[dict[str, float]] = []
    ort_runs: list[float] = []
    with torch.no_grad():
        model.timed(*inputs)  # warm-up
        session.run(None, feeds)
        for i in range(repeat):
            say(f"run {i + 1}/{repeat}")
            torch_runs.append(model.timed(*inputs)[1])
            time.sleep(0.05)  # let either side's idle worker threads park before the other runs
            start = time.perf_counter()
            session.run(None, feeds)
            ort_runs.append((time.perf_counter() - start) * 1000.0)
            time.sleep(0.05)
    return torch_runs, ort_runs


def _model_for(size: str, backbone: str, checkpoint: str | None, weights=None, mast3r_blocks=None):
    sizes = Sizes.preset(size)
    if weights:
        from inference.model.checkpoint import backbone_weights_record, build_with_weights, seed_record

        model, _ = build_with_weights(ModelConfig.for_backbone(backbone, sizes), weights)
        return model, seed_record(0, backbone_weights_record(weights))
    if not checkpoint:
        cfg = ModelConfig.for_backbone(backbone, sizes)
        if mast3r_blocks:
            cfg.backbone.mast3r_encoder_blocks, cfg.backbone.mast3r_decoder_blocks = mast3r_blocks
        return build_model(cfg), None
    from inference.model.checkpoint import checkpoint_record, load_checkpoint

    model = load_checkpoint(checkpoint)
    if model.cfg.sizes != sizes:
        raise InferenceError(f"{checkpoint}: the checkpoint is configured for sizes {model.cfg.sizes.describe()}, not '{size}'")
    return model, checkpoint_record(checkpoint)


def format_table(result: dict) -> str:
    sizes = ", ".join(f"{k} {v}" for k, v in result["size"].items())
    backbone = result["backbone"]
    if "mast3r_blocks" in result:
        backbone += f" ({result['mast3r_blocks'][0]} encoder + {result['mast3r_blocks'][1]} decoder blocks, weights: {result['mast3r_weights']})"
    rows = [f"Splat-SAP pipeline at {result['preset']} sizes ({sizes}), backbone {backbone}, ONNX Runtime on {', '.join(result['providers'])}"]
    rows.append(f"{'stage':<18}{'torch ms':>12}{'ORT ms':>12}{'paper ms':>12}")
    for k in list(STAGES) + ["other", "total"]:
        if k not in result["ort_ms"] and k not in result["torch_ms"]:
            continue
        t = result["torch_ms"].get(k)
        o = result["ort_ms"].get(k)
        p = result["paper_ms_rtx3090"].get(k)
        rows.append(f"{k:<18}{'' if t is None else f'{t:.1f}':>12}{'' if o is None else f'{o:.1f}':>12}{'' if p is None else f'{p:.0f}':>12}")
    rows.append(f"speedup (torch total / ORT total): {result['speedup']:.2f}x")
    return "\n".join(rows)


def to_json(result: dict) -> str:
    return json.dumps(result, default=lambda o: o.item() if isinstance(o, np.generic) else str(o))
