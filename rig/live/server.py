"""The live server: moves encoded frames and viewpoint messages between the engine and browsers.

    create_app(engine, token) -> FastAPI        the routes below
    serve(engine, host, port, token) -> LiveServer   started in a thread: .port, .url, .stop()
    LiveServer(...).run()                        the same in the calling thread, until SIGINT/SIGTERM

Routes (`token` set: every one needs it, as `?token=`, `Authorization: Bearer`, or the cookie the
page sets when loaded with `?token=`; without it the answer is 401 and nothing else, the WebSocket
handshake included, which is refused with an HTTP 401 before it is accepted):

    GET /                   the viewer page; GET /static/...  its script and style
    WS  /ws                 one per viewer (rig/live/protocol.py): frames out, at most CREDIT
                            unacknowledged; viewpoint and ack messages in; hello and status out
    GET /status             engine.status() as JSON
    GET /snapshot.png       a PNG at ?t=0.5 or ?preset=NAME (any viewpoint field; default halfway);
                            400 for a bad viewpoint, 503 when no frame set arrived in time
    GET /mjpeg              multipart/x-mixed-replace MJPEG (VLC, ffplay) at a viewpoint as above;
                            each client is a viewer of its own

`token=None` is for a loopback bind only (`rig live` gives a non-loopback bind a token): such a
server answers only requests whose Host is a loopback name (no DNS rebinding), and a WebSocket
handshake from a page of another origin is refused (403) whether or not there is a token.

The engine's methods block: they run on the server's own thread pool, never on the event loop, so
a slow engine call or a slow viewer holds only its own connection.
"""
from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import signal
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Optional

import uvicorn
from fastapi import FastAPI, Request, WebSocket
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from starlette.background import BackgroundTask
from starlette.websockets import WebSocketDisconnect

from rig.errors import RigError
from rig.http_access import AccessGuard, bind_socket, token_matches
from rig.live import protocol
from rig.live.api import Engine, Viewer

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
COOKIE = "rig_live_token"
CREDIT = 2  # frames in flight per WebSocket viewer (sent, not yet acknowledged)
FRAME_POLL_S = 0.25  # how long one next_frame call waits; also how soon a closed viewer lets go
STATUS_PERIOD_S = 0.5
STATUS_CACHE_S = 0.2  # one engine.status() serves every viewer asking within this long
MAX_VIEWERS = 32  # WebSocket and MJPEG viewers together
WS_MAX_SIZE = 64 * 1024  # a browser message above this closes its connection (1009); above 4 KB it is refused
SNAPSHOT_TIMEOUT_S = 5.0
GRACE_S = 3.0  # how long a stopping server waits for connections to finish
MJPEG_BOUNDARY = "rigliveframe"


# --- the hub: what every connection shares -------------------------------------------------------------------
class _Hub:
    def __init__(self, engine: Engine, max_viewers: int, snapshot_timeout: float):
        self.engine = engine
        self.max_viewers = max_viewers
        self.snapshot_timeout = snapshot_timeout
        # each viewer keeps one thread waiting for its next frame; the rest is for short calls
        self.executor = ThreadPoolExecutor(max_workers=2 * max_viewers + 8, thread_name_prefix="live-server")
        self.stopping = threading.Event()
        self.viewers = 0
        self._status: tuple[float, Optional[dict]] = (0.0, None)
        self._status_lock: Optional[asyncio.Lock] = None

    async def call(self, fn, *args):
        """Run a blocking engine call on the server's pool."""
        return await asyncio.get_running_loop().run_in_executor(self.executor, functools.partial(fn, *args))

    def call_detached(self, fn, *args) -> None:
        """Run it even when the caller is being cancelled (closing a viewer)."""
        try:
            self.executor.submit(fn, *args)
        except RuntimeError:  # the pool is shut down: the server is gone, call it here
            fn(*args)

    async def status(self) -> dict:
        if self._status_lock is None:
            self._status_lock = asyncio.Lock()
        async with self._status_lock:
            at, value = self._status
            if value is None or time.monotonic() - at > STATUS_CACHE_S:
                value = protocol.jsonable(await self.call(self.engine.status))
                self._status = (time.monotonic(), value)
            return value

    def close(self) -> None:
        self.stopping.set()
        self.executor.shutdown(wait=False)  # queued calls (a viewer's removal) still run


def _view_message(request: Request) -> Optional[dict]:
    """A viewpoint message from query parameters (all but the token); None when there are none.
    Numbers become floats ("preset" stays text); the engine checks the fields."""
    msg: dict = {}
    for key, value in request.query_params.items():
        if key == "token":
            continue
        if key == "preset":
            msg[key] = value
            continue
        try:
            number = float(value)
        except ValueError:
            msg[key] = value
            continue
        if not math.isfinite(number):
            raise ValueError(f"{key}: {value!r} is not a finite number")
        msg[key] = number
    return {"type": "viewpoint", **msg} if msg else None


def _bad_request(reason: str) -> JSONResponse:
    return JSONResponse({"error": reason}, status_code=400)


# --- one WebSocket viewer ----------------------------------------------------------------------------------
class _Connection:
    def __init__(self, ws: WebSocket, viewer: Viewer, hub: _Hub):
        self.ws = ws
        self.viewer = viewer
        self.hub = hub
        self.in_flight: list[tuple[int, int]] = []  # (set, viewpoint) sent and not acknowledged
        self.credit_back = asyncio.Event()
        self.send_lock = asyncio.Lock()

    async def send_text(self, text: str) -> None:
        async with self.send_lock:
            await self.ws.send_text(text)

    async def send_bytes(self, data: bytes) -> None:
        async with self.send_lock:
            await self.ws.send_bytes(data)

    async def run(self) -> None:
        await self.send_text(protocol.hello_message(self.viewer.id, await self.hub.call(self.hub.engine.presets)))
        tasks = [asyncio.create_task(c, name=f"live-ws-{self.viewer.id}-{c.__name__}")
                 for c in (self.receiver(), self.sender(), self.status())]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        failure = None
        for t in done:
            exc = t.exception()
            if exc is not None and not isinstance(exc, (WebSocketDisconnect, OSError)):
                failure = exc
        if failure is not None:
            log.error("live: viewer %s: %s", self.viewer.id, failure, exc_info=failure)
            with contextlib.suppress(Exception):
                await self.send_text(protocol.error_message(f"server error: {failure}"))
                await self.ws.close(code=1011)
        elif self.hub.stopping.is_set():
            with contextlib.suppress(Exception):
                await self.ws.close(code=1001)

    async def sender(self) -> None:
        """Frames out, at most CREDIT unacknowledged; the engine replaces what a slow viewer misses."""
        while not self.hub.stopping.is_set():
            while len(self.in_flight) >= CREDIT:
                self.credit_back.clear()
                await self.credit_back.wait()
            frame = await self.hub.call(self.viewer.next_frame, FRAME_POLL_S)
            if frame is None:
                continue
            self.in_flight.append((frame.set_index, frame.viewpoint_id))
            await self.send_bytes(protocol.pack_frame(frame))

    async def receiver(self) -> None:
        while True:
            message = await self.ws.receive()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("text")
            if data is None:
                data = message.get("bytes") or b""
            try:
                parsed = protocol.parse_client_message(data)
            except protocol.ProtocolError as exc:
                await self.send_text(protocol.error_message(str(exc), exc.seq))
                continue
            if isinstance(parsed, protocol.Ack):
                await self.on_ack(parsed)
            else:
                await self.on_viewpoint(parsed)

    async def on_ack(self, ack: protocol.Ack) -> None:
        key = (ack.set_index, ack.viewpoint_id)
        if key not in self.in_flight:
            await self.send_text(protocol.error_message(
                f"ack for set {ack.set_index} viewpoint {ack.viewpoint_id}: no such frame is waiting for an ack", ack.seq))
            return
        self.in_flight.remove(key)
        self.credit_back.set()
        try:
            await self.hub.call(self.viewer.acknowledge, ack.set_index, ack.viewpoint_id)
        except Exception:  # the engine's figures, not this viewer's stream
            log.exception("live: viewer %s: acknowledge failed", self.viewer.id)

    async def on_viewpoint(self, vp: protocol.Viewpoint) -> None:
        try:
            vid = await self.hub.call(self.viewer.set_viewpoint, vp.message)
        except ValueError as exc:
            await self.send_text(protocol.error_message(f"viewpoint: {exc}", vp.seq))
            return
        except Exception as exc:
            log.exception("live: viewer %s: set_viewpoint failed", self.viewer.id)
            await self.send_text(protocol.error_message(f"viewpoint: engine error: {exc}", vp.seq))
            return
        await self.send_text(protocol.viewpoint_reply(int(vid), vp.seq))

    async def status(self) -> None:
        while not self.hub.stopping.is_set():
            try:
                status = await self.hub.status()
            except Exception as exc:
                log.exception("live: engine status failed")
                status = {"error": f"engine status failed: {exc}"}
            await self.send_text(protocol.status_message(status, self.viewer.id))
            await asyncio.sleep(STATUS_PERIOD_S)


# --- the app ----------------------------------------------------------------------------------------------------
def create_app(engine: Engine, token: Optional[str], *, max_viewers: int = MAX_VIEWERS,
               snapshot_timeout: float = SNAPSHOT_TIMEOUT_S) -> FastAPI:
    """The live server's routes over `engine`. `token=None`: loopback use only (see the module doc)."""
    if token is not None and not token:
        raise ValueError("token must be None or a non-empty string")
    hub = _Hub(engine, max_viewers, snapshot_timeout)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        yield
        hub.close()

    app = FastAPI(title="rig live", docs_url=None, redoc_url=None, openapi_url=None, lifespan=lifespan)
    app.state.live = hub
    app.add_middleware(AccessGuard, token=token, cookie=COOKIE)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    async def index(request: Request):
        response = FileResponse(STATIC_DIR / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"})
        given = request.query_params.get("token")
        if token is not None and token_matches(given, token):
            # the page's own requests (script, style, WebSocket) then carry it
            response.set_cookie(COOKIE, token, httponly=True, samesite="strict", path="/")
        return response

    @app.get("/status")
    async def status():
        return JSONResponse(protocol.jsonable(await hub.call(engine.status)), headers={"Cache-Control": "no-store"})

    @app.get("/snapshot.png")
    async def snapshot(request: Request):
        try:
            message = _view_message(request)
            png = await hub.call(engine.snapshot, message, hub.snapshot_timeout)
        except ValueError as exc:
            return _bad_request(f"viewpoint: {exc}")
        if png is None:
            return JSONResponse({"error": f"no frame set arrived within {hub.snapshot_timeout:g} s"}, status_code=503)
        return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})

    @app.get("/mjpeg")
    async def mjpeg(request: Request):
        return await _mjpeg(request, hub, engine)

    @app.websocket("/ws")
    async def ws_viewer(ws: WebSocket):
        await _websocket_viewer(ws, hub, engine)

    return app


async def _mjpeg(request: Request, hub: _Hub, engine: Engine):
    """GET /mjpeg: a viewer of its own (the query's viewpoint) as a multipart JPEG stream; the viewer
    is removed when the stream ends or the client goes."""
    if hub.viewers >= hub.max_viewers:
        return JSONResponse({"error": f"too many viewers (at most {hub.max_viewers})"}, status_code=503)
    try:
        message = _view_message(request)
        viewer = await hub.call(engine.add_viewer, message)
    except ValueError as exc:
        return _bad_request(f"viewpoint: {exc}")
    hub.viewers += 1
    closed = []

    def close() -> None:  # from the stream's end, or the response's background task: once
        if not closed:
            closed.append(True)
            hub.viewers -= 1
            hub.call_detached(engine.remove_viewer, viewer)

    async def parts():
        try:
            while not hub.stopping.is_set():
                frame = await hub.call(viewer.next_frame, FRAME_POLL_S)
                if frame is None:
                    continue
                jpeg = frame.jpeg
                yield (f"--{MJPEG_BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n"
                       f"X-Set-Index: {frame.set_index}\r\n\r\n").encode("ascii") + jpeg + b"\r\n"
        finally:
            close()

    return StreamingResponse(parts(), media_type=f"multipart/x-mixed-replace; boundary={MJPEG_BOUNDARY}",
                             headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
                             background=BackgroundTask(close))


async def _websocket_viewer(ws: WebSocket, hub: _Hub, engine: Engine) -> None:
    """/ws: a viewer steered by its messages (`_Connection`), removed when the socket closes."""
    await ws.accept()
    if hub.viewers >= hub.max_viewers:
        await ws.send_text(protocol.error_message(f"too many viewers (at most {hub.max_viewers})"))
        await ws.close(code=1013)
        return
    hub.viewers += 1
    try:
        try:
            viewer = await hub.call(engine.add_viewer)
        except Exception as exc:
            log.exception("live: add_viewer failed")
            await ws.send_text(protocol.error_message(f"engine error: {exc}"))
            await ws.close(code=1011)
            return
        try:
            await _Connection(ws, viewer, hub).run()
        except WebSocketDisconnect:  # gone before its hello
            pass
        finally:
            hub.call_detached(engine.remove_viewer, viewer)
    finally:
        hub.viewers -= 1


# --- running it ---------------------------------------------------------------------------------------------
class _Uvicorn(uvicorn.Server):
    def __init__(self, config: uvicorn.Config, hub: _Hub):
        super().__init__(config)
        self.hub = hub

    @contextlib.contextmanager
    def capture_signals(self):
        """SIGINT/SIGTERM stop the server (in the main thread only); unlike uvicorn's own, the
        signal is not raised again afterwards, so run() returns normally."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {sig: signal.signal(sig, self.handle_exit) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    async def shutdown(self, sockets=None) -> None:
        self.hub.stopping.set()  # MJPEG streams and frame senders end, so their connections can close
        await super().shutdown(sockets=sockets)


class LiveServer:
    """The app on uvicorn, on a socket bound at construction (port 0: any free port; `.port` says
    which). `start()` runs it in a thread (`stop()` from any thread ends it); `run()` runs it in the
    calling thread until `stop()`, or SIGINT/SIGTERM when that is the main thread."""

    def __init__(self, engine: Engine, host: str = "127.0.0.1", port: int = 8080, token: Optional[str] = None, *,
                 log_level: str = "warning", sock: Optional[socket.socket] = None, **app_options):
        """`sock`: a listening socket bound beforehand (rig.http_access.bind_socket; `rig live` binds
        before it opens the cameras and the model), else one is bound here on host:port."""
        self.app = create_app(engine, token, **app_options)
        self.host = host
        self._sock = sock if sock is not None else bind_socket(host, port, "live")
        self.port: int = self._sock.getsockname()[1]
        config = uvicorn.Config(self.app, log_config=None, log_level=log_level, access_log=False, lifespan="on",
                                ws_per_message_deflate=False, ws_max_size=WS_MAX_SIZE,
                                timeout_graceful_shutdown=GRACE_S, server_header=False)
        self._server = _Uvicorn(config, self.app.state.live)
        self._thread: Optional[threading.Thread] = None
        self._failure: Optional[BaseException] = None
        self._ran = False

    @property
    def url(self) -> str:
        host = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(self.host, self.host)
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}/"

    def run(self) -> None:
        if self._ran:
            raise RuntimeError("a LiveServer runs once")
        self._ran = True
        try:
            self._server.run(sockets=[self._sock])
        except SystemExit as exc:  # uvicorn's way to say the startup failed
            raise RigError(f"live: the server did not start (exit {exc.code})") from None
        finally:
            self.app.state.live.close()
            self._sock.close()

    def start(self, timeout: float = 15.0) -> "LiveServer":
        def target():
            try:
                self.run()
            except BaseException as exc:  # reported by start()
                self._failure = exc

        self._thread = threading.Thread(target=target, name=f"live-server-{self.port}", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise RigError(f"live: the server did not start: {self._failure or 'timed out'}")
            time.sleep(0.01)
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Stop serving: viewers are closed (1001/1012), MJPEG streams end; returns once it is down."""
        self._server.should_exit = True
        self.app.state.live.stopping.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
            if self._thread.is_alive():
                self._server.force_exit = True
                self._thread.join(timeout)
        elif not self._ran:
            self._sock.close()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def __enter__(self) -> "LiveServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def serve(engine: Engine, host: str = "127.0.0.1", port: int = 8080, token: Optional[str] = None, **options) -> LiveServer:
    """Start serving `engine` in a background thread; returns the running server (`.port`, `.url`,
    `.stop()`). The caller keeps the main thread (and its Ctrl-C)."""
    return LiveServer(engine, host, port, token, **options).start()
