"""The console's live tab: `rig live`'s engine and viewer, fed by the console's own frame sets.

The console already holds the cameras (its previews, or a take running); a second session for the
live view would fight it for them. So the live engine reads the sources' frames from the console's
tap: the newest set is handed over and an older one not yet taken is replaced, never queued (the
model's pace never reaches capture). The engine, its model and its page are `rig live`'s own
(rig.live.app / engine / server), served under /live/ behind the console's access guard.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Optional

from rig.errors import ConfigError, RigError
from rig.live.source import Health, LiveSet

log = logging.getLogger(__name__)

QUIET_S = 2.0  # no frame set for this long: the live view's health says so


class TapSource:
    """A live engine source (rig.live.source's contract) over the frame sets the console sees."""

    def __init__(self, left: str, right: str):
        self.left, self.right = left, right
        self.incomplete = 0
        self.replaced = 0  # sets handed over but replaced by a newer one before the engine took them
        self._cond = threading.Condition()
        self._newest: Optional[LiveSet] = None
        self._stopped = False
        self._last = time.monotonic()

    # called on the capture thread: keep a reference, return at once
    def offer(self, fs) -> None:
        left, right = fs.frames.get(self.left), fs.frames.get(self.right)
        if left is None or right is None:
            self.incomplete += 1
            return
        capture = fs.host_ts_ns if getattr(fs, "host_ts_ns", None) is not None else min(left.host_ts_ns, right.host_ts_ns)
        with self._cond:
            if self._newest is not None:
                self.replaced += 1
            self._newest = LiveSet(fs.index, int(capture), {self.left: left.image, self.right: right.image})
            self._last = time.monotonic()
            self._cond.notify_all()

    def start(self) -> None:
        self._last = time.monotonic()

    def next(self, timeout: float) -> Optional[LiveSet]:
        with self._cond:
            if self._newest is None and not self._stopped:
                self._cond.wait(timeout)
            s, self._newest = self._newest, None
            return s

    @property
    def finished(self) -> bool:
        return self._stopped

    def health(self) -> Health:
        quiet = time.monotonic() - self._last
        if quiet > QUIET_S:
            return Health(False, [f"no frame set from the console for {quiet:.0f} s"])
        return Health()

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()


class LiveMount:
    """ASGI app at /live: `rig live`'s routes while the live view runs, 503 otherwise."""

    def __init__(self):
        self.app = None

    async def __call__(self, scope, receive, send):
        app = self.app
        if app is not None:
            return await app(scope, receive, send)
        from fastapi.responses import JSONResponse

        if scope["type"] == "http":
            await JSONResponse({"error": "the live view is not running (start it from the Live tab)"}, status_code=503)(scope, receive, send)
        elif scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1013, "reason": "the live view is not running"})


class ConsoleLive:
    """Starts and stops the live view; `offer` is called with every frame set the console sees."""

    def __init__(self, cfg, mount: Optional[LiveMount] = None, model=None, threads: Optional[int] = None):
        self.cfg = cfg
        self.mount = mount or LiveMount()
        self.model_path = model
        self.threads = threads
        self.lock = threading.Lock()
        self.source: Optional[TapSource] = None
        self.engine = None
        self.hub = None
        self.error: Optional[str] = None
        self.state = "off"  # off, starting, running

    def offer(self, fs) -> None:
        src = self.source
        if src is not None:
            src.offer(fs)

    def start(self) -> dict:
        with self.lock:
            if self.state != "off":
                return self.status()
            self.state, self.error = "starting", None
        try:
            engine, source = self._build()
        except (ConfigError, RigError) as exc:
            with self.lock:
                self.state, self.error = "off", str(exc)
            raise
        except Exception as exc:  # a model that does not load must not take the console with it
            log.exception("console live view")
            with self.lock:
                self.state, self.error = "off", f"the live view did not start: {exc}"
            raise RigError(self.error) from None
        from rig.live.server import create_app

        engine.start()
        app = create_app(engine, token=None)  # the console's guard is in front of it
        with self.lock:
            self.engine, self.source, self.hub, self.state = engine, source, app.state.live, "running"
            self.mount.app = app
        return self.status()

    def _build(self):
        from rig.live.app import check_frame_sizes, open_model, rig_calibration, source_cameras
        from rig.live.engine import LiveEngine

        left, right = source_cameras(self.cfg)
        rig = rig_calibration(self.cfg, None, None)
        for name in (left, right):
            if name not in rig:
                raise ConfigError(f"calibration has no camera '{name}' (it has: {', '.join(rig.names)})")
        check_frame_sizes(self.cfg, rig, (left, right), None, None)
        model = open_model(self.model_path, None, self.threads)
        source = TapSource(left, right)
        return LiveEngine(source, rig, left, right, model), source

    def stop(self) -> dict:
        with self.lock:
            engine, hub = self.engine, self.hub
            self.engine = self.source = self.hub = None
            self.mount.app = None
            self.state = "off"
        if hub is not None:
            hub.close()
        if engine is not None:
            engine.stop()
        return self.status()

    def status(self) -> dict:
        s = {"state": self.state, "error": self.error, "url": "live/"}
        engine = self.engine
        if engine is not None:
            try:
                e = engine.status()
                s.update({k: e.get(k) for k in ("fps_in", "fps_out", "latency_ms", "health") if k in e})
            except Exception as exc:
                s["error"] = str(exc)
        return s
