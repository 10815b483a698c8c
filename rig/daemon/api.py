"""A camera daemon's control API: HTTP JSON, FastAPI on uvicorn in a thread of the daemon.

    GET  /status              state, frames written, fps, camera counters, recent events
    GET  /clock               {"monotonic_ns": this host's monotonic clock} (sync.peer_clock)
    GET  /settings            the camera's settings
    PUT  /settings            {"exposure_us": .., "gain": .., "fps": .., "trigger": ..}: opened again with them
    POST /start, POST /stop   acquisition on / off (the daemon stays up)
    POST /trigger             one software trigger (the camera must be in software-trigger mode)
    GET  /frames/next?after=K&timeout=S
                              the first frame written after sequence K (K = -1: the newest), as raw
                              pixels; its metadata in the X-Rig-Frame header (JSON: the frame's meta,
                              seq, shape, dtype). 204 when none came within the timeout. How a session
                              on another host reads this camera (rig.daemon.client).

Bad input gets a 4xx with {"error": "..."}; nothing a request does stops acquisition except /stop.
Loopback only, unless the daemon has a token (rig.http_access): then every request needs it.
"""
from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time
from typing import Optional

import uvicorn
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response

from rig.daemon.ring import FrameNotReady, FrameOverwritten, RingReader
from rig.errors import ConfigError, DeviceError, RigError
from rig.http_access import AccessGuard, bind_socket
from sync.frames import monotonic_ns

MAX_BODY = 4096
MAX_WAIT_S = 5.0


def _error(status: int, reason: str) -> JSONResponse:
    return JSONResponse({"error": reason}, status_code=status)


async def _change_settings(daemon, request: Request):
    """PUT /settings: a JSON object of settings to change; the camera's settings after the change."""
    body = await request.body()
    if len(body) > MAX_BODY:
        return _error(413, f"request body over {MAX_BODY} bytes")
    try:
        changes = json.loads(body or b"null")
    except ValueError:
        return _error(400, "the body is not JSON")
    if not isinstance(changes, dict):
        return _error(400, 'the body must be a JSON object, e.g. {"exposure_us": 8000}')
    try:
        return await asyncio.get_running_loop().run_in_executor(None, daemon.change_settings, changes)
    except ConfigError as exc:
        return _error(422, str(exc))
    except RigError as exc:
        return _error(503, str(exc))


class _FrameReader:
    """The daemon's ring as GET /frames/next reads it: attached on the first request."""

    def __init__(self, daemon):
        self.daemon = daemon
        self.ring: Optional[RingReader] = None

    def next(self, after: int, timeout: float):
        """(sequence number, frame) of the frame after `after` (-1: the newest), waiting up to
        `timeout` seconds; None when none came."""
        ring = self.ring
        if ring is None:
            ring = self.ring = RingReader.attach(self.daemon.ring.path)
        k = ring.latest() - 1 if after < 0 else after + 1
        k = max(k, ring.latest() - ring.slots + 1, 0)
        if not ring.wait(k, timeout):
            return None
        for _ in range(3):
            try:
                return k, ring.read(k)
            except FrameOverwritten:  # this reader fell a ring behind: the oldest frame still there
                k = max(k + 1, ring.latest() - ring.slots + 1)
            except FrameNotReady:
                return None
        return None


def create_app(daemon, token: Optional[str]) -> FastAPI:
    app = FastAPI(title=f"rig camera daemon {daemon.cfg.name}", docs_url=None, redoc_url=None, openapi_url=None)
    app.add_middleware(AccessGuard, token=token)
    frames = _FrameReader(daemon)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request, exc):  # bad query values: one line, 400
        first = exc.errors()[0] if exc.errors() else {}
        return _error(400, f"bad request: {'.'.join(str(x) for x in first.get('loc', ()))} {first.get('msg', '')}".strip())

    @app.get("/status")
    async def status():
        return daemon.status()

    @app.get("/clock")
    async def clock():
        # this host's monotonic clock: a reader on another host measures its offset (sync.peer_clock)
        return {"monotonic_ns": monotonic_ns()}

    @app.get("/settings")
    async def settings():
        return daemon.settings()

    @app.put("/settings")
    async def put_settings(request: Request):
        return await _change_settings(daemon, request)

    @app.post("/start")
    async def start():
        await asyncio.get_running_loop().run_in_executor(None, daemon.start_acquisition)
        return daemon.status()

    @app.post("/stop")
    async def stop():
        await asyncio.get_running_loop().run_in_executor(None, daemon.stop_acquisition)
        return daemon.status()

    @app.post("/trigger")
    async def trigger():
        try:
            daemon.software_trigger()
        except ConfigError as exc:
            return _error(409, str(exc))
        except DeviceError as exc:
            return _error(503, str(exc))
        return {"triggered": True}

    @app.get("/frames/next")
    async def next_frame(after: int = -1, timeout: float = 1.0):
        if not (0 <= timeout <= MAX_WAIT_S):
            return _error(400, f"timeout must be from 0 to {MAX_WAIT_S:g} s")
        got = await asyncio.get_running_loop().run_in_executor(None, frames.next, after, timeout)
        if got is None:
            return Response(status_code=204)
        k, frame = got
        meta = {**frame.meta(), "seq": k, "shape": list(frame.image.shape), "dtype": str(frame.image.dtype)}
        return Response(frame.image.tobytes(), media_type="application/octet-stream", headers={"X-Rig-Frame": json.dumps(meta)})

    return app


class _ThreadServer(uvicorn.Server):
    @contextlib.contextmanager
    def capture_signals(self):  # the daemon's main thread owns SIGINT / SIGTERM
        yield


class ApiServer:
    """The app on uvicorn in a daemon thread; `port` is the bound one (0 asks for any)."""

    def __init__(self, app: FastAPI, host: str, port: int):
        self.host = host
        self._sock = bind_socket(host, port, "camera daemon API")
        self.port = self._sock.getsockname()[1]
        config = uvicorn.Config(app, log_config=None, log_level="warning", access_log=False, lifespan="off", server_header=False,
                                limit_concurrency=64, timeout_keep_alive=5)
        self._server = _ThreadServer(config)
        self._thread = threading.Thread(target=lambda: self._server.run(sockets=[self._sock]), name="rig-daemon-api", daemon=True)

    @property
    def url(self) -> str:
        host = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(self.host, self.host)
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}"

    def start(self, timeout: float = 10.0) -> "ApiServer":
        self._thread.start()
        deadline = time.monotonic() + timeout
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise RigError(f"camera daemon API on {self.host}:{self.port} did not start")
            time.sleep(0.01)
        return self

    def stop(self) -> None:
        self._server.should_exit = True
        self._thread.join(5)


def serve(daemon, host: str, port: int, token: Optional[str]) -> ApiServer:
    return ApiServer(create_app(daemon, token), host, port).start()
