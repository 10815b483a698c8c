"""The console's web server (FastAPI on uvicorn, as `rig live`): one page that runs the rig.

Routes (access: rig/console/access.py; every state change needs the operator's role):

    GET  /                       the page; GET /static/...  its script and style
    GET  /api/status             cameras (name, role, fps, target_fps, dropped, age_s, health,
                                 exposure_us, gain, ranges), recording (state, take, sets, lost, ...),
                                 takes (with their validation), events, disk, role
    POST /api/controls           {"camera": NAME | "*", "exposure_us": x, "gain": y}: set live, read back
    POST /api/record/start       {"take": NAME, "notes": TEXT, "seconds": S, "codec": "raw" | "png"} (all optional)
    POST /api/record/stop
    POST /api/live/start         starts `rig live`'s engine on the console's frame sets; its page at /live/
    POST /api/live/stop
    GET  /live/...               `rig live`'s viewer and routes (/live/ws, /live/status, ...) while it runs
    POST /api/calibration/start  {"auto": bool}: stills with the board drawn; views kept when it is still and adds coverage
    POST /api/calibration/auto   {"auto": bool}
    POST /api/calibration/capture  keep the next set in which the board is seen
    POST /api/calibration/stop
    POST /api/calibration/solve  rig calibrate run's solve; written where the config names the calibration
    POST /api/doctor             rig doctor's checks; their lines in status's health
    POST /api/sync-check         {"seconds": N}: rig sync check's own run; its verdict in status's sync.check
    PUT  /api/notes              {"take": NAME, "text": TEXT}: saved as typed
    GET  /api/take-name          the name offered next (?after=LAST counts it up)
    WS   /ws                     status out (JSON, every STATUS_S); previews out (binary: 4-byte header
                                 length, JSON header {camera, seq, histogram, clipped}, JPEG), at most one
                                 unacknowledged per camera, at the viewer's rate: a frame not yet sent is
                                 replaced by a newer one, never queued. In: {"type": "prefs", "rate": fps
                                 (0: off), "width": px, "sizes": {camera: px}, "overlay": [camera, ...]} and
                                 {"type": "ack", "camera": NAME}.

Every bad value is one line of JSON ({"error": ...}, 400) and changes nothing.
"""
from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import math
import struct
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Optional

import uvicorn
from fastapi import FastAPI, Request, WebSocket
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.websockets import WebSocketDisconnect

from rig.console import previews, takes as take_names
from rig.console.access import COOKIE, MAX_BODY, ConsoleGuard
from rig.errors import ConfigError, RigError
from rig.http_access import bind_socket, token_matches

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
STATUS_S = 0.25
MAX_RATE = 30.0
DEFAULT_RATE = 5.0
WS_MAX_SIZE = 16 * 1024
MAX_VIEWERS = 16
GRACE_S = 3.0


def _bad(reason: str, status: int = 400) -> JSONResponse:
    return JSONResponse({"error": reason}, status_code=status)


async def _body(request: Request) -> dict:
    raw = await request.body()
    if len(raw) > MAX_BODY:
        raise ConfigError(f"a request body is limited to {MAX_BODY} bytes")
    if not raw:
        return {}
    try:
        data = json.loads(raw)
    except ValueError:
        raise ConfigError("the body is not JSON") from None
    if not isinstance(data, dict):
        raise ConfigError("the body must be a JSON object")
    return data


def _number_or_none(data: dict, key: str):
    v = data.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{key} must be a finite number, got {v!r}")
    return float(v)


def _only(data: dict, allowed: set) -> None:
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise ConfigError(f"unknown field {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")


def create_app(rig, operator_token: Optional[str] = None, viewer_token: Optional[str] = None) -> FastAPI:
    executor = ThreadPoolExecutor(max_workers=2 * MAX_VIEWERS + 8, thread_name_prefix="console")
    stopping = threading.Event()
    viewers = {"n": 0}

    async def call(fn, *args, **kw):
        return await asyncio.get_running_loop().run_in_executor(executor, functools.partial(fn, *args, **kw))

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        yield
        stopping.set()
        executor.shutdown(wait=False)

    app = FastAPI(title="rig console", docs_url=None, redoc_url=None, openapi_url=None, lifespan=lifespan)
    app.state.stopping = stopping
    app.add_middleware(ConsoleGuard, operator_token=operator_token, viewer_token=viewer_token)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    if rig.live is None:
        from rig.console.live import ConsoleLive

        rig.live = ConsoleLive(rig.cfg)
    app.mount("/live", rig.live.mount)

    def role_of(request) -> str:
        return request.scope.get("state", {}).get("role", "viewer")

    async def guarded(fn, *args, **kw):
        try:
            return JSONResponse(await call(fn, *args, **kw), headers={"Cache-Control": "no-store"})
        except ConfigError as exc:
            return _bad(str(exc))
        except RigError as exc:
            return _bad(str(exc), 409)

    @app.get("/", include_in_schema=False)
    async def index(request: Request):
        response = FileResponse(STATIC_DIR / "console.html", media_type="text/html", headers={"Cache-Control": "no-cache"})
        given = request.query_params.get("token")
        if given and any(t is not None and token_matches(given, t) for t in (operator_token, viewer_token)):
            response.set_cookie(COOKIE, given, httponly=True, samesite="strict", path="/")
        return response

    @app.get("/api/status")
    async def status(request: Request):
        s = await call(rig.status)
        s["role"] = role_of(request)
        return JSONResponse(s, headers={"Cache-Control": "no-store"})

    @app.get("/api/take-name")
    async def take_name(request: Request):
        after = request.query_params.get("after")
        return JSONResponse({"take": await call(take_names.suggest, rig.storage, after)})

    @app.post("/api/controls")
    async def controls(request: Request):
        try:
            data = await _body(request)
            _only(data, {"camera", "exposure_us", "gain"})
            camera = data.get("camera")
            if not isinstance(camera, str) or not camera:
                raise ConfigError('camera must be a camera name, or "*" for every camera')
            exposure, gain = _number_or_none(data, "exposure_us"), _number_or_none(data, "gain")
        except ConfigError as exc:
            return _bad(str(exc))
        return await guarded(rig.set_controls, camera, exposure_us=exposure, gain=gain)

    @app.post("/api/record/start")
    async def record_start(request: Request):
        try:
            data = await _body(request)
            _only(data, {"take", "notes", "seconds", "codec"})
            name, notes = data.get("take") or None, data.get("notes")
            seconds = _number_or_none(data, "seconds")
            if seconds is not None and not seconds > 0:
                raise ConfigError(f"seconds must be positive, got {seconds:g}")
            if notes is not None and not isinstance(notes, str):
                raise ConfigError("notes must be text")
        except ConfigError as exc:
            return _bad(str(exc))
        return await guarded(rig.start_take, name, notes, seconds, data.get("codec", "raw"))

    @app.post("/api/record/stop")
    async def record_stop():
        return await guarded(lambda: rig.stop_take() or {"state": "idle"})

    @app.post("/api/sync-check")
    async def sync_check(request: Request):
        try:
            data = await _body(request)
            _only(data, {"seconds"})
            seconds = _number_or_none(data, "seconds")
        except ConfigError as exc:
            return _bad(str(exc))
        return await guarded(rig.start_sync_check, 10.0 if seconds is None else seconds)

    @app.post("/api/live/start")
    async def live_start():
        return await guarded(rig.live.start)

    @app.post("/api/live/stop")
    async def live_stop():
        return await guarded(rig.live.stop)

    async def with_auto(request: Request, fn):
        """`fn(auto)` with the body's {"auto": bool} (default true), checked first."""
        try:
            data = await _body(request)
            _only(data, {"auto"})
            auto = data.get("auto", True)
            if not isinstance(auto, bool):
                raise ConfigError(f"auto must be true or false, got {str(auto)[:20]!r}")
        except ConfigError as exc:
            return _bad(str(exc))
        return await guarded(fn, auto)

    @app.post("/api/calibration/start")
    async def calibration_start(request: Request):
        return await with_auto(request, rig.calibration.start)

    @app.post("/api/calibration/auto")
    async def calibration_auto(request: Request):
        return await with_auto(request, rig.calibration.set_auto)

    @app.post("/api/calibration/capture")
    async def calibration_capture():
        return await guarded(rig.calibration.capture)

    @app.post("/api/calibration/stop")
    async def calibration_stop():
        return await guarded(rig.calibration.stop)

    @app.post("/api/calibration/solve")
    async def calibration_solve():
        return await guarded(rig.calibration.solve)

    @app.post("/api/doctor")
    async def doctor():
        return await guarded(rig.start_doctor)

    @app.put("/api/notes")
    async def notes(request: Request):
        try:
            data = await _body(request)
            _only(data, {"take", "text"})
        except ConfigError as exc:
            return _bad(str(exc))
        return await guarded(lambda: {"saved": str(rig.notes.save(data.get("take"), data.get("text")))})

    @app.websocket("/ws")
    async def ws(socket: WebSocket):
        await socket.accept()
        if viewers["n"] >= MAX_VIEWERS:
            await socket.send_text(json.dumps({"type": "error", "error": f"too many viewers (at most {MAX_VIEWERS})"}))
            await socket.close(code=1013)
            return
        viewers["n"] += 1
        try:
            await _Viewer(socket, rig, call, stopping, role_of(socket)).run()
        except WebSocketDisconnect:
            pass
        finally:
            viewers["n"] -= 1

    return app


class _Viewer:
    """One browser: status pushes and previews at its own rate, one unacknowledged preview per camera."""

    def __init__(self, socket: WebSocket, rig, call, stopping: threading.Event, role: str):
        self.socket, self.rig, self.call, self.stopping, self.role = socket, rig, call, stopping, role
        self.rate = DEFAULT_RATE
        self.width = 320
        self.sizes: dict[str, int] = {}
        self.overlay: set[str] = set()
        self.waiting: set[str] = set()  # cameras with a preview sent and not acknowledged
        self.sent_seq: dict[str, int] = {}
        self.sent_at: dict[str, float] = {}
        self.acked = asyncio.Event()
        self.lock = asyncio.Lock()

    async def send(self, data) -> None:
        async with self.lock:
            if isinstance(data, bytes):
                await self.socket.send_bytes(data)
            else:
                await self.socket.send_text(data)

    async def run(self) -> None:
        tasks = [asyncio.create_task(c) for c in (self.receiver(), self.status(), self.previews())]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        for t in done:
            exc = t.exception()
            if exc is not None and not isinstance(exc, (WebSocketDisconnect, OSError)):
                log.error("console: viewer failed: %s", exc, exc_info=exc)
                with contextlib.suppress(Exception):
                    await self.socket.close(code=1011)

    async def receiver(self) -> None:
        while True:
            message = await self.socket.receive()
            if message["type"] == "websocket.disconnect":
                return
            try:
                self.handle(json.loads(message.get("text") or message.get("bytes") or b""))
            except (ValueError, TypeError, ConfigError) as exc:
                await self.send(json.dumps({"type": "error", "error": str(exc)[:300]}))

    def handle(self, msg) -> None:
        if not isinstance(msg, dict):
            raise ConfigError("a message is a JSON object")
        kind = msg.get("type")
        if kind == "ack":
            self.waiting.discard(str(msg.get("camera")))
            self.acked.set()
        elif kind == "prefs":
            _only(msg, {"type", "rate", "width", "sizes", "overlay"})
            if "rate" in msg:
                rate = _number_or_none(msg, "rate")
                if rate is None or not 0 <= rate <= MAX_RATE:
                    raise ConfigError(f"rate must be from 0 (off) to {MAX_RATE:g} previews per second")
                self.rate = rate
            if "width" in msg:
                w = _number_or_none(msg, "width")
                if w is None or not 16 <= w <= previews.MAX_WIDTH:
                    raise ConfigError(f"width must be from 16 to {previews.MAX_WIDTH} pixels")
                self.width = int(w)
            if "sizes" in msg:
                sizes = msg["sizes"]
                if not isinstance(sizes, dict) or any(not isinstance(v, (int, float)) or isinstance(v, bool) or not 16 <= v <= previews.MAX_WIDTH
                                                      for v in sizes.values()):
                    raise ConfigError(f"sizes maps camera names to widths from 16 to {previews.MAX_WIDTH}")
                self.sizes = {str(k): int(v) for k, v in sizes.items()}
            if "overlay" in msg:
                if not isinstance(msg["overlay"], list):
                    raise ConfigError("overlay is a list of camera names")
                self.overlay = {str(c) for c in msg["overlay"]}
            self.acked.set()
        else:
            raise ConfigError(f"unknown message type {str(kind)[:40]!r} (ack, prefs)")

    async def status(self) -> None:
        while not self.stopping.is_set():
            s = await self.call(self.rig.status)
            s["role"] = self.role
            await self.send(json.dumps({"type": "status", **s}))
            await asyncio.sleep(STATUS_S)

    async def previews(self) -> None:
        while not self.stopping.is_set():
            if self.rate <= 0:
                self.acked.clear()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self.acked.wait(), 0.5)
                continue
            period = 1.0 / self.rate
            now = time.monotonic()
            sent = False
            for name, view in list(self.rig.views.items()):
                image, seq = view.image, view.seq
                if image is None or name in self.waiting or seq == self.sent_seq.get(name):
                    continue
                if now - self.sent_at.get(name, 0.0) < period:
                    continue
                jpeg, stats = await self.call(previews.preview, image, self.sizes.get(name, self.width), name in self.overlay)
                header = json.dumps({"camera": name, "seq": seq, **stats}).encode()
                self.waiting.add(name)
                self.sent_seq[name], self.sent_at[name] = seq, now
                await self.send(struct.pack(">I", len(header)) + header + jpeg)
                sent = True
            if not sent:
                self.acked.clear()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self.acked.wait(), min(period, 0.05))


class ConsoleServer:
    """The app on uvicorn in a thread of its own (`start()`, `stop()`), or in the calling thread (`run()`)."""

    def __init__(self, rig, host: str = "127.0.0.1", port: int = 8090, operator_token: Optional[str] = None,
                 viewer_token: Optional[str] = None, sock=None, log_level: str = "warning"):
        self.app = create_app(rig, operator_token, viewer_token)
        self.host = host
        self._sock = sock if sock is not None else bind_socket(host, port, "console")
        self.port = self._sock.getsockname()[1]
        config = uvicorn.Config(self.app, log_config=None, log_level=log_level, access_log=False, lifespan="on",
                                ws_per_message_deflate=False, ws_max_size=WS_MAX_SIZE, timeout_graceful_shutdown=GRACE_S,
                                server_header=False)
        self._server = uvicorn.Server(config)
        self._thread: Optional[threading.Thread] = None

    @property
    def url(self) -> str:
        host = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(self.host, self.host)
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}/"

    def run(self) -> None:
        try:
            self._server.run(sockets=[self._sock])
        finally:
            self.app.state.stopping.set()
            self._sock.close()

    def start(self, timeout: float = 15.0) -> "ConsoleServer":
        self._thread = threading.Thread(target=self.run, name=f"console-server-{self.port}", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise RigError("console: the server did not start")
            time.sleep(0.01)
        return self

    def stop(self, timeout: float = 10.0) -> None:
        self.app.state.stopping.set()
        self._server.should_exit = True
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
