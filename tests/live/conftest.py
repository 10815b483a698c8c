"""Fixtures of the live server and browser tests.

`live_rig` is what the tests run against: an engine (rig.live.api.Engine) behind a recorder of what the
server asked of it, and the few things a test must do to the rig (make a fault and clear it, know what
a viewpoint should look like). It is parametrised by engine kind; today there is one:

- "colour": ColourEngine, a stand-in with no model: a producer thread makes "frame sets" at a fixed
  rate, and each viewer gets a solid-colour JPEG whose colour encodes its viewpoint (`colour_of`).

A kind for the real engine (rig.live.engine on a simulated rig) adds a branch to `live_rig` that
returns a LiveRig whose `expected_rgb` is None (the tests then check that the image changes rather
than its colour) and whose fault()/clear() stop and restart a simulated camera.
"""
from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Optional

import cv2
import numpy as np
import pytest

from rig.live.api import LiveFrame

# "colour": a stand-in engine whose frames are flat colours that encode the viewpoint (exact checks of
# the server and the page); "sim": the real engine (rig.live.engine) on a simulated six-camera rig with
# the test-size model. The browser tests run on the real engine.
ENGINE_KINDS = ["colour"]


# --- ColourEngine -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ColourView:
    t: Optional[float] = 0.5
    preset: Optional[str] = None
    yaw: float = 0.0
    pitch: float = 0.0
    zoom: float = 1.0


def _number(message: dict, key: str, default: float) -> float:
    v = message.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"'{key}' must be a finite number, got {v!r}")
    return float(v)


class ColourEngine:
    """A stand-in for the live engine (rig.live.api.Engine): no cameras, no model. Viewpoint
    messages: {"type": "viewpoint", "t": 0..1} or {"preset": name}, optionally yaw/pitch (degrees)
    and zoom, clamped to +-180, +-60, 0.25..4."""

    PRESETS = [{"name": "left", "kind": "source"}, {"name": "right", "kind": "source"},
               {"name": "top", "kind": "supervision"}]
    SIZE = (320, 180)

    def __init__(self, fps: float = 30.0):
        self.fps = fps
        self.paused = False  # no frame sets come in (a rig that has not started)
        self.fault: Optional[str] = None
        self.raise_in_set_viewpoint = False  # an engine bug: set_viewpoint raises RuntimeError
        self.extra_status: dict = {}
        self.set_index = 0
        self._lock = threading.Lock()
        self._viewers: dict[int, ColourViewer] = {}
        self._next_id = 1
        self._stop = threading.Event()
        self._set_times: deque = deque(maxlen=256)
        self._latency: deque = deque(maxlen=256)
        self._jpegs: dict = {}
        self._thread = threading.Thread(target=self._produce, name="colour-engine", daemon=True)

    # life
    def start(self) -> "ColourEngine":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    # what a view looks like
    def parse(self, message: Optional[dict]) -> ColourView:
        if message is None:
            return ColourView()
        if not isinstance(message, dict):
            raise ValueError("a viewpoint message is a JSON object")
        unknown = sorted(set(message) - {"type", "t", "preset", "yaw", "pitch", "zoom"})
        if unknown:
            raise ValueError(f"unknown viewpoint field '{unknown[0]}'")
        if message.get("type", "viewpoint") != "viewpoint":
            raise ValueError("not a viewpoint message")
        if ("t" in message) == ("preset" in message):
            raise ValueError("give either 't' or 'preset'")
        t, preset = None, None
        if "preset" in message:
            preset = message["preset"]
            if preset not in [p["name"] for p in self.PRESETS]:
                raise ValueError(f"no camera {str(preset)[:40]!r}")
        else:
            t = _number(message, "t", 0.5)
            if not 0.0 <= t <= 1.0:
                raise ValueError(f"'t' must be between 0 and 1, got {t}")
        return ColourView(t=t, preset=preset,
                          yaw=min(180.0, max(-180.0, _number(message, "yaw", 0.0))),
                          pitch=min(60.0, max(-60.0, _number(message, "pitch", 0.0))),
                          zoom=min(4.0, max(0.25, _number(message, "zoom", 1.0))))

    @staticmethod
    def colour_of(view: ColourView) -> tuple[int, int, int]:
        """RGB of a view: along the arc red grows and green falls with t; the supervision camera
        'top' is blue; orbiting adds blue."""
        if view.preset == "top":
            return (20, 20, 230)
        t = {"left": 0.0, "right": 1.0}.get(view.preset, view.t)
        blue = 40 + min(150, int(abs(view.yaw) + abs(view.pitch) + 40 * abs(math.log(view.zoom))))
        return (round(255 * t), round(255 * (1 - t)), blue)

    def expected_rgb(self, message: Optional[dict]) -> tuple[int, int, int]:
        return self.colour_of(self.parse(message))

    def image(self, view: ColourView) -> np.ndarray:
        r, g, b = self.colour_of(view)
        w, h = self.SIZE
        img = np.empty((h, w, 3), np.uint8)
        img[:] = (b, g, r)  # BGR for OpenCV
        label = view.preset or f"t={view.t:.3f}"
        cv2.putText(img, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
        return img

    def jpeg(self, view: ColourView) -> bytes:
        data = self._jpegs.get(view)
        if data is None:
            ok, buf = cv2.imencode(".jpg", self.image(view), [cv2.IMWRITE_JPEG_QUALITY, 90])
            assert ok
            data = self._jpegs[view] = buf.tobytes()
            if len(self._jpegs) > 512:
                self._jpegs.pop(next(iter(self._jpegs)))
        return data

    def _produce(self) -> None:
        period = 1.0 / self.fps
        next_at = time.monotonic()
        while not self._stop.is_set():
            next_at += period
            delay = next_at - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_at = time.monotonic()
            if self.paused:
                continue
            with self._lock:
                self.set_index += 1
                index = self.set_index
                viewers = list(self._viewers.values())
            self._set_times.append(time.monotonic())
            capture_ns = time.time_ns()
            for v in viewers:
                view, vid = v.current()
                v.deliver(LiveFrame(index, vid, capture_ns, self.jpeg(view)))

    # rig.live.api.Engine
    def add_viewer(self, message: Optional[dict] = None) -> "ColourViewer":
        view = self.parse(message)
        with self._lock:
            viewer = ColourViewer(self, self._next_id, view)
            self._viewers[viewer.id] = viewer
            self._next_id += 1
        return viewer

    def remove_viewer(self, viewer) -> None:
        with self._lock:
            self._viewers.pop(viewer.id, None)
        viewer.closed = True

    def presets(self) -> list[dict]:
        return [dict(p) for p in self.PRESETS]

    def viewers(self) -> list["ColourViewer"]:
        with self._lock:
            return list(self._viewers.values())

    def status(self) -> dict:
        now = time.monotonic()
        fps_in = sum(1 for t in list(self._set_times) if now - t <= 2.0) / 2.0
        viewers = self.viewers()
        lat = sorted(self._latency)
        pct = (lambda q: round(lat[min(len(lat) - 1, int(q * len(lat)))], 1)) if lat else (lambda q: None)
        right_ok = self.fault is None
        return {
            "fps_in": fps_in,
            "fps_out": round(sum(v.fps_out() for v in viewers), 2),
            "sets_in": self.set_index,
            "sets_dropped": sum(v.dropped for v in viewers),
            "ms": {"stage1": 12.5, "view": 4.25, "encode": 0.75},
            "latency_ms": {"p50": pct(0.5), "p95": pct(0.95)},
            "cameras": {"left": {"ok": True, "fps": fps_in}, "right": {"ok": right_ok, "fps": fps_in if right_ok else 0.0}},
            "trigger": {"ok": True, "rate_hz": self.fps},
            "viewers": [v.describe() for v in viewers],
            "health": {"ok": self.fault is None, "messages": [self.fault] if self.fault else []},
            **self.extra_status,
        }

    def snapshot(self, message: Optional[dict] = None, timeout: float = 5.0) -> Optional[bytes]:
        view = self.parse(message)
        deadline = time.monotonic() + timeout
        while self.paused or self.set_index == 0:
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.02)
        ok, buf = cv2.imencode(".png", self.image(view))
        return buf.tobytes()


class ColourViewer:
    def __init__(self, engine: ColourEngine, vid: int, view: ColourView):
        self.id = vid
        self.closed = False
        self.dropped = 0
        self.frames_out = 0
        self._engine = engine
        self._cond = threading.Condition()
        self._view = view
        self._viewpoint_id = 1
        self._mailbox: Optional[LiveFrame] = None
        self._out_times: deque = deque(maxlen=256)
        self._sent: dict = {}

    def current(self) -> tuple[ColourView, int]:
        with self._cond:
            return self._view, self._viewpoint_id

    def deliver(self, frame: LiveFrame) -> None:
        with self._cond:
            if self._mailbox is not None:
                self.dropped += 1
            self._mailbox = frame
            self._cond.notify_all()

    def set_viewpoint(self, message: dict) -> int:
        if self._engine.raise_in_set_viewpoint:
            raise RuntimeError("colour engine: a deliberate failure")
        view = self._engine.parse(message)
        with self._cond:
            if view != self._view:
                self._view = view
                self._viewpoint_id += 1
            return self._viewpoint_id

    def next_frame(self, timeout: float) -> Optional[LiveFrame]:
        with self._cond:
            self._cond.wait_for(lambda: self._mailbox is not None, timeout=timeout)
            frame, self._mailbox = self._mailbox, None
            if frame is not None:
                self.frames_out += 1
                self._out_times.append(time.monotonic())
                self._sent[(frame.set_index, frame.viewpoint_id)] = frame.capture_ns
        return frame

    def acknowledge(self, set_index: int, viewpoint_id: int) -> None:
        with self._cond:
            capture_ns = self._sent.pop((set_index, viewpoint_id), None)
        if capture_ns is not None:
            self._engine._latency.append((time.time_ns() - capture_ns) / 1e6)

    def fps_out(self) -> float:
        now = time.monotonic()
        return sum(1 for t in list(self._out_times) if now - t <= 2.0) / 2.0

    def describe(self) -> dict:
        with self._cond:
            view, vid = self._view, self._viewpoint_id
        where = {"preset": view.preset} if view.preset is not None else {"t": view.t}
        return {"id": self.id, "fps_out": self.fps_out(), "frames_out": self.frames_out, "viewpoint_id": vid,
                "viewpoint": {**where, "yaw": view.yaw, "pitch": view.pitch, "zoom": view.zoom}}


# --- recording what the server asks of any engine -------------------------------------------------------------
class RecordingViewer:
    def __init__(self, inner, log: "RecordingEngine"):
        self.inner = inner
        self.id = inner.id
        self.messages: list[dict] = []  # viewpoint messages the engine accepted
        self.refused: list[dict] = []
        self.ids: list[int] = []
        self.acks: list[tuple[int, int]] = []
        self.frames_out = 0
        self._log = log

    def set_viewpoint(self, message: dict) -> int:
        try:
            vid = self.inner.set_viewpoint(message)
        except ValueError:
            self.refused.append(message)
            raise
        self.messages.append(message)
        self.ids.append(vid)
        return vid

    def next_frame(self, timeout: float):
        frame = self.inner.next_frame(timeout)
        if frame is not None:
            self.frames_out += 1
        return frame

    def acknowledge(self, set_index: int, viewpoint_id: int) -> None:
        self.acks.append((set_index, viewpoint_id))
        self.inner.acknowledge(set_index, viewpoint_id)


class RecordingEngine:
    """Any engine, with a record of the viewers the server made and what it passed on to them."""

    def __init__(self, inner):
        self.inner = inner
        self.viewers: list[RecordingViewer] = []
        self.removed: list[int] = []
        self.snapshots: list[Optional[dict]] = []
        self._lock = threading.Lock()

    def add_viewer(self, message: Optional[dict] = None) -> RecordingViewer:
        viewer = RecordingViewer(self.inner.add_viewer(message), self)
        with self._lock:
            self.viewers.append(viewer)
        return viewer

    def remove_viewer(self, viewer: RecordingViewer) -> None:
        self.inner.remove_viewer(viewer.inner)
        with self._lock:
            self.removed.append(viewer.id)

    def presets(self) -> list[dict]:
        return self.inner.presets()

    def status(self) -> dict:
        return self.inner.status()

    def snapshot(self, message: Optional[dict] = None, timeout: float = 5.0):
        self.snapshots.append(message)
        return self.inner.snapshot(message, timeout)

    def open_viewers(self) -> list[RecordingViewer]:
        with self._lock:
            return [v for v in self.viewers if v.id not in self.removed]


# --- the fixture ---------------------------------------------------------------------------------------------
@dataclass
class LiveRig:
    kind: str
    engine: RecordingEngine  # what the server is given
    fault: Callable[[str], None]  # make the rig report a fault whose message contains the text
    clear: Callable[[], None]  # and recover
    expected_rgb: Optional[Callable[[Optional[dict]], tuple]] = None  # None: the engine's views are not predictable
    presets: list = field(default_factory=list)
    supervision: Optional[str] = None  # a preset of kind "supervision"
    inner: object = None


def wait_until(predicate, timeout: float = 5.0, interval: float = 0.02, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


@pytest.fixture(scope="session")
def sim_live(tiny_onnx):
    """A LiveApp on a simulated six-camera rig (320x180 at 15 Hz, triggered by the emulated board)
    rendering with the test-size model; one per test run (its start-up is a few seconds)."""
    from rig.sim.rig_config import sim_rig_config
    from rig.config import parse_config
    from rig.live.app import LiveApp

    cfg = parse_config(sim_rig_config(6, 320, 180, fps=15.0))
    app = LiveApp.build(cfg, model=tiny_onnx.path, threads=2)
    with app:
        wait_until(lambda: app.engine.status()["sets_in"] > 0, timeout=30, what="the simulated rig's first frame set")
        yield app


def model_rate(engine) -> float:
    """Frames per second the engine's model can render for one viewer (stage 1 + one view)."""
    ms = wait_until(lambda: (m := engine.status()["ms"])["stage1"] and m["view"] and m, what="model timings")
    return 1000.0 / (ms["stage1"] + ms["view"])


@pytest.fixture(params=ENGINE_KINDS)
def live_rig(request):
    if request.param == "sim":
        app = request.getfixturevalue("sim_live")
        engine = app.engine
        emulator = engine.source.session.emulator

        unplugged = []

        def fault(text: str) -> str:
            emulator.unplug()
            unplugged.append(True)
            return "disconnected"  # the trigger board's message: the page shows what the rig says

        def clear() -> None:
            emulator.replug()
            unplugged.clear()

        sup = next(p["name"] for p in engine.presets() if p["kind"] == "supervision")
        rig = LiveRig("sim", RecordingEngine(engine), fault, clear, None, engine.presets(), sup, engine)
        try:
            yield rig
        finally:
            if unplugged:
                emulator.replug()
            for v in list(engine._viewers.values()):
                if not getattr(v, "internal", False):
                    engine.remove_viewer(v)
    elif request.param == "colour":
        inner = ColourEngine(fps=30.0).start()

        def fault(text: str) -> None:
            inner.fault = text

        def clear() -> None:
            inner.fault = None

        rig = LiveRig("colour", RecordingEngine(inner), fault, clear, inner.expected_rgb, inner.presets(), "top", inner)
        try:
            yield rig
        finally:
            inner.stop()
    else:  # pragma: no cover
        raise AssertionError(f"unknown engine kind {request.param}")


@pytest.fixture
def colour_engine(live_rig):
    """The ColourEngine behind live_rig, for tests of its stand-in behaviour (skipped for other kinds)."""
    if live_rig.kind != "colour":
        pytest.skip("needs the colour engine's switches")
    return live_rig.inner


def start_server(engine, token=None, **options):
    from rig.live.server import LiveServer

    return LiveServer(engine, "127.0.0.1", 0, token, **options).start()


@pytest.fixture
def server(live_rig):
    srv = start_server(live_rig.engine)
    try:
        yield srv
    finally:
        srv.stop()
