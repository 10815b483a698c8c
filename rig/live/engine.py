"""The live loop: frame sets in, one encoded novel view per viewer out.

Three threads, so that the model never waits for a frame:
- capture: takes the source's next frame set and preprocesses its two frames (undistort + resize
  with precomputed tables) into the one "newest set" slot; a set still in the slot when a newer one
  arrives is dropped and counted, never queued;
- model: takes the newest set, runs stage 1 (what does not depend on the viewpoint) once, then the
  viewpoint-dependent part once for each viewer that is ready for a frame, at its newest viewpoint;
- encoder: JPEG-encodes each rendered view into its viewer's one-frame mailbox.

A viewer is ready for the next set when its mailbox is empty (its last view may still be in the
encoder: stage 1 of the next set starts meanwhile): the server takes a frame only when the browser
has credit, so a slow browser gets fewer renders and never holds the model or the other viewers.
"""
from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from calibration.camera import CameraModel, RigCalibration
from rig.cameras.pixels import rgb8
from rig.live.api import LiveFrame, runtime_of
from rig.live.viewpoint import Viewpoint, parse_viewpoint, presets

log = logging.getLogger(__name__)

DEFAULT_VIEW = {"type": "viewpoint", "t": 0.5}
ERROR_SHOWN_S = 5.0  # a failure of the loop stays in the health messages this long after it last happened


class _Window:
    """Recent values (ms, or event times for rates) for the status figures."""

    def __init__(self, n: int = 120):
        self.values: deque = deque(maxlen=n)
        self.lock = threading.Lock()

    def add(self, v: float) -> None:
        with self.lock:
            self.values.append(v)

    def percentile(self, q: float) -> Optional[float]:
        with self.lock:
            vals = list(self.values)
        return round(float(np.percentile(vals, q)), 1) if vals else None

    def rate(self, span_s: float = 2.0) -> float:
        """Events per second over the last `span_s` (values are monotonic times)."""
        now = time.monotonic()
        with self.lock:
            n = sum(1 for t in self.values if now - t <= span_s)
        return round(n / span_s, 2)


@dataclass
class _Prepared:
    version: int
    index: int
    capture_ns: int
    feeds: Optional[dict]  # the model's source inputs (images, intrinsics, poses); None: not yet prepared
    images: Optional[dict] = None  # the raw frames while `feeds` is None


@dataclass
class _Stage1:
    version: int
    index: int
    capture_ns: int
    feeds: dict
    outputs: dict


class LiveViewer:
    """One viewer of the engine (rig.live.api.Viewer)."""

    def __init__(self, engine: "LiveEngine", vid: int, viewpoint: Viewpoint, png: bool = False):
        self.id = vid
        self._engine = engine
        self._cond = threading.Condition()
        self._viewpoint = viewpoint
        self._viewpoint_id = 1
        self._camera: Optional[CameraModel] = None
        self._mailbox: Optional[LiveFrame] = None
        self._busy = False  # a render for it is in the encoder
        self.rendered_key: tuple = ()
        self.png = png  # snapshot viewers get PNG bytes
        self.frames_out = 0
        self.renders = 0
        self.out_times = _Window(256)
        self.latency = _Window(256)
        self._sent: dict[tuple[int, int], int] = {}  # (set, viewpoint) -> capture_ns of frames handed out

    # --- rig.live.api.Viewer ----------------------------------------------------------------------
    def set_viewpoint(self, message: dict) -> int:
        vp = parse_viewpoint(message, self._engine.rig, self._engine.sources)  # ValueError on bad input: nothing changes
        with self._cond:
            if vp != self._viewpoint:
                self._viewpoint = vp
                self._viewpoint_id += 1
                self._camera = None
            vid = self._viewpoint_id
        self._engine.wake()
        return vid

    def next_frame(self, timeout: float) -> Optional[LiveFrame]:
        with self._cond:
            if self._mailbox is None:
                self._cond.wait_for(lambda: self._mailbox is not None, timeout=timeout)
            frame, self._mailbox = self._mailbox, None
            if frame is not None:
                self.frames_out += 1
                self.out_times.add(time.monotonic())
                self._sent[(frame.set_index, frame.viewpoint_id)] = frame.capture_ns
                if len(self._sent) > 64:
                    self._sent.pop(next(iter(self._sent)))
        if frame is not None:
            self._engine.wake()  # its mailbox is free: it may get the next render
        return frame

    def acknowledge(self, set_index: int, viewpoint_id: int) -> None:
        with self._cond:
            capture_ns = self._sent.pop((int(set_index), int(viewpoint_id)), None)
        if capture_ns is not None:
            ms = (time.monotonic_ns() - capture_ns) / 1e6
            self.latency.add(ms)
            self._engine.latency.add(ms)

    # --- the engine's side ------------------------------------------------------------------------
    def wants(self, version: int) -> Optional[tuple[CameraModel, int]]:
        """(camera, viewpoint id) to render for frame-set `version`, or None when it has that view
        already or its last frame has not been taken yet."""
        with self._cond:
            if self._mailbox is not None or self._busy:
                return None
            if self.rendered_key == (version, self._viewpoint_id):
                return None
            if self._camera is None:
                self._camera = self._viewpoint.camera(self._engine.rig, self._engine.output_size, self._engine.sources)
            self._busy = True
            self.rendered_key = (version, self._viewpoint_id)
            return self._camera, self._viewpoint_id

    def holding(self) -> bool:
        """A rendered frame waits for it to take it."""
        with self._cond:
            return self._mailbox is not None

    def ready_soon(self) -> bool:
        """Free for a new render, or about to be: its last frame was taken (or it has none), or its
        last render is in the encoder (a few ms from its mailbox, which the server empties at once
        while the browser has credit). Stage 1 of the next set starts meanwhile, so the model does
        not wait for the encoder and the hand-off."""
        with self._cond:
            return self._mailbox is None

    def deliver(self, frame: Optional[LiveFrame]) -> None:
        with self._cond:
            self._busy = False
            if frame is not None:
                self._mailbox = frame
                self.renders += 1
            self._cond.notify_all()

    def describe(self) -> dict:
        return {"id": self.id, "viewpoint": self._viewpoint.describe(), "viewpoint_id": self._viewpoint_id,
                "fps_out": self.out_times.rate(), "frames_out": self.frames_out,
                "latency_ms_p50": self.latency.percentile(50), "latency_ms_p95": self.latency.percentile(95)}


class LiveEngine:
    """Capture → stage 1 once per set → the view of every ready viewer → JPEG (rig.live.api.Engine)."""

    def __init__(self, source, rig: RigCalibration, left: str, right: str, model, *, jpeg_quality: int = 85,
                 recorder=None, record_view: Optional[dict] = None):
        """`model`: an inference.runtime.SplitPipeline (stage 1 and the view as two ONNX Runtime sessions). `rig`: every calibrated camera (sources and
        supervision cameras: the presets). `recorder`: an object with write(rgb uint8) and close(),
        fed the view at `record_view` (default halfway)."""
        self.source = source
        self.rig = rig
        self.left, self.right = rig[left], rig[right]
        self.sources = (left, right)
        self._presets = presets(rig, self.sources)  # the rig is fixed for the engine's life: once, not per viewer
        self.model = model
        self.sizes = model.sizes
        self.output_size = tuple(self.sizes.output)
        self.jpeg_quality = int(jpeg_quality)
        self._viewers: dict[int, LiveViewer] = {}
        self._viewers_lock = threading.Lock()
        self._next_id = 1
        self._slot: Optional[_Prepared] = None
        self._slot_cond = threading.Condition()
        self._version = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._encode_q: queue.Queue = queue.Queue(maxsize=8)
        self._threads: list[threading.Thread] = []
        self._current: Optional[_Stage1] = None
        self._model_lock = threading.Lock()  # held around every model run of the loop
        self._busy_since: Optional[float] = None  # when the model started its current frame set
        self._held = False
        self._errors: list[tuple[float, str]] = []
        # figures
        self.sets_in = 0
        self.sets_dropped = 0  # preprocessed sets replaced by a newer one before the model took them
        self.stage1_runs = 0
        self.view_runs = 0
        self.sets_prepared_late = 0  # sets the model had to preprocess itself (it came free sooner than expected)
        self.in_times = _Window(256)
        self.stage1_ms = _Window()
        self.view_ms = _Window()
        self.prep_ms = _Window()
        self.encode_ms = _Window()
        self.latency = _Window(512)
        self.started = time.monotonic()
        self._recorder = recorder
        self._record_viewer = self.add_viewer(record_view or DEFAULT_VIEW, internal=True) if recorder is not None else None

    # --- life -------------------------------------------------------------------------------------
    def start(self) -> "LiveEngine":
        self.source.start()
        self.started = time.monotonic()
        for name, target in (("live-capture", self._capture_loop), ("live-model", self._model_loop), ("live-encode", self._encode_loop)):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        self.wake()
        with self._slot_cond:
            self._slot_cond.notify_all()
        for t in self._threads:
            t.join(timeout=5.0)
        try:
            self.source.stop()
        finally:
            if self._recorder is not None:
                self._recorder.close()

    def __enter__(self) -> "LiveEngine":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wake(self) -> None:
        self._wake.set()

    @contextlib.contextmanager
    def model_held(self):
        """The model to the caller alone (the loop waits): to time it without the loop in the way."""
        with self._model_lock:
            self._held = True  # sets are kept raw meanwhile (no preprocessing beside the caller's runs)
            try:
                yield self.model
            finally:
                self._held = False

    # --- rig.live.api.Engine ----------------------------------------------------------------------
    def add_viewer(self, message: Optional[dict] = None, internal: bool = False, png: bool = False) -> LiveViewer:
        vp = parse_viewpoint(message or DEFAULT_VIEW, self.rig, self.sources)
        with self._viewers_lock:
            viewer = LiveViewer(self, self._next_id, vp, png=png)
            viewer.internal = internal
            self._viewers[viewer.id] = viewer
            self._next_id += 1
        self.wake()
        return viewer

    def remove_viewer(self, viewer) -> None:
        with self._viewers_lock:
            self._viewers.pop(viewer.id, None)

    def presets(self) -> list[dict]:
        return [dict(p) for p in self._presets]

    def snapshot(self, message: Optional[dict] = None, timeout: float = 5.0) -> Optional[bytes]:
        viewer = self.add_viewer(message or DEFAULT_VIEW, internal=True, png=True)
        try:
            frame = viewer.next_frame(timeout)
            return frame.jpeg if frame is not None else None
        finally:
            self.remove_viewer(viewer)

    def status(self) -> dict:
        with self._viewers_lock:
            viewers = [v for v in self._viewers.values() if not getattr(v, "internal", False)]
        health = self.source.health().to_dict()
        recent = [line for t, line in list(self._errors) if time.monotonic() - t < ERROR_SHOWN_S]
        if recent:
            health = {"ok": False, "messages": health["messages"] + recent[-3:]}
        cur = self._current
        return {
            "uptime_s": round(time.monotonic() - self.started, 1),
            "fps_in": self.in_times.rate(),
            "fps_out": round(sum(v.out_times.rate() for v in viewers), 2),
            "sets_in": self.sets_in,
            "sets_dropped": self.sets_dropped,
            "sets_incomplete": getattr(self.source, "incomplete", 0),
            "sets_prepared_late": self.sets_prepared_late,
            "stage1_runs": self.stage1_runs,
            "view_runs": self.view_runs,
            "last_set": cur.index if cur is not None else None,
            "ms": {"preprocess": self.prep_ms.percentile(50), "stage1": self.stage1_ms.percentile(50),
                   "view": self.view_ms.percentile(50), "encode": self.encode_ms.percentile(50)},
            "latency_ms": {"p50": self.latency.percentile(50), "p95": self.latency.percentile(95)},
            "viewers": [v.describe() for v in viewers],
            "health": health,
            "model": self._model_status(),
            "runtime": runtime_of(self.model),
        }

    def _model_status(self) -> dict:
        out = {"path": str(getattr(self.model, "path", "")), "sizes": self.sizes.describe()}
        scale = getattr(self.model, "scale_status", None)  # ONNX Runtime's SplitPipeline: how often the scale search runs
        if scale is not None and scale() is not None:
            out["scale_search"] = scale()
        return out

    # --- threads ----------------------------------------------------------------------------------
    def _capture_loop(self) -> None:
        while not self._stop.is_set():
            try:
                live = self.source.next(timeout=0.2)
            except Exception as exc:  # a device failing mid-run: reported in the status, the server goes on
                self._error(f"capture: {exc}")
                time.sleep(0.2)
                continue
            if live is None:
                if self.source.finished:
                    return
                continue
            self.sets_in += 1
            self.in_times.add(time.monotonic())
            feeds = self._prepare(live.images) if self._model_due_soon() else None
            if feeds is False:
                continue
            with self._slot_cond:
                if self._slot is not None:
                    self.sets_dropped += 1
                self._version += 1
                self._slot = _Prepared(self._version, live.index, live.capture_ns, feeds, None if feeds else live.images)
                self._slot_cond.notify_all()
            self.wake()

    def _prepare(self, images: dict):
        """The model's source inputs from a set's two frames (False after an error, reported)."""
        t0 = time.perf_counter()
        try:
            feeds = self.model.source_feeds(rgb8(images[self.left.name]), rgb8(images[self.right.name]), self.left, self.right)
        except Exception as exc:
            self._error(f"preprocess: {exc}")
            return False
        self.prep_ms.add((time.perf_counter() - t0) * 1000.0)
        return feeds

    def _model_due_soon(self) -> bool:
        """Whether the model may take the next set soon: then a set is prepared as it arrives, so
        the model never waits for it. Sets that arrive while the model still has far to go are only
        kept raw (most of them are replaced by newer ones before the model is free: preparing them
        all would take CPU from the model)."""
        if self._held:
            return False
        if self._busy_since is None:
            return True
        s1, view = self.stage1_ms.percentile(50), self.view_ms.percentile(50)
        if s1 is None or view is None:
            return True
        with self._viewers_lock:
            n = max(1, len(self._viewers))
        period = 1.0 / max(self.in_times.rate(), 1.0)
        left_s = (s1 + n * view) / 1000.0 - (time.monotonic() - self._busy_since)
        return left_s <= 2.0 * period + (self.prep_ms.percentile(50) or 0.0) / 1000.0

    def _take_slot(self) -> Optional[_Prepared]:
        with self._slot_cond:
            prepared, self._slot = self._slot, None
        return prepared

    def _model_loop(self) -> None:
        while not self._stop.is_set():
            with self._viewers_lock:
                anyone = any(v.ready_soon() for v in self._viewers.values())
            if not anyone:  # nobody could take a frame soon: no stage 1 for a set no one will see
                self._wake.wait(0.05)
                self._wake.clear()
                continue
            prepared = self._take_slot()
            if prepared is not None and prepared.feeds is None:
                self.sets_prepared_late += 1
                prepared.feeds = self._prepare(prepared.images)  # it arrived while the model was far from done
                prepared.images = None
                if prepared.feeds is False:
                    continue
            if prepared is not None:
                self._busy_since = time.monotonic()
                t0 = time.perf_counter()
                try:
                    with self._model_lock:
                        outputs = self.model.stage1(prepared.feeds)
                except Exception as exc:
                    self._error(f"model stage 1: {exc}")
                    continue
                self.stage1_ms.add((time.perf_counter() - t0) * 1000.0)
                self.stage1_runs += 1
                self._current = _Stage1(prepared.version, prepared.index, prepared.capture_ns, prepared.feeds, outputs)
            cur = self._current
            rendered = False
            if cur is not None:
                with self._viewers_lock:
                    viewers = list(self._viewers.values())
                for viewer in viewers:
                    if self._stop.is_set():
                        return
                    want = viewer.wants(cur.version)
                    if want is None:
                        continue
                    camera, vp_id = want
                    t0 = time.perf_counter()
                    try:
                        with self._model_lock:
                            view = self.model.render(cur.outputs, cur.feeds, camera)
                    except Exception as exc:
                        viewer.deliver(None)
                        self._error(f"model view: {exc}")
                        continue
                    self.view_ms.add((time.perf_counter() - t0) * 1000.0)
                    self.view_runs += 1
                    rendered = True
                    self._encode_q.put((viewer, cur.index, vp_id, cur.capture_ns, view))
            if not rendered and self._slot is None:
                self._wake.wait(0.05)
                self._wake.clear()

    def _encode_loop(self) -> None:
        while not self._stop.is_set():
            try:
                viewer, index, vp_id, capture_ns, view = self._encode_q.get(timeout=0.2)
            except queue.Empty:
                continue
            t0 = time.perf_counter()
            rgb = view.image_uint8()
            bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
            if viewer.png:
                ok, data = cv2.imencode(".png", bgr)
            else:
                ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            self.encode_ms.add((time.perf_counter() - t0) * 1000.0)
            if viewer is self._record_viewer:
                try:
                    self._recorder.write(rgb, capture_ns / 1e9)
                except Exception as exc:
                    self._error(f"--record-output: {exc}")
            viewer.deliver(LiveFrame(index, vp_id, capture_ns, data.tobytes()) if ok else None)
            if viewer is self._record_viewer:
                viewer.next_frame(0)  # the recorder takes every frame it is given

    def _error(self, line: str) -> None:
        log.warning(line)
        self._errors = [(t, x) for t, x in self._errors if x != line][-9:] + [(time.monotonic(), line)]
