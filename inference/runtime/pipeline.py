"""The live pipeline: ONNX Runtime and numpy only (this module never imports torch).

    from inference.runtime import NovelViewPipeline
    pipe = NovelViewPipeline("model.onnx")            # providers: TensorRT, CUDA, CPU as installed
    view = pipe.render(left_rgb, right_rgb, left_cam, right_cam, target_cam)
    view.image  # (H, W, 3) float32 in [0, 1] at the model's output size
    view.depth  # (H, W) float32 metres, 0 where nothing was rendered

Frames are RGB arrays (uint8, or float in [0, 1]) at their camera's calibrated size; cameras are
`calibration.camera.CameraModel`s in one world frame. Frames are undistorted and resized to the
model's fine size here (tables cached per camera). The target camera may have any size: the view
is rendered as its pinhole at the model's output size (aspect kept by the intrinsics).
"""
from __future__ import annotations

import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

from calibration.camera import CameraModel
from inference.config import ModelConfig
from inference.errors import InferenceError
from inference.runtime.metadata import read_file_metadata
from inference.runtime.preprocess import InputPreparer

PREFERRED_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider")


@dataclass
class NovelView:
    image: np.ndarray  # (H, W, 3) float32 RGB in [0, 1]
    depth: np.ndarray  # (H, W) float32 metres
    ms: float = 0.0  # wall time of the model run

    def image_uint8(self) -> np.ndarray:
        return np.clip(self.image * 255.0 + 0.5, 0, 255).astype(np.uint8)


def available_providers(requested: list[str] | tuple[str, ...] | None = None) -> list[str]:
    """Execution providers to use, best first, among those this onnxruntime build has."""
    have = ort.get_available_providers()
    if requested:
        missing = [p for p in requested if p not in have]
        if missing:
            raise InferenceError(f"execution provider(s) {', '.join(missing)} not available (this onnxruntime has: {', '.join(have)})")
        return list(requested)
    return [p for p in PREFERRED_PROVIDERS if p in have]


PRECISIONS = ("fp32", "fp16")


def model_precision(path: str | os.PathLike) -> str:
    """The precision the model was exported in ("fp32" or "fp16"), from the metadata written at
    export; "fp32" for a model without it (a foreign model is never run in reduced precision)."""
    precision = read_file_metadata(path).get("splat_sap.precision", "fp32")
    if precision not in PRECISIONS:
        raise InferenceError(f"{path}: unknown precision {precision!r} in its metadata (this program runs {', '.join(PRECISIONS)})")
    return precision


def provider_options(providers: list[str], model_path: Path, precision: str) -> list:
    """The providers as ONNX Runtime takes them, with their options.

    TensorRT may compute in float16 only for a model exported as fp16: with trt_fp16_enable it is
    free to run any layer in float16, and an fp32 model's projections (pixel coordinates around
    1000 round to 0.5 px in float16) and z-buffer must stay float32. The switch is always written
    out rather than left to TensorRT's default. For an fp16 model, layer normalisation stays
    float32, as at export.
    """
    if precision not in PRECISIONS:
        raise InferenceError(f"unknown model precision {precision!r} (this program runs {', '.join(PRECISIONS)})")
    half = "True" if precision == "fp16" else "False"
    out = []
    for p in providers:
        if p == "TensorrtExecutionProvider":
            cache = model_path.with_name(model_path.name + ".trt-cache")
            out.append((p, {"trt_engine_cache_enable": "True", "trt_engine_cache_path": str(cache), "trt_fp16_enable": half, "trt_layer_norm_fp32_fallback": half}))
        else:
            out.append(p)
    return out


@dataclass
class ModelInfo:
    config: ModelConfig
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    precision: str
    weights: str
    metadata: dict[str, str] = field(default_factory=dict)

    @property
    def needs_depth(self) -> bool:
        return "left_depth" in self.inputs


def read_model_info(session: ort.InferenceSession, path: Path) -> ModelInfo:
    meta = session.get_modelmeta().custom_metadata_map
    if meta.get("splat_sap.format") != "1" or "splat_sap.config" not in meta:
        raise InferenceError(f"{path}: not a Splat-SAP model (no splat_sap metadata; export it with `rig model export`)")
    cfg = ModelConfig.from_json(meta["splat_sap.config"], saved=True)
    return ModelInfo(
        cfg,
        tuple(meta["splat_sap.inputs"].split(",")),
        tuple(meta["splat_sap.outputs"].split(",")),
        meta.get("splat_sap.precision", "fp32"),
        meta.get("splat_sap.weights", ""),
        dict(meta),
    )


def _omp_threads() -> int | None:
    """OMP_NUM_THREADS, where it is set to a count: the threads the user (or a scheduler sharing the
    machine among processes) gives this process. ONNX Runtime does not read it; left to itself it
    runs a spinning thread per core, which on cores other processes use spins against them."""
    value = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(value) if value.isdigit() and int(value) > 0 else None


def open_session(path: str | os.PathLike, providers: list[str] | None = None, threads: int | None = None, profile: str | None = None,
                 spinning: bool = True) -> ort.InferenceSession:
    """An ONNX Runtime session; `profile` is a file prefix that turns ONNX Runtime's profiler on.
    `spinning=False`: idle intra-op threads sleep instead of busy-waiting for the next parallel
    section (for sessions that share the cores with other work)."""
    path = Path(path)
    if not path.is_file():
        raise InferenceError(f"{path}: no such model file")
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # ONNX Runtime logs a failed load (a truncated data file, a corrupt graph) to stderr itself, in
    # several lines, before it raises; the exception below says it in one, so only fatal logs print
    opts.log_severity_level = 4
    threads = threads or _omp_threads()
    if threads:
        opts.intra_op_num_threads = threads
    if not spinning:
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if profile:
        opts.enable_profiling = True
        opts.profile_file_prefix = str(profile)
    chosen = available_providers(providers)
    precision = model_precision(path) if "TensorrtExecutionProvider" in chosen else "fp32"  # only TensorRT's options depend on it
    try:
        # by its real path: ONNX Runtime looks for a model's data file (`--shared-data`) in the folder
        # of the path it is given and refuses one outside the model file's real folder, so a link to
        # a model (the installed package's models/ is one in a source tree) reads the data beside the file
        return ort.InferenceSession(str(path.resolve()), sess_options=opts, providers=provider_options(chosen, path, precision))
    except Exception as exc:  # onnxruntime raises its own exception types for corrupt or unsupported files
        # a model whose weights are in a data file beside it (`rig model export --shared-data`),
        # copied without it: ONNX Runtime names the file it looked for
        missing = re.search(r'External data path does not exist: "([^"]+)"', str(exc))
        if missing:
            raise InferenceError(f"{path}: its weights file {Path(missing.group(1)).name} is not beside it; copy the "
                                 f"model's files together (M.onnx, its parts and M.onnx.*.data)") from None
        if re.search(r"External initializer: .* out of bounds or can not be read in full", str(exc)):
            # the data file beside it is shorter than the graph says (a copy cut short, another export's)
            data = sorted(p.name for p in path.resolve().parent.glob(path.name + ".*.data"))
            raise InferenceError(f"{path}: its weights file {data[0] if data else path.name + '.*.data'} is shorter than the model "
                                 "needs (cut short, or from another export); copy the model's files together again") from None
        if path.suffix == ".pt":
            raise InferenceError(f"{path}: a checkpoint, not an ONNX model; export it first "
                                 f"(rig model export --checkpoint {path} -o MODEL.onnx)") from None
        raise InferenceError(f"{path}: ONNX Runtime cannot load it ({str(exc).splitlines()[0]})") from None


class NovelViewPipeline:
    """Two synced frames + calibration + a viewpoint in, a novel view and its depth out."""

    def __init__(self, path: str | os.PathLike | None = None, providers: list[str] | None = None, threads: int | None = None):
        """`path`: an exported model; None: the shipped trained model (inference.runtime.shipped)."""
        if path is None:
            from inference.runtime.shipped import shipped_onnx

            path = shipped_onnx()
        self.path = Path(path)
        self.session = open_session(self.path, providers, threads)
        self.info = read_model_info(self.session, self.path)
        part = self.info.metadata.get("splat_sap.part")
        if part is not None:  # M.stage1.onnx or M.view.onnx: half of the graph, not a view renderer
            whole = self.path.name.replace(f".{part}.onnx", ".onnx")
            raise InferenceError(f"{self.path}: the {part} part of a Splat-SAP model, not a whole one; give the model itself ({whole})")
        self.sizes = self.info.config.sizes
        names = tuple(i.name for i in self.session.get_inputs())
        if names != self.info.inputs:
            raise InferenceError(f"{self.path}: inputs {names} do not match its metadata {self.info.inputs}")
        self.prepare = InputPreparer(self.sizes, self.info.needs_depth)

    @property
    def providers(self) -> list[str]:
        return self.session.get_providers()

    def run(self, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Run the model on prepared inputs; returns (image (1,3,H,W), depth (1,1,H,W))."""
        missing = [n for n in self.info.inputs if n not in feeds]
        if missing:
            raise InferenceError(f"missing model inputs: {', '.join(missing)}")
        image, depth = self.session.run(list(self.info.outputs), {n: feeds[n] for n in self.info.inputs})
        return image, depth

    def render(self, left, right, left_cam: CameraModel, right_cam: CameraModel, target_cam: CameraModel, left_depth=None, right_depth=None) -> NovelView:
        try:
            feeds = self.prepare(left, right, left_cam, right_cam, target_cam, left_depth, right_depth)
        except InferenceError as exc:
            raise InferenceError(f"{self.path}: {exc}") from None
        start = time.perf_counter()
        image, depth = self.run(feeds)
        ms = (time.perf_counter() - start) * 1000.0
        return NovelView(np.ascontiguousarray(image[0].transpose(1, 2, 0)), depth[0, 0], ms)

    def describe(self) -> dict:
        return {
            "model": str(self.path),
            "providers": self.providers,
            "precision": self.info.precision,
            "weights": self.info.weights,
            "backbone": self.info.config.backbone.kind,
            "sizes": self.sizes.describe(),
            "config": json.loads(self.info.config.to_json()),
        }
