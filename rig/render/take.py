"""Views of a recorded take at chosen viewpoints: one image, or an orbit video that sweeps from
the left source to the right one over consecutive frame sets (`rig model render`).

Every check of what the user asked for against the take (the set, the frames, the viewpoint, the
dropped frames) runs in `plan_views` before a model is loaded; `open_renderer` loads the model;
`render_take` renders and writes the file (atomically for an image).
"""
from __future__ import annotations

import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from calibration.camera import RigCalibration
from rig.errors import ConfigError


@dataclass
class Take:
    """A recorded take to render: its sequence, the two source cameras and every calibrated camera
    (the viewpoint presets)."""

    seq: object  # rig.storage.dataset.Sequence
    left: str
    right: str
    rig: RigCalibration

    @property
    def sources(self) -> tuple[str, str]:
        return self.left, self.right


def open_take(root: Path) -> Take:
    from rig.storage.dataset import Sequence
    from rig.storage.layout import SequenceError

    if not root.is_dir():
        raise ConfigError(f"--sequence {root}: no such sequence folder")
    if (root / "dataset.json").is_file():
        raise ConfigError(f"--sequence {root}: is a data set of several takes; name one of them")
    seq = Sequence(root)
    left, right = seq.sources()
    cameras = []
    for name in seq.camera_names:
        try:
            cameras.append(seq.camera_model(name))
        except SequenceError:
            if name in (left, right):
                raise
    return Take(seq, left, right, RigCalibration(cameras))


@dataclass
class Steer:
    """Orbit and zoom on top of every viewpoint (None: the viewpoint's own)."""

    yaw: Optional[float] = None
    pitch: Optional[float] = None
    zoom: Optional[float] = None


def viewpoint_message(view: str | float, steer: Steer) -> dict:
    """The live page's viewpoint message for a number along the arc or a camera name."""
    message: dict = {"type": "viewpoint"}
    try:
        message["t"] = float(view)
    except ValueError:
        message["preset"] = view
    for key in ("yaw", "pitch", "zoom"):
        if getattr(steer, key) is not None:
            message[key] = getattr(steer, key)
    return message


def parse_view(take: Take, view: str | float, steer: Steer):
    from rig.live.viewpoint import parse_viewpoint

    message = viewpoint_message(view, steer)
    if "preset" in message and message["preset"] not in take.rig:
        raise ConfigError(f"--view {view}: no camera {view!r} in the sequence's calibration "
                          f"(cameras: {', '.join(take.rig.names)}; or a number from 0 to 1 along the arc)")
    try:
        return parse_viewpoint(message, take.rig, sources=take.sources)
    except ValueError as exc:
        raise ConfigError(f"--view {view}: {exc}") from None


@dataclass
class Plan:
    """What to render: frame set `positions[i]` from `viewpoints[i]`; `orbit`: a video."""

    positions: list[int]
    viewpoints: list
    orbit: bool


def plan_views(take: Take, start: int, steer: Steer, *, view: Optional[str] = None, frames: Optional[int] = None) -> Plan:
    """One image of set `start` at `view`, or (view None) an orbit of `frames` sets from `start`
    (default: to the end of the take), t going from 0 to 1; every set must hold both sources."""
    seq = take.seq
    n_sets = len(seq)
    if start >= n_sets:
        raise ConfigError(f"--set {start}: out of range ({seq.root} has {n_sets} frame set{'s' * (n_sets != 1)}: 0 to {n_sets - 1})"
                          if n_sets else f"--set {start}: {seq.root} has no frame sets")
    if view is None:
        frames = frames if frames is not None else n_sets - start
        if start + frames > n_sets:
            raise ConfigError(f"--frames {frames} from --set {start}: {seq.root} has only {n_sets - start} sets from there")
        positions = list(range(start, start + frames))
        ts = [0.5] if frames == 1 else [i / (frames - 1) for i in range(frames)]
        plan = Plan(positions, [parse_view(take, t, steer) for t in ts], orbit=True)
    else:
        plan = Plan([start], [parse_view(take, view, steer)], orbit=False)
    for p in plan.positions:
        missing = [n for n in take.sources if seq.rows[p]["frames"].get(n) is None]
        if missing:
            raise ConfigError(f"--set {p}: frame set {p} of {seq.root} has no frame of {' and '.join(missing)} (a dropped frame); choose another set")
    return plan


@dataclass
class Renderer:
    """A loaded model: `render(left, right, left_cam, right_cam, target, left_depth, right_depth)`
    gives a view (image, ms), as NovelViewPipeline.render."""

    pipe: object
    render: Callable
    needs_depth: bool
    device: str

    def runtime(self) -> dict:
        if self.device != "cpu":
            return self.pipe.runtime_status()
        return {"kind": "onnxruntime", "providers": self.pipe.providers}


def _two_part_render(pipe) -> Callable:
    """NovelViewPipeline.render's call for a two-part runtime: stage 1 then the view (ms: both)."""
    def render(left, right, left_cam, right_cam, target, left_depth=None, right_depth=None):
        feeds = pipe.source_feeds(left, right, left_cam, right_cam)
        view = pipe.render(pipe.stage1(feeds), feeds, target)
        view.ms = pipe.stage1_ms + pipe.view_ms
        return view
    return render


def open_renderer(model: Optional[str], device: str, providers: Optional[list[str]] = None, size: Optional[str] = None) -> Renderer:
    """The exported model (default: the shipped one) in ONNX Runtime on `cpu`; on a CUDA device the
    checkpoint behind it in the torch GPU runtime, at `size` (default the model's own)."""
    from inference.errors import InferenceError

    if device != "cpu":
        if providers:
            raise ConfigError(f"--providers is for ONNX Runtime (--device cpu); --device {device} renders in torch")
        from rig.live.app import gpu_runtime

        pipe = gpu_runtime(device).TorchLivePipeline(model, device, size, compile=False)
        return Renderer(pipe, _two_part_render(pipe), False, device)  # the GPU runtime refuses an oracle model
    if size is not None:
        raise ConfigError("--size is for --device cuda (the ONNX model's sizes are fixed at export)")
    from inference.runtime import NovelViewPipeline

    if model is None:
        from inference.runtime.shipped import shipped_onnx

        try:
            model = shipped_onnx()
        except InferenceError:
            raise ConfigError("no shipped model in this installation (models/splat-sap-preview.onnx); "
                              "name one with --model M.onnx (rig model export)") from None
    pipe = NovelViewPipeline(model, providers=providers)
    return Renderer(pipe, pipe.render, pipe.info.needs_depth, device)


@dataclass
class Rendered:
    """What render_take wrote."""

    frames: int
    size: tuple[int, int]
    ms: list[float] = field(default_factory=list)
    fps: Optional[float] = None
    codec: Optional[str] = None
    codec_label: Optional[str] = None


def render_take(take: Take, plan: Plan, renderer: Renderer, out: Path, *, fps: Optional[float] = None,
                progress: Callable[[str], None] = lambda text: None) -> Rendered:
    """Render the plan's views into `out`: a video at `fps` (default: the take's rate, else 30) for
    an orbit, else one image."""
    seq, (left, right) = take.seq, take.sources
    if renderer.needs_depth and not seq.has_ground_truth():
        raise ConfigError(f"{renderer.pipe.path}: an oracle model reads ground-truth depth, which only simulator takes have; render a trained model")
    size = tuple(renderer.pipe.sizes.output)
    done = Rendered(0, size)

    def views():
        for i, (p, vp) in enumerate(zip(plan.positions, plan.viewpoints)):
            progress(f"rendering {i + 1}/{len(plan.positions)} (set {p}, {vp.label()}) ...")
            sample = seq.sample(p, [left, right], with_depth=renderer.needs_depth)
            target = vp.camera(take.rig, size, sources=take.sources)
            view = renderer.render(sample.images[left], sample.images[right], sample.cameras[left], sample.cameras[right], target,
                                   sample.depth.get(left), sample.depth.get(right))
            done.ms.append(view.ms)
            yield view.image_uint8()

    if plan.orbit:
        from rig.live.video import write_video

        done.fps = fps or float(seq.meta.rate_hz or 30.0)
        out.parent.mkdir(parents=True, exist_ok=True)  # a missing folder was checked writable (output_file)
        video = write_video(out, views(), done.fps)
        done.frames, done.codec, done.codec_label = video.frames, video.codec, video.codec_label
    else:
        import cv2

        from common.files import atomic_path
        from inference.errors import OutputError

        rgb = next(views())
        with atomic_path(out, make_parents=True) as tmp:  # a missing folder was checked writable (output_file)
            if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
                raise OutputError(f"{out}: could not write the image")
        done.frames = 1
    return done


def summary(take: Take, plan: Plan, renderer: Renderer, out: Path, done: Rendered) -> dict:
    """The --json object of `rig model render`."""
    return {
        "output": str(out),
        "kind": "video" if plan.orbit else "image",
        "model": str(renderer.pipe.path),
        "providers": getattr(renderer.pipe, "providers", None),
        "runtime": renderer.runtime(),
        "sequence": str(take.seq.root),
        "sets": plan.positions,
        "sources": list(take.sources),
        "viewpoints": [vp.describe() for vp in plan.viewpoints],
        "size": list(done.size),
        "frames": done.frames,
        "codec": done.codec,
        "fps": done.fps,
        "model_ms_median": round(statistics.median(done.ms), 1) if done.ms else None,
    }
