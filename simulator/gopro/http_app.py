"""The emulated GoPro's HTTP API (FastAPI): the routes of the Open GoPro specification that the
product and the official SDK use, each answering as the specification says. What a route does is
the emulator's business (`GoProEmulator`); this module parses the request and shapes the answer.

Every answer is JSON (the SDK parses every body), an empty object where the specification
answers "200Empty". Webcam commands answer `{"status", "error"}` (the webcam's state after the
command): the specification's empty object allows it, and the SDK reads `error` from every
webcam command.

In front of the routes, `FaultGate` logs each request and applies the injected faults: a dead link
holds a request until the link is back (TCP would deliver it late, and a client that gave up has
gone by then); an injected error answers with its status instead of the route.
"""
from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
import time
from typing import TYPE_CHECKING, Optional
from urllib.parse import parse_qsl

import uvicorn
from fastapi import FastAPI, Query, Request
from fastapi.responses import JSONResponse, Response

from common.net import listening_socket
from simulator.errors import SimulatorError
from simulator.gopro.camera_state import API_VERSION
from simulator.gopro.ranges import Body, Unsatisfiable, parse_range

if TYPE_CHECKING:
    from simulator.gopro.emulator import GoProEmulator


class FaultGate:
    """ASGI middleware: request log, dead link, injected errors."""

    def __init__(self, app, camera: "GoProEmulator"):
        self.app = app
        self.camera = camera

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        self.camera._log_request(scope)
        while (wait := self.camera.faults.link_down_for()) > 0:
            await asyncio.sleep(wait)
        status = self.camera.faults.take_error()
        if status is not None:
            return await JSONResponse({}, status_code=status)(scope, receive, send)
        return await self.app(scope, receive, send)


class _ExpectedCuts(logging.Filter):
    """uvicorn logs a body that ends short as an error; a cut the emulator made on purpose is not one."""

    def __init__(self):
        super().__init__()
        self._lock = threading.Lock()
        self._pending = 0

    def expect(self) -> None:
        with self._lock:
            self._pending += 1

    def filter(self, record: logging.LogRecord) -> bool:
        if record.getMessage() != "ASGI callable returned without completing response.":
            return True
        with self._lock:
            if self._pending:
                self._pending -= 1
                return False
        return True


_CUTS = _ExpectedCuts()
logging.getLogger("uvicorn.error").addFilter(_CUTS)


class _MediaBody(Response):
    """A file (or one range of it) sent through `ranges.Body`; stops when the client has gone."""

    def __init__(self, body: Body, status_code: int, headers: dict[str, str]):
        super().__init__(status_code=status_code, headers=headers, media_type="application/octet-stream")
        self.body_source = body

    async def __call__(self, scope, receive, send):
        gone = asyncio.Event()

        async def watch():
            while True:
                if (await receive())["type"] == "http.disconnect":
                    gone.set()
                    return

        outer_hold = self.body_source.hold

        async def hold() -> bool:
            if outer_hold is not None and not await outer_hold():
                return False
            return not gone.is_set()

        self.body_source.hold = hold
        watcher = asyncio.create_task(watch())
        try:
            await send({"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers})
            if await self.body_source.send(send) == "cut":
                _CUTS.expect()  # returning without the final body message makes the server close the connection
        finally:
            watcher.cancel()


def create_app(camera: "GoProEmulator") -> FastAPI:
    app = FastAPI(title=f"GoPro emulator {camera.serial}", docs_url=None, redoc_url=None, openapi_url=None)
    _query_and_control(app, camera)
    _presets_and_settings(app, camera)
    _shutter(app, camera)
    _webcam(app, camera)
    _media(app, camera)
    return FaultGate(app, camera)


def _ok() -> JSONResponse:
    return JSONResponse({})  # the specification's 200Empty


def _query_and_control(app: FastAPI, camera: "GoProEmulator") -> None:
    """Version, state, info, keep-alive and who controls the camera."""
    @app.get("/gopro/version")
    def version():
        return {"version": API_VERSION}

    @app.get("/gopro/camera/state")
    def state():
        return camera.state.state_json(camera.media.free_kb())

    @app.get("/gopro/camera/info")
    def info():
        return camera.info()

    @app.get("/gopro/camera/keep_alive")
    def keep_alive():
        camera.keep_alive()
        return _ok()

    @app.get("/gopro/camera/control/wired_usb")
    def wired_usb(p: int = Query(...)):
        if p not in (0, 1):
            return JSONResponse({"error": f"p must be 0 or 1, not {p}"}, status_code=400)
        camera.set_wired_control(bool(p))
        return _ok()

    @app.get("/gopro/camera/control/set_ui_controller")
    def set_ui_controller(p: int = Query(...)):
        if p not in (0, 2):
            return JSONResponse({"error": f"p must be 0 (idle) or 2 (external control), not {p}"}, status_code=400)
        camera.state.camera_control = p
        return _ok()

    @app.get("/gopro/camera/analytics/set_client_info")
    def set_client_info():
        return _ok()


def _presets_and_settings(app: FastAPI, camera: "GoProEmulator") -> None:
    """Presets and settings: read one, load one, set one (a refusal as the specification shapes it)."""
    @app.get("/gopro/camera/presets/get")
    def presets_get(include_hidden: int = Query(0, alias="include-hidden")):
        return camera.state.presets_json()

    @app.get("/gopro/camera/presets/load")
    def presets_load(id: int = Query(...)):
        return _ok() if camera.load_preset(id) else JSONResponse({}, status_code=403)

    @app.get("/gopro/camera/presets/set_group")
    def presets_set_group(id: int = Query(...)):
        return _ok() if camera.load_preset_group(id) else JSONResponse({}, status_code=403)

    @app.get("/gopro/camera/setting")
    def setting(setting: int = Query(...), option: Optional[int] = Query(None)):
        if option is None:
            current = camera.state.setting(setting)
            if current is None:
                return JSONResponse({"error": 2, "setting_id": setting, "supported_options": []}, status_code=403)
            return {"option": current}
        refusal = camera.set_setting(setting, option)
        return _ok() if refusal is None else JSONResponse(refusal.to_json(), status_code=403)


def _shutter(app: FastAPI, camera: "GoProEmulator") -> None:
    """Start and stop recording to the card."""
    @app.get("/gopro/camera/shutter/{mode}")
    def shutter(mode: str):
        if mode == "start":
            camera.shutter_start()
        elif mode == "stop":
            camera.shutter_stop()
        else:
            return JSONResponse({"error": f"mode must be start or stop, not {mode!r}"}, status_code=400)
        return _ok()


def _webcam(app: FastAPI, camera: "GoProEmulator") -> None:
    """Webcam mode: start, stop, exit, preview, status, version."""
    @app.get("/gopro/webcam/start")
    def webcam_start(request: Request, res: Optional[int] = None, fov: Optional[int] = None,
                     port: Optional[int] = None, protocol: Optional[str] = None):
        status, body = camera.webcam_start(request.client.host if request.client else "127.0.0.1",
                                           res=res, fov=fov, port=port, protocol=protocol)
        return JSONResponse(body, status_code=status)

    @app.get("/gopro/webcam/stop")
    def webcam_stop():
        return camera.webcam_stop()

    @app.get("/gopro/webcam/exit")
    def webcam_exit():
        return camera.webcam_exit()

    @app.get("/gopro/webcam/preview")
    def webcam_preview(request: Request):
        return camera.webcam_preview(request.client.host if request.client else "127.0.0.1")

    @app.get("/gopro/webcam/status")
    def webcam_status():
        return camera.webcam_status()

    @app.get("/gopro/webcam/version")
    def webcam_version():
        return {"version": 5, "max_lens_support": True, "usb_3_1_compatible": True}


def _media(app: FastAPI, camera: "GoProEmulator") -> None:
    """The card's media: the list, the last capture and downloads (ranges, HEAD, injected cuts, paced)."""
    @app.get("/gopro/media/list")
    def media_list():
        return camera.media.list_json()

    @app.get("/gopro/media/last_captured")
    def last_captured():
        last = camera.media.last()
        if last is None:
            return Response(status_code=204)
        return {"folder": last.directory, "file": last.name}

    @app.api_route("/videos/DCIM/{directory}/{filename}", methods=["GET", "HEAD"])
    async def download(directory: str, filename: str, request: Request):
        path = camera.media.find(directory, filename)
        if path is None:
            return JSONResponse({"error": f"no media {directory}/{filename}"}, status_code=404)
        size = path.stat().st_size
        try:
            span = parse_range(request.headers.get("range"), size)
        except Unsatisfiable:
            return Response(status_code=416, headers={"Content-Range": f"bytes */{size}", "Accept-Ranges": "bytes"})
        first, last = span if span else (0, size - 1)
        headers = {"Accept-Ranges": "bytes", "Content-Length": str(last - first + 1)}
        if span:
            headers["Content-Range"] = f"bytes {first}-{last}/{size}"
        status = 206 if span else 200
        if request.method == "HEAD" or size == 0:
            return Response(status_code=status, headers=headers, media_type="application/octet-stream")
        body = Body(path, first, last, cut_after=camera.faults.take_cut(), pace=camera.download_bytes_per_s,
                    hold=camera._link_hold)
        return _MediaBody(body, status, headers)


# --- the server ------------------------------------------------------------------------------------
class _ThreadServer(uvicorn.Server):
    @contextlib.contextmanager
    def capture_signals(self):  # the process's main thread owns SIGINT / SIGTERM
        yield


def _bind(host: str, port: int) -> socket.socket:
    try:
        return listening_socket(host, port)
    except OSError as exc:
        raise SimulatorError(f"GoPro emulator: cannot listen on {host}:{port}: {exc.strerror or exc}") from None


class HttpServer:
    """An ASGI app on uvicorn in a daemon thread; port 0 asks for any free port (`port` says which)."""

    def __init__(self, app, host: str, port: int, name: str):
        self.host = host
        self._sock = _bind(host, port)
        self.port = self._sock.getsockname()[1]
        config = uvicorn.Config(app, log_config=None, log_level="warning", access_log=False, lifespan="off",
                                server_header=False, timeout_keep_alive=5, timeout_graceful_shutdown=1)
        self._server = _ThreadServer(config)
        self._thread = threading.Thread(target=lambda: self._server.run(sockets=[self._sock]), name=name, daemon=True)

    def start(self, timeout: float = 10.0) -> "HttpServer":
        self._thread.start()
        deadline = time.monotonic() + timeout
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise SimulatorError(f"GoPro emulator: the HTTP server on {self.host}:{self.port} did not start")
            time.sleep(0.01)
        return self

    def stop(self) -> None:
        self._server.should_exit = True
        self._thread.join(5)
        with contextlib.suppress(OSError):
            self._sock.close()


def query_of(scope) -> dict[str, str]:
    return dict(parse_qsl(scope.get("query_string", b"").decode("latin-1"), keep_blank_values=True))
