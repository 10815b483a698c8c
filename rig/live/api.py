"""What the live server asks of the live engine (and nothing more).

The engine (`rig.live.engine`) runs capture, preprocessing, the model and JPEG encoding in its own
threads; the server (`rig.live.server`) only moves encoded frames and viewpoint messages between the
engine and the browsers. Everything here is thread-safe: the server calls the blocking methods
from worker threads (`asyncio.to_thread`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Protocol


@dataclass(frozen=True)
class LiveFrame:
    """One rendered view, encoded, for one viewer."""

    set_index: int  # the frame set it was rendered from (increasing; gaps are dropped sets)
    viewpoint_id: int  # the viewpoint it shows (the id `Viewer.set_viewpoint` returned)
    capture_ns: int  # when the frames were exposed, host monotonic clock (time.monotonic_ns())
    jpeg: bytes


class Viewer(Protocol):
    """One browser (or MJPEG client): its own viewpoint, its own stream of frames."""

    id: int

    def set_viewpoint(self, message: dict) -> int:
        """Apply a viewpoint message (see `rig.live.viewpoint.parse_viewpoint`); returns its id.
        Raises ValueError with a one-line reason for a bad message (nothing changes then)."""

    def next_frame(self, timeout: float) -> Optional[LiveFrame]:
        """The newest frame rendered for this viewer that it has not had yet; None after `timeout`
        seconds without one. Frames rendered while the viewer was not asking are replaced by newer
        ones (counted as dropped), never queued."""

    def acknowledge(self, set_index: int, viewpoint_id: int) -> None:
        """The browser has drawn that frame (end-to-end latency is measured here)."""


class Engine(Protocol):
    def add_viewer(self, message: Optional[dict] = None) -> Viewer:
        """A new viewer, at the viewpoint `message` (default: halfway between the sources)."""

    def remove_viewer(self, viewer: Viewer) -> None: ...

    def presets(self) -> list[dict]:
        """Snap-to viewpoints: [{"name": camera name, "kind": "source" | "supervision", "t": where
        it stands along the arc between the sources, 0 to 1, or None}, ...]."""

    def status(self) -> dict:
        """JSON-able figures: fps in/out, model ms per stage, latency percentiles, drops, camera
        and trigger health (`health`: {"ok": bool, "messages": [str, ...]}), and where the model
        runs (`runtime`, see `runtime_of`)."""

    def snapshot(self, message: Optional[dict] = None, timeout: float = 5.0) -> Optional[bytes]:
        """A PNG of the newest frame set at a viewpoint (default: halfway); None if no frame set
        arrived within `timeout`."""


# ONNX Runtime's providers that run on an NVIDIA GPU (onnxruntime-gpu, or NVIDIA's build on a Jetson).
GPU_PROVIDERS = {"CUDAExecutionProvider": "cuda", "TensorrtExecutionProvider": "cuda"}


def runtime_of(model) -> dict:
    """Where and how the live model runs, as /status says it: the torch GPU runtime describes itself
    ({"kind": "torch", "device": "cuda:0", "gpu": ..., "graphs": "compiling" | "compiled" | "eager ..."});
    an ONNX Runtime model is {"kind": "onnxruntime", "device": "cpu" | "cuda", "providers": [...]}, its
    device the one its first provider runs on (ONNX Runtime puts a layer its first provider cannot
    run on the next)."""
    own = getattr(model, "runtime_status", None)
    if callable(own):
        return own()
    providers = list(getattr(model, "providers", None) or [])
    return {"kind": "onnxruntime", "device": GPU_PROVIDERS.get(providers[0], "cpu") if providers else "cpu", "providers": providers}
