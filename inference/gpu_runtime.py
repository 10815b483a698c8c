"""The live view in torch, on a GPU: stage 1 once per frame set, the view once per viewer, each captured
as a CUDA graph once it is compiled (the ONNX Runtime path, inference.runtime.split, stays torch-free).

`rig live --device cuda` and `rig model render --device cuda` use it; `benchmarks/gpu_check.py` times
it. It runs the torch checkpoint the ONNX model was exported from, at a size preset of its own
choosing: no weight depends on the sizes (the networks are convolutions and attention over tokens),
so the shipped preview-size checkpoint runs at the paper's sizes (512x288 / 1024x576 -> 1280x720).

    from inference.gpu_runtime import TorchLivePipeline, parity
    pipe = TorchLivePipeline("models/splat-sap-preview.onnx", device="cuda", size="paper")
    pipe.warm()                       # one eager run, then the graphs are built in a background thread
    feeds = pipe.source_feeds(left_rgb, right_rgb, left_cam, right_cam)   # numpy/cv2, then uploaded
    s1 = pipe.stage1(feeds)           # once per set; pipe.stage1_ms (CUDA-synchronised)
    view = pipe.render(s1, feeds, target_cam)   # per viewer: .image_uint8(), .image, .depth, .ms; pipe.view_ms
    pipe.graphs                       # "compiling" (eager frames meanwhile), "compiled", "eager",
                                      # "compiled, no CUDA graphs (...)" (capture failed: Inductor's
                                      # kernels without graphs), "eager (compile failed: ...)" or
                                      # "eager (graph failed: ...)"
    pipe.wait_compiled(timeout=300)   # True once the graphs serve the calls
    parity("models/splat-sap-preview.onnx", "cuda", "paper")   # max |runtime - torch CPU reference|

The exact API the GPU check builds on:
- `TorchLivePipeline(model=None, device="cuda", size="paper", *, compile=True, compiler=None,
  tf32=False, check_tolerance=1e-3)`: `model` an M.onnx (its checkpoint: M.pt beside it, else the
  one its metadata records), a checkpoint M.pt, or None (the shipped model); `size` a preset name
  (paper, preview, test), a `Sizes`, or None (the checkpoint's own). `compile=False`: eager only.
  `compiler(fn) -> fn` replaces the runtime's own (Inductor with frozen weights, then plain
  Inductor: pass None to measure what the live view runs; `lambda f: f` captures the eager kernels
  in CUDA graphs without Inductor). `tf32`: let cuDNN and matmuls round to TF32
  (faster, but not within 1e-3 of the CPU reference: off by default).
- `.warm(background=True)`, `.wait_compiled(timeout) -> bool`, `.graphs -> str`,
  `.compile_s` (seconds the graphs took to build, None before).
- `.synthetic() -> (feeds, target_K, target_pose)`: `rig model check`'s synthetic inputs on the device.
- `.source_feeds(...)`, `.stage1(feeds) -> dict`, `.view(s1, feeds, target_K, target_pose) ->
  (image, depth)` numpy (1,3,H,W), (1,1,H,W); `.render(s1, feeds, camera) -> TorchView`.
- `.stage1_ms`, `.view_ms`: wall ms of the latest call, the device synchronised at both ends.
- `.runtime_status()` (also `.describe()`): what `/status` says of the runtime ({"kind": "torch", "device", "gpu", "graphs", ...}).
- `parity(model, device, size, *, compile=False, seed=0, timeout=600) -> dict` of max abs diffs.

How the graphs are made: the two stage functions are compiled with `torch.compile` (Inductor,
`freezing` on: the weights become constants folded into the kernels; plain Inductor if freezing
fails; the per-frame geometry builds no tensor from host values, which a capture could not hold), run
twice on the device (kernels load, cuDNN picks its algorithms), then captured into a
`torch.cuda.CUDAGraph` each, reading and writing static buffers: a call copies its inputs into them,
replays the graph and copies the outputs out (a later replay overwrites them). That is what
`mode="reduce-overhead"` does, minus its per-thread graph trees: a graph captured here in the
background thread replays from the live engine's model thread. The compile runs beside eager
frames; the capture itself holds the device lock (milliseconds), as every call does, because a
capture must not see another thread's synchronisation. The compiled graph is then checked against
the eager functions on the synthetic inputs: over `check_tolerance` in the image, it is not used.
A capture that fails leaves the compiled functions serving without graphs; any other failure
(compile, the check, a later replay) leaves the runtime eager. Either is one warning in the log.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from calibration.camera import CameraModel
from inference.config import ModelConfig, Sizes
from inference.device import describe as describe_device, resolve_device, synchronize
from inference.errors import InferenceError
from inference.model.checkpoint import file_digest, load_checkpoint, load_weights, model_from_record
from inference.model.pipeline import STAGE1_OUTPUT_NAMES, SplatSAP, build_model
from inference.runtime.metadata import read_file_metadata
from inference.runtime.preprocess import InputPreparer, intrinsics, pose
from inference.runtime.split import target_matrix
from inference.runtime.synthetic import example_inputs

log = logging.getLogger(__name__)

SOURCE_NAMES = ("left_image", "right_image", "left_K", "right_K", "left_pose", "right_pose")
TARGET_NAMES = ("target_K", "target_pose")
LIVE_SIZE = "paper"  # what `rig live --device cuda` runs at unless told
PARTS = ("stage1", "view")


# --- the model cut in two (what inference/export.py cuts the ONNX graph into) ------------------------

def stage1_forward(model: SplatSAP, left_image, right_image, left_K, right_K, left_pose, right_pose):
    """The stage-1 tensors (STAGE1_OUTPUT_NAMES, in order), as SplatSAP.run computes them."""
    _, _, stage1 = model.run_stage1(left_image, right_image, left_K, right_K, left_pose, right_pose)
    return tuple(stage1[n] for n in STAGE1_OUTPUT_NAMES)


def view_forward(model: SplatSAP, points_left, points_right, opacity_left, opacity_right,
                 left_image, right_image, left_K, right_K, left_pose, right_pose, target_K, target_pose):
    """depth_init onwards: (image clamped to [0, 1], depth) of the target view."""
    stage1 = dict(zip(STAGE1_OUTPUT_NAMES, (points_left, points_right, opacity_left, opacity_right)))
    out = model.run_view(stage1, left_image, right_image, left_K, right_K, left_pose, right_pose, target_K, target_pose)
    return out["image"], out["depth"]


# --- which checkpoint, at which size ----------------------------------------------------------------

def checkpoint_model(model: str | os.PathLike | None) -> tuple[SplatSAP, Path]:
    """The torch model (on the CPU) behind `model`: an M.onnx (M.pt beside it, else the checkpoint its
    metadata records, or the seed of an untrained export), a checkpoint, or None (the shipped one).
    Returns (model, the file it came from). One-line InferenceError otherwise."""
    if model is None:
        from inference.runtime.shipped import shipped_checkpoint

        path = shipped_checkpoint()
        return load_checkpoint(path), path
    path = Path(model)
    if not path.is_file():
        raise InferenceError(f"{path}: no such model file")
    if path.suffix != ".onnx":
        return load_checkpoint(path), path
    meta = read_file_metadata(path)
    if meta.get("splat_sap.format") != "1" or "splat_sap.config" not in meta:
        raise InferenceError(f"{path}: not a Splat-SAP model (no splat_sap metadata; export it with `rig model export`)")
    part = meta.get("splat_sap.part")
    if part is not None:
        raise InferenceError(f"{path}: the {part} part of a Splat-SAP model, not a whole one; give the model itself "
                             f"({path.name.replace(f'.{part}.onnx', '.onnx')})")
    cfg = ModelConfig.from_json(meta["splat_sap.config"], saved=True)
    record = meta.get("splat_sap.weights", "")
    stem = path.stem[: -len(".fp16")] if path.stem.endswith(".fp16") else path.stem
    beside = path.with_name(stem + ".pt")
    if beside.is_file():
        import json

        try:
            digest = json.loads(record).get("sha256")
        except (json.JSONDecodeError, AttributeError):
            digest = None
        if digest and file_digest(beside) != digest:
            raise InferenceError(f"{beside}: not the checkpoint {path.name} was exported from (sha256 differs); "
                                 f"give --model {beside} to run that checkpoint")
        return load_checkpoint(beside), beside
    source = model_from_record(cfg, record)  # the recorded checkpoint (or the shipped one by digest), or the seed
    return source, path


def at_size(model: SplatSAP, size: str | Sizes | None, origin: Path) -> SplatSAP:
    """The same weights in a model built at another size preset (no weight depends on the sizes)."""
    if size is None:
        return model
    sizes = Sizes.preset(size) if isinstance(size, str) else size
    if sizes == model.cfg.sizes:
        return model
    cfg = ModelConfig.from_dict(model.cfg.to_dict())
    cfg.sizes = sizes
    resized = build_model(cfg, seed=None)
    load_weights(resized, model.state_dict(), origin, strict=True)
    return resized.eval()


def set_tf32(on: bool) -> None:
    """Whether cuDNN convolutions and matmuls may round float32 to TF32 (process-wide, as torch has it).
    Convolutions do by default on Ampere and later: off, the GPU computes what the CPU does to ~1e-6."""
    mode = "tf32" if on else "ieee"
    cudnn = torch.backends.cudnn
    if hasattr(getattr(cudnn, "conv", None), "fp32_precision"):  # torch >= 2.9: the legacy flags must not be mixed in
        cudnn.conv.fp32_precision = mode
        cudnn.rnn.fp32_precision = mode
        torch.backends.cuda.matmul.fp32_precision = mode
    else:
        cudnn.allow_tf32 = on
        torch.backends.cuda.matmul.allow_tf32 = on


# --- outputs ----------------------------------------------------------------------------------------

@dataclass
class TorchView:
    """A rendered view (as inference.runtime.NovelView): the uint8 image is made on the device (a
    quarter of the float image's bytes cross the bus); the float image and depth stay there until read."""
    image_u8: np.ndarray  # (H, W, 3) uint8 RGB
    image_device: torch.Tensor  # (3, H, W) float in [0, 1]
    depth_device: torch.Tensor  # (H, W) metres
    ms: float = 0.0

    def image_uint8(self) -> np.ndarray:
        return self.image_u8

    @property
    def image(self) -> np.ndarray:
        return np.ascontiguousarray(self.image_device.permute(1, 2, 0).cpu().numpy())

    @property
    def depth(self) -> np.ndarray:
        return self.depth_device.cpu().numpy()


def to_uint8(image: torch.Tensor) -> torch.Tensor:
    """(3, H, W) in [0, 1] to (H, W, 3) uint8, rounded as NovelView.image_uint8 rounds."""
    return (image * 255.0 + 0.5).clamp(0.0, 255.0).to(torch.uint8).permute(1, 2, 0).contiguous()


class _Graph:
    """One stage function captured as a CUDA graph over static input and output buffers."""

    def __init__(self, fn: Callable, example: tuple[torch.Tensor, ...]):
        device = example[0].device
        self.inputs = tuple(t.clone() for t in example)
        with torch.cuda.device(device), torch.no_grad():
            # Warm-up on a side stream before capture, as torch.cuda.graphs asks: kernels load and
            # cuDNN chooses its algorithms outside the graph.
            stream = torch.cuda.Stream(device=device)
            stream.wait_stream(torch.cuda.current_stream(device))
            with torch.cuda.stream(stream):
                for _ in range(2):
                    fn(*self.inputs)
            torch.cuda.current_stream(device).wait_stream(stream)
            self.graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.graph):
                self.outputs = tuple(fn(*self.inputs))

    def __call__(self, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        for buf, a in zip(self.inputs, args):
            buf.copy_(a)
        self.graph.replay()
        return tuple(o.clone() for o in self.outputs)


class TorchLivePipeline:
    """The SplitPipeline interface (LiveEngine takes either) over the torch model on a device."""

    def __init__(self, model: str | os.PathLike | None = None, device: str | torch.device = "cuda", size: str | Sizes | None = LIVE_SIZE,
                 *, compile: bool = True, compiler: Optional[Callable[[Callable], Callable]] = None, tf32: bool = False,
                 check_tolerance: float = 1e-3, sync_timing: bool = True):
        self.device = device if isinstance(device, torch.device) else resolve_device(str(device))
        net, origin = checkpoint_model(model)
        if net.needs_depth:
            raise InferenceError(f"{model or origin}: this model uses the oracle backbone (ground-truth depth as input); "
                                 "the live view needs a model that sees only the images")
        net = at_size(net, size, origin)
        self.path = Path(model) if model is not None else origin
        self.checkpoint = origin
        self.cfg = net.cfg
        self.sizes = net.cfg.sizes
        self.tf32 = bool(tf32)
        if self.device.type == "cuda":
            set_tf32(self.tf32)
            torch.backends.cudnn.benchmark = True  # fixed sizes: the fastest algorithm per layer, chosen once
        self.net = net.to(self.device).eval()
        for p in self.net.parameters():
            p.requires_grad_(False)
        self.prepare = InputPreparer(self.sizes, False)
        self.check_tolerance = float(check_tolerance)
        self.sync_timing = sync_timing
        self._compile = bool(compile)
        self._compiler = compiler
        self._lock = threading.RLock()  # every device call and the capture (see the module doc)
        self._graphs: Optional[dict[str, Callable]] = None
        self._state = "compile not started" if self._compile else "eager"
        self._state_changed = threading.Condition()
        self._thread: Optional[threading.Thread] = None
        self._warned = False
        self.compile_s: Optional[float] = None
        self.stage1_ms = 0.0
        self.view_ms = 0.0

    # --- the eager stage functions ---------------------------------------------------------------
    def _stage1_eager(self, *sources):
        return stage1_forward(self.net, *sources)

    def _view_eager(self, *args):
        return view_forward(self.net, *args)

    # --- graphs ------------------------------------------------------------------------------------
    @property
    def graphs(self) -> str:
        return self._state

    def warm(self, background: bool = True) -> "TorchLivePipeline":
        """One eager run on the synthetic inputs (memory, cuDNN's choices: the first viewer does not
        pay them), then the graphs are built: in a thread (`background`), eager calls meanwhile."""
        if self.device.type == "cuda":  # the CPU has nothing to set up that a first run would do
            feeds, target_K, target_pose = self.synthetic()
            with self._lock, torch.no_grad():
                s1 = self._stage1_eager(*self._sources(feeds))
                self._view_eager(*s1, *self._sources(feeds), target_K, target_pose)
                synchronize(self.device)
        if self._compile and self._thread is None and self._graphs is None and self._state == "compile not started":
            self._set_state("compiling")
            if background:
                self._thread = threading.Thread(target=self._build_graphs, name="gpu-graphs", daemon=True)
                self._thread.start()
            else:
                self._build_graphs()
        return self

    def wait_compiled(self, timeout: Optional[float] = None) -> bool:
        """Wait until the graphs are built or given up; True when they serve the calls."""
        with self._state_changed:
            self._state_changed.wait_for(lambda: self._state not in ("compiling",), timeout=timeout)
        return self._graphs is not None

    def _set_state(self, state: str) -> None:
        with self._state_changed:
            self._state = state
            self._state_changed.notify_all()

    def _compilers(self) -> list[tuple[str, Callable]]:
        """What to compile with, in turn until one works: the caller's compiler, else Inductor with
        its weights and constants frozen (folded into the kernels at compile time), then plain
        Inductor."""
        if self._compiler is not None:
            return [("given", self._compiler)]
        return [("inductor, frozen", lambda fn: torch.compile(fn, dynamic=False, options={"freezing": True})),
                ("inductor", lambda fn: torch.compile(fn, dynamic=False))]

    def _build_graphs(self) -> None:
        start = time.perf_counter()
        failure: Optional[BaseException] = None
        for name, compiler in self._compilers():
            try:
                graphs, captured = self._compile_with(compiler)
            except Exception as exc:  # torch.compile and capture raise many types: the next way, else eager
                log.info("gpu runtime: compiling (%s) failed: %s: %s", name, type(exc).__name__, exc)
                failure = exc
                continue
            self.compile_s = time.perf_counter() - start
            self._graphs = graphs
            self._set_state("compiled" if captured is True else f"compiled, no CUDA graphs ({captured})")
            if captured is not True:
                self._warn(f"CUDA graph capture failed, serving compiled frames without graphs ({captured})")
            return
        self._give_up("compile failed", failure)

    def _compile_with(self, compiler: Callable) -> tuple[dict[str, Callable], object]:
        """(the two parts, True if captured as CUDA graphs else why not); raises when compiling fails
        or the compiled image is over `check_tolerance` from the eager one."""
        stage1_fn, view_fn = compiler(self._stage1_eager), compiler(self._view_eager)
        feeds, target_K, target_pose = self.synthetic()
        sources = self._sources(feeds)
        # Compiling happens on the first calls, outside the lock: eager frames go on meanwhile.
        with torch.no_grad():
            s1 = tuple(t.clone() for t in stage1_fn(*sources))
            got = view_fn(*s1, *sources, target_K, target_pose)[0]
        graphs = {"stage1": _plain(stage1_fn), "view": _plain(view_fn)}
        captured: object = "no CUDA on the CPU"  # the compiled functions themselves (how the tests run this path)
        if self.device.type == "cuda":
            try:
                with self._lock, torch.no_grad():
                    captured_graphs = {"stage1": _Graph(stage1_fn, sources), "view": _Graph(view_fn, s1 + sources + (target_K, target_pose))}
                    got = captured_graphs["view"](*captured_graphs["stage1"](*sources), *sources, target_K, target_pose)[0]  # what replays give
                graphs, captured = captured_graphs, True
            except Exception as exc:  # the compiled functions still run, without graphs
                captured = _reason(exc)
        with self._lock, torch.no_grad():
            want = self._view_eager(*self._stage1_eager(*sources), *sources, target_K, target_pose)[0]
            diff = float((got - want).abs().max())
        if not diff <= self.check_tolerance:
            raise InferenceError(f"the compiled image differs from eager by {diff:.3g} (tolerance {self.check_tolerance:g})")
        return graphs, (True if self.device.type != "cuda" else captured)

    def _warn(self, line: str) -> None:
        if not self._warned:
            self._warned = True
            log.warning("gpu runtime: %s", line)

    def _give_up(self, what: str, exc: BaseException) -> None:
        self._graphs = None
        reason = _reason(exc)
        self._set_state(f"eager ({what}: {reason})")
        self._warn(f"{what}, serving eager frames ({reason})")

    def _run(self, part: str, eager: Callable, args: tuple) -> tuple[torch.Tensor, ...]:
        graphs = self._graphs
        if graphs is not None:
            try:
                return graphs[part](*args)
            except Exception as exc:  # a replay that fails: eager from now on, this call included
                self._give_up("graph failed", exc)
        return tuple(eager(*args))

    # --- the SplitPipeline interface --------------------------------------------------------------
    def _upload(self, array) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32)).to(self.device, non_blocking=False)

    def _sources(self, feeds: dict) -> tuple[torch.Tensor, ...]:
        missing = [n for n in SOURCE_NAMES if n not in feeds]
        if missing:
            raise InferenceError(f"missing model inputs: {', '.join(missing)}")
        return tuple(feeds[n] if isinstance(feeds[n], torch.Tensor) else self._upload(feeds[n]) for n in SOURCE_NAMES)

    def source_feeds(self, left, right, left_cam: CameraModel, right_cam: CameraModel, left_depth=None, right_depth=None) -> dict[str, torch.Tensor]:
        """The frame set's inputs on the device (undistorted and resized on the CPU, as ONNX Runtime's)."""
        try:
            arrays = self.prepare(left, right, left_cam, right_cam, left_cam)
        except InferenceError as exc:
            raise InferenceError(f"{self.path}: {exc}") from None
        with self._lock:  # the engine prepares sets in its capture thread: never during a capture
            return {n: self._upload(arrays[n]) for n in SOURCE_NAMES}

    def target(self, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
        return intrinsics(camera, self.sizes.output), pose(camera)

    def synthetic(self, seed: int = 0) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
        """`rig model check`'s synthetic inputs at this size, on the device: (feeds, target_K, target_pose)."""
        arrays = example_inputs(self.sizes, False, seed).arrays
        return {n: self._upload(arrays[n]) for n in SOURCE_NAMES}, self._upload(arrays["target_K"]), self._upload(arrays["target_pose"])

    def stage1(self, feeds: dict) -> dict[str, torch.Tensor]:
        sources = self._sources(feeds)
        with self._lock, torch.no_grad():
            start = self._clock()
            out = self._run("stage1", self._stage1_eager, sources)
            self.stage1_ms = self._clock(start)
        return dict(zip(STAGE1_OUTPUT_NAMES, out))

    def _view(self, stage1_out: dict, feeds: dict, target_K, target_pose) -> tuple[torch.Tensor, torch.Tensor, float]:
        missing = [n for n in STAGE1_OUTPUT_NAMES if n not in stage1_out]
        if missing:
            raise InferenceError(f"missing model inputs: {', '.join(missing)}")
        target = tuple(t if isinstance(t, torch.Tensor) else self._upload(target_matrix(t, n, name)) for t, n, name in
                       ((target_K, 3, "target_K"), (target_pose, 4, "target_pose")))
        args = tuple(stage1_out[n] for n in STAGE1_OUTPUT_NAMES) + self._sources(feeds) + target
        with self._lock, torch.no_grad():
            start = self._clock()
            image, depth = self._run("view", self._view_eager, args)
            ms = self.view_ms = self._clock(start)
        return image, depth, ms

    def view(self, stage1_out: dict, feeds: dict, target_K, target_pose) -> tuple[np.ndarray, np.ndarray]:
        """(image (1,3,H,W), depth (1,1,H,W)) as numpy, as SplitPipeline.view returns them."""
        image, depth, _ = self._view(stage1_out, feeds, target_K, target_pose)
        return image.cpu().numpy(), depth.cpu().numpy()

    def render(self, stage1_out: dict, feeds: dict, target_cam: CameraModel) -> TorchView:
        image, depth, ms = self._view(stage1_out, feeds, *self.target(target_cam))
        with torch.no_grad():
            u8 = to_uint8(image[0]).cpu().numpy()
        return TorchView(u8, image[0], depth[0, 0], ms)

    def _clock(self, start: Optional[float] = None) -> float:
        if self.sync_timing:
            synchronize(self.device)
        now = time.perf_counter()
        return now if start is None else (now - start) * 1000.0

    def runtime_status(self) -> dict:
        """The runtime as /status and --json say it (rig.live.api.runtime_of)."""
        out = {"kind": "torch", **describe_device(self.device), "graphs": self._state, "tf32": self.tf32,
               "checkpoint": str(self.checkpoint), "sizes": self.sizes.describe(), "backbone": self.cfg.backbone.kind}
        if self.compile_s is not None:
            out["compile_s"] = round(self.compile_s, 1)
        return out

    describe = runtime_status


def _reason(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"[:300]


def _plain(fn: Callable) -> Callable:
    return lambda *args: tuple(fn(*args))


def parity(model: str | os.PathLike | None = None, device: str = "cuda", size: str | Sizes | None = LIVE_SIZE, *, compile: bool = False,
           seed: int = 0, timeout: float = 600.0, compiler: Optional[Callable] = None) -> dict:
    """The runtime (stage 1 then view, on `device`, eager or through its graphs) against the whole
    model's plain forward in torch on the CPU, on `rig model check`'s synthetic inputs: the largest
    absolute differences of the image (in [0, 1]) and the depth (metres)."""
    pipe = TorchLivePipeline(model, device, size, compile=compile, compiler=compiler)
    pipe.warm(background=False)
    if compile and not pipe.wait_compiled(timeout):
        raise InferenceError(f"parity: the graphs were not built ({pipe.graphs})")
    arrays = example_inputs(pipe.sizes, False, seed).arrays
    reference = build_model(pipe.cfg, seed=None)
    load_weights(reference, {k: v.cpu() for k, v in pipe.net.state_dict().items()}, pipe.checkpoint)
    reference.eval()
    with torch.no_grad():
        want_image, want_depth = reference(*[torch.from_numpy(arrays[n]) for n in reference.input_names])
    feeds = {n: arrays[n] for n in SOURCE_NAMES}
    image, depth = pipe.view(pipe.stage1(feeds), feeds, arrays["target_K"], arrays["target_pose"])
    return {"device": str(pipe.device), "sizes": pipe.sizes.describe(), "graphs": pipe.graphs,
            "max_abs_diff_image": float(np.abs(image - want_image.numpy()).max()),
            "max_abs_diff_depth": float(np.abs(depth - want_depth.numpy()).max()),
            "stage1_ms": round(pipe.stage1_ms, 2), "view_ms": round(pipe.view_ms, 2)}
