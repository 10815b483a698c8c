"""`rig live` put together: the rig's calibration and source cameras, the model, the frame source,
the engine, the optional video of the output, and the server."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from calibration.camera import CalibrationError, RigCalibration
from rig.errors import ConfigError
from rig.live.engine import LiveEngine
from rig.live.source import ReplaySource, SessionSource


def source_cameras(cfg) -> tuple[str, str]:
    left, right = cfg.by_role("left"), cfg.by_role("right")
    if left is None or right is None:
        missing = " and ".join(r for r, c in (("left", left), ("right", right)) if c is None)
        raise ConfigError(f"{cfg.path or 'config'}: live needs a camera with role = \"{missing}\" (the stereo pair the model renders from)")
    return left.name, right.name


def rig_calibration(cfg, calibration: Optional[Path], replay: Optional[ReplaySource], notes: Optional[list] = None) -> RigCalibration:
    """The calibration the model renders with: --calibration, else the config's, else a replayed
    take's copy, else (simulated cameras only) their exact models."""
    path = calibration or (cfg.resolve(cfg.calibration) if cfg.calibration else None)
    if path is not None:
        try:
            return RigCalibration.load(path)
        except FileNotFoundError:
            raise ConfigError(f"--calibration: {path}: no such file") from None
        except (CalibrationError, ValueError, KeyError) as exc:
            raise ConfigError(f"--calibration: {path}: not a calibration file ({exc})") from None
    if replay is not None:  # the take's own calibration copy (a simulated take: its exact cameras)
        seq = replay.sequence
        if seq.calibration is not None:
            return seq.calibration
        if seq.ground_truth is not None:
            return seq.ground_truth
        raise ConfigError(f"--replay: {seq.root} has no calibration.json (give --calibration)")
    from rig.truth import take_truth, truth_cameras

    truth = take_truth(cfg)
    if truth:
        if notes is not None:
            notes.append("no calibration named; the simulated cameras render with their exact models")
        return RigCalibration.from_dict({"version": 1, "cameras": truth_cameras(truth)})
    raise ConfigError(f"{cfg.path or 'config'}: no calibration (set rig.calibration, or give --calibration; `rig calibrate run` makes one)")


def check_frame_sizes(cfg, rig: RigCalibration, sources: tuple[str, str], replay: Optional[ReplaySource],
                      calibration: Optional[Path]) -> None:
    """The calibration must be of the frames the model will get, at their size: a replayed take's
    (a take of another rig, or at another size), or the rig's cameras' when --calibration names a
    file (the config's own rig.calibration is checked when the config loads). Else every frame set
    would fail in preprocessing while the server runs."""
    if replay is None and calibration is None:
        return
    for name in sources:
        if replay is not None:
            entry = replay.sequence.meta.camera(name)
            size, where = (int(entry.width), int(entry.height)), f"in the take {replay.sequence.root}"
        else:
            cam = cfg.camera(name)
            size, where = (int(cam.width), int(cam.height)), f"in {cfg.path or 'the config'}"
        model = rig[name]
        if (model.width, model.height) != size:
            source = f"--calibration {calibration}" if calibration is not None else (
                f"rig.calibration {cfg.resolve(cfg.calibration)}" if cfg.calibration else "the take's calibration")
            raise ConfigError(f"camera '{name}' is {size[0]}x{size[1]} {where} but {model.width}x{model.height} in {source}; "
                              "give the calibration of the rig that recorded the frames (--calibration)")


DEVICES = ("cpu", "cuda")


def parse_device(text: str) -> str:
    """--device: cpu (ONNX Runtime, the default), cuda or cuda:N (the torch GPU runtime). Checked
    without torch: a wrong word is one line before anything is opened."""
    t = (text or "cpu").strip().lower()
    kind, _, index = t.partition(":")
    if kind not in DEVICES or (kind == "cpu" and index) or (index and not index.isdigit()):
        raise ConfigError(f"--device: {text!r} is not a device (give cpu, cuda or cuda:N)")
    return t


def check_providers(providers) -> None:
    """--providers: each an ONNX Runtime execution provider this installation has (one line if not)."""
    if not providers:
        return
    import onnxruntime as ort

    known, have = ort.get_all_providers(), ort.get_available_providers()
    for p in providers:
        if p not in known:
            raise ConfigError(f"--providers: {p!r} is not an ONNX Runtime execution provider (this onnxruntime has: {', '.join(have)})")
        if p not in have:
            raise ConfigError(f"--providers: {p} is not in this onnxruntime {ort.__version__} (it has: {', '.join(have)}); "
                              "the CUDA and TensorRT providers come with the onnxruntime-gpu package (on a Jetson, NVIDIA's build)")


def gpu_runtime(device: str):
    """The torch GPU runtime module, imported here only (the CPU live path never loads torch), and
    the device checked: no torch, or no GPU, is one line."""
    try:
        from inference import gpu_runtime as module  # the one import of torch on the live path (tests/test_layering.py)
    except ImportError as exc:
        raise ConfigError(f"--device {device}: the GPU runtime needs PyTorch, which this installation lacks ({exc}); "
                          "run --device cpu (ONNX Runtime, also on a GPU with --providers)") from None
    module.resolve_device(device)  # InferenceError, one line: no CUDA in this torch, no GPU, no such index
    return module


# The scale search (most of stage 1's time on a CPU) runs on one frame set in this many; the sets
# between reuse its factor, which is the same on every set of a take (docs/live.md, "On a CPU").
SCALE_SEARCH_EVERY = 15


def open_model(path: Optional[Path], providers, threads, device: str = "cpu", size: Optional[str] = None, compile: bool = True):
    """The model as its two parts (stage 1 once per frame set, the view per viewer); default: the
    shipped trained model. `device` cpu: ONNX Runtime on `providers`; cuda: the torch runtime
    (inference.gpu_runtime) on the checkpoint behind the model, at `size` (default the paper's),
    its CUDA graphs built in the background while it serves eager frames."""
    if path is not None and not Path(path).is_file():
        raise ConfigError(f"--model: {path}: no such model file")
    if device != "cpu":
        module = gpu_runtime(device)
        model = module.TorchLivePipeline(path, device, size or module.LIVE_SIZE, compile=compile)
        return model.warm()
    from inference.runtime import SplitPipeline

    check_providers(providers)
    if path is None:
        from inference.runtime.pipeline import available_providers
        from inference.runtime.shipped import shipped_live_onnx, shipped_onnx

        # On a CPU the preview model draws 0.3-0.7 frames/s on 2 cores: the shipped model at the
        # live size instead (docs/live.md, "On a CPU"); with a GPU provider the preview model.
        path = shipped_live_onnx() if available_providers(providers) == ["CPUExecutionProvider"] else shipped_onnx()
    model = SplitPipeline(path, providers=providers, threads=threads, scale_every=SCALE_SEARCH_EVERY)
    if model.info.needs_depth:
        raise ConfigError(f"{path}: this model uses the oracle backbone (ground-truth depth as input); live needs a model that sees only the images")
    return model


def _runtime_line(r: dict) -> str:
    where = f"model on {r['device']}{' (' + r['gpu'] + ')' if r.get('gpu') else ''} in torch at {r.get('sizes', {}).get('output', '?')}"
    if r["graphs"] == "compiling":
        return where + "; CUDA graphs compiling in the background, eager frames until they are ready (/status runtime.graphs)"
    return f"{where}; {r['graphs']}"


class LiveApp:
    def __init__(self, engine: LiveEngine, recorder=None):
        self.engine = engine
        self.recorder = recorder
        self.server = None

    @classmethod
    def build(cls, cfg, *, model: Optional[Path] = None, calibration: Optional[Path] = None, replay: Optional[Path] = None,
              record_output: Optional[Path] = None, record_view: Optional[dict] = None, threads: Optional[int] = None,
              providers=None, jpeg_quality: int = 85, notes=None, device: str = "cpu", size: Optional[str] = None,
              compile: bool = True) -> "LiveApp":
        device = parse_device(device)
        if device != "cpu":
            for flag, value in (("--providers", providers), ("--threads", threads)):
                if value:
                    raise ConfigError(f"{flag} is for ONNX Runtime (--device cpu); --device {device} runs the torch GPU runtime")
            gpu_runtime(device)  # no torch or no GPU: one line before the source and the calibration are opened
        elif size is not None or not compile:
            raise ConfigError(f"{'--size' if size is not None else '--no-compile'} is for --device cuda "
                              "(the ONNX model's sizes are fixed at export; ONNX Runtime builds no CUDA graphs)")
        left, right = source_cameras(cfg)
        replayed = ReplaySource(replay, left, right) if replay is not None else None
        said: list[str] = []  # notes are printed once everything opened: a bad input stays one line
        rig = rig_calibration(cfg, calibration, replayed, said)
        for name in (left, right):
            if name not in rig:
                raise ConfigError(f"calibration has no camera '{name}' (it has: {', '.join(rig.names)})")
        check_frame_sizes(cfg, rig, (left, right), replayed, calibration)
        if record_output is not None and record_view is not None:
            from rig.live.viewpoint import parse_viewpoint

            try:  # the engine parses it again; a wrong one is one line before anything opens
                parse_viewpoint(record_view, rig, (left, right))
            except ValueError as exc:
                raise ConfigError(f"--record-view: {exc}") from None
        live_model = open_model(model, providers, threads, device, size, compile)
        recorder = None
        if record_output is not None:
            from rig.live.video import VideoWriter

            if record_output.suffix.lower() not in (".mp4", ".mkv", ".mov"):
                raise ConfigError(f"--record-output: {record_output}: give a .mp4 (or .mkv, .mov) file")
            if record_output.exists():
                raise ConfigError(f"--record-output: {record_output} exists; nothing is written over")
            if not record_output.parent.is_dir():
                raise ConfigError(f"--record-output: {record_output.parent}: no such folder")
            recorder = VideoWriter(record_output, fps=cfg.trigger.rate_hz if cfg.trigger else 30.0)
        if device != "cpu":
            said.append(_runtime_line(live_model.runtime_status()))
        for line in said:
            if notes is not None:
                notes(line)
        source = replayed if replayed is not None else SessionSource(cfg, left, right, on_phase=notes)
        engine = LiveEngine(source, rig, left, right, live_model, jpeg_quality=jpeg_quality, recorder=recorder, record_view=record_view)
        return cls(engine, recorder)

    def __enter__(self) -> "LiveApp":
        self.engine.start()
        return self

    def __exit__(self, *exc) -> None:
        if self.server is not None:
            self.server.stop()
        self.engine.stop()

    def serve(self, host: str, port: int, token: Optional[str], sock=None):
        """`sock`: the listening socket, bound beforehand (else bound here on host:port)."""
        from rig.live.server import serve

        self.server = serve(self.engine, host, port, token, sock=sock)
        return self.server

    def summary(self) -> dict:
        s = self.engine.status()
        if self.recorder is not None:
            s["record_output"] = {"path": str(self.recorder.path), "frames": self.recorder.frames, "codec": self.recorder.codec}
        return s
