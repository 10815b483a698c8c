"""`rig daemon --board -c RIG.toml`: the trigger board's owner, as a process of its own.

It opens the rig's trigger board (the serial port, or for a `sim://` trigger its emulator, whose
pulse output fires the camera daemons' trigger inputs) and relays it to the sessions that use it
(rig.daemon.board_client.RemoteBoard):

- control, HTTP JSON on loopback: `POST /rate?rate_hz=R&pulse_width_us=W`, `POST /start?pulses=N`,
  `POST /stop`, `GET /status` (the board's report, its clock model included);
- pulses, board events and the board clock model's current fit, one JSON datagram each, to every
  session subscribed on its UDP event port (a subscription is renewed every second and lapses after
  five); the clock fit goes out with every pulse and twice a second besides, so a session maps board
  times to host times exactly as the owner's model does.

Its info file (<root>/<rig>/@board.json) carries a heartbeat the supervisor watches.
"""
from __future__ import annotations

import dataclasses
import json
import os
import socket
import threading
import time
from typing import Any, Optional

from fastapi import FastAPI
from fastapi.responses import JSONResponse

from common.files import atomic_write_json
from rig.boards import open_board
from rig.cameras.daemon import TRIGGER
from rig.config import RigConfig
from rig.daemon import paths
from rig.errors import ConfigError, DeviceError
from rig.http_access import AccessGuard
from sync.board import BoardEvent, Pulse, TriggerBoard
from sync.errors import TriggerBoardError
from sync.frames import monotonic_ns

SUBSCRIPTION_S = 5.0
CLOCK_EVERY_S = 0.5


def fit_dict(clock) -> Optional[dict[str, Any]]:
    fit = clock.fit
    return None if fit is None else {**dataclasses.asdict(fit), "age_s": clock.age_s()}


class BoardDaemon:
    def __init__(self, config: RigConfig):
        if config.trigger is None:
            raise ConfigError(f"rig '{config.name}' has no [trigger] board to own")
        self.config = config
        self.board: Optional[TriggerBoard] = None
        self.emulator = None
        self.stop_event = threading.Event()
        self._subs: dict[tuple, float] = {}  # subscriber address -> lapses at (monotonic s)
        self._lock = threading.Lock()
        self._sock: Optional[socket.socket] = None
        self._udp_out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._ports: dict[str, tuple[float, Optional[int]]] = {}  # camera -> (looked up at, trigger port)
        self.api = None

    # --- the emulator's outputs: the camera daemons' trigger inputs ------------------------------------
    def _camera_port(self, name: str) -> Optional[int]:
        at, port = self._ports.get(name, (0.0, None))
        if port is None or time.monotonic() - at > 0.5:  # a restarted daemon has a new port
            info = paths.read_json(paths.info_path(self.config.name, name))
            port = info.get("trigger_port") if info else None
            self._ports[name] = (time.monotonic(), port)
        return port

    def _fire(self, name: str, pulse: int, host_ns: int) -> None:
        port = self._camera_port(name)
        if port:
            try:
                self._udp_out.sendto(TRIGGER.pack(b"H", pulse, host_ns), ("127.0.0.1", int(port)))
            except OSError:
                pass

    # --- relaying ------------------------------------------------------------------------------------
    def _send(self, message: dict) -> None:
        data = json.dumps(message, separators=(",", ":")).encode()
        now = time.monotonic()
        with self._lock:
            subs = [a for a, until in self._subs.items() if until > now]
            self._subs = {a: u for a, u in self._subs.items() if u > now}
        for address in subs:
            try:
                self._sock.sendto(data, address)
            except OSError:
                pass

    def _on_pulse(self, pulse: Pulse) -> None:
        self._send({"t": "pulse", "index": pulse.index, "board_us": pulse.board_us, "received_ns": pulse.received_ns,
                    "late": pulse.late, "clock": fit_dict(self.board.clock)})

    def _on_event(self, event: BoardEvent) -> None:
        self._send({"t": "event", "kind": event.kind, "detail": event.detail, "time_ns": event.time_ns, "values": event.values})

    def _listen(self) -> None:
        while not self.stop_event.is_set():
            try:
                data, address = self._sock.recvfrom(64)
            except socket.timeout:
                continue
            except OSError:
                return
            if data == b"SUB":
                with self._lock:
                    self._subs[address] = time.monotonic() + SUBSCRIPTION_S
                self._send_clock()
            elif data == b"UNSUB":
                with self._lock:
                    self._subs.pop(address, None)

    def _send_clock(self) -> None:
        self._send({"t": "clock", "clock": fit_dict(self.board.clock), "connected": self.board.connected,
                    "rate_hz": self.board.rate_hz, "pulse_width_us": self.board.pulse_width_us})

    # --- lifecycle -----------------------------------------------------------------------------------
    def open(self) -> "BoardDaemon":
        from rig.daemon import notify
        from rig.daemon.api import ApiServer

        trig = self.config.trigger
        # the cameras are in their daemons: an emulated board fires their trigger inputs by datagram
        hardware = [c.name for c in self.config.cameras if c.trigger == "hardware"]
        self.board, self.emulator = open_board(trig, {n: (lambda i, ns, n=n: self._fire(n, i, ns)) for n in hardware})
        self.board.subscribe(on_pulse=self._on_pulse, on_event=self._on_event)
        try:
            self.board.connect()
            self.board.set_rate(trig.rate_hz, trig.pulse_width_us)
        except TriggerBoardError as exc:
            raise DeviceError(f"trigger board {trig.uri}: {exc}") from None
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(0.2)
        threading.Thread(target=self._listen, name="rig-board-relay", daemon=True).start()
        self.api = ApiServer(self._app(), "127.0.0.1", 0).start()
        self._publish()
        notify.ready(f"trigger board {trig.uri}")
        return self

    def _publish(self) -> None:
        atomic_write_json(paths.board_info_path(self.config.name), {
            "rig": self.config.name, "pid": os.getpid(), "uri": self.config.trigger.uri, "api": self.api.url,
            "event_port": self._sock.getsockname()[1], "heartbeat_ns": monotonic_ns(), "kind": "board"})

    def _app(self) -> FastAPI:
        app = FastAPI(title="rig trigger board daemon", docs_url=None, redoc_url=None, openapi_url=None)
        app.add_middleware(AccessGuard, token=None)

        def call(fn, *args):
            try:
                fn(*args)
            except TriggerBoardError as exc:
                return JSONResponse({"error": str(exc)}, status_code=503)
            return {"ok": True}

        @app.post("/rate")
        def rate(rate_hz: float, pulse_width_us: float):
            return call(self.board.set_rate, rate_hz, pulse_width_us)

        @app.post("/start")
        def start(pulses: int = 0):
            if pulses < 0:
                return JSONResponse({"error": "pulses must be 0 (until stop) or more"}, status_code=400)
            return call(self.board.start, pulses)

        @app.post("/stop")
        def stop():
            return call(self.board.stop)

        @app.get("/status")
        def status():
            return {"report": self.board.report(), "rate_hz": self.board.rate_hz, "pulse_width_us": self.board.pulse_width_us}

        return app

    def run(self) -> None:
        from rig.daemon import notify

        watchdog = notify.Watchdog()
        while not self.stop_event.wait(CLOCK_EVERY_S):
            self._send_clock()
            self._publish()  # the heartbeat
            watchdog.tick()

    def close(self) -> None:
        from rig.daemon import notify

        notify.stopping()
        self.stop_event.set()
        for step in (lambda: self.api and self.api.stop(), lambda: paths.board_info_path(self.config.name).unlink(missing_ok=True),
                     lambda: self.board and self.board.close(), lambda: self.emulator and self.emulator.close(),
                     lambda: self._sock and self._sock.close(), self._udp_out.close):
            try:
                step()
            except Exception:  # noqa: BLE001 - closing: every step is tried
                pass
