"""`rig daemon --board -c RIG.toml`: the trigger board's owner, as a process of its own.

It opens the rig's trigger board (the serial port, or for a `sim://` trigger its emulator, whose
pulse output fires the camera daemons' trigger inputs) and relays it to the sessions that use it
(rig.daemon.board_client.RemoteBoard):

- control, HTTP JSON on loopback: `POST /rate?rate_hz=R&pulse_width_us=W`, `POST
  /start?session=S`, `POST /stop?session=S`, `GET /status` (the board's report, its clock model
  included);
- pulses, board events and the board clock model's current fit, one JSON datagram each, to every
  session subscribed on its UDP event port (a subscription is renewed every second and lapses after
  five); the clock fit goes out with every pulse and twice a second besides, so a session maps board
  times to host times exactly as the owner's model does.

Its info file (<root>/<rig>/@board.json) carries a heartbeat the supervisor watches.

Several sessions share the board (`rig live` serving while `rig record` writes takes): the board runs
one pulse train while any session holds it. A session's start is a hold (it joins the train that
runs, or starts it), its stop a release; the board stops when the last hold goes, also when a
session dies without releasing (its subscription lapses). A session that wants N pulses counts
them itself (rig.daemon.board_client), so one session's train never ends another's. A rate other
than the one the board runs at, while another session holds it, is refused (409).
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


class _Busy(TriggerBoardError):
    """The board runs for other sessions at another rate."""
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
        self._holds: set[int] = set()  # sessions holding the pulse train (their event ports)
        self._running = False
        # apart from _lock (taken on the board's thread by every relayed pulse): starting or stopping
        # the board waits for that thread
        self._hold_lock = threading.Lock()
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

    # --- holds on the pulse train ------------------------------------------------------------------------
    def hold(self, session: int) -> dict:
        """`session` holds the train: it starts one when none runs, or joins the running one."""
        with self._hold_lock:
            joined = self._running
            if not self._running:
                self.board.start(0)
                self._running = True
            self._holds.add(int(session))
            return {"ok": True, "joined": joined, "holders": len(self._holds)}

    def release(self, session: int) -> dict:
        """`session` lets go; the last one to let go stops the board."""
        with self._hold_lock:
            self._holds.discard(int(session))
            stopped = False
            if self._running and not self._holds:
                self.board.stop()
                self._running, stopped = False, True
            return {"ok": True, "stopped": stopped, "holders": len(self._holds)}

    def _release_lapsed(self) -> None:
        """A session that died holding the train (its subscription lapsed) lets go of it."""
        now = time.monotonic()
        with self._lock:
            alive = {a[1] for a, until in self._subs.items() if until > now}
        with self._hold_lock:
            gone = {h for h in self._holds if h not in alive}
        for h in gone:
            try:
                self.release(h)
            except TriggerBoardError:
                pass

    def set_rate(self, rate_hz: float, pulse_width_us: float) -> None:
        """The board's rate: refused while the train runs for a session at another rate."""
        with self._hold_lock:
            if self._running and (abs(self.board.rate_hz - rate_hz) > 1e-9 or abs(self.board.pulse_width_us - pulse_width_us) > 1e-9):
                raise _Busy(f"the board runs at {self.board.rate_hz:g} Hz ({self.board.pulse_width_us:g} us pulses) for "
                            f"{len(self._holds)} other session(s); stop them first or use that rate")
            if not self._running:
                self.board.set_rate(rate_hz, pulse_width_us)

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
                out = fn(*args)
            except _Busy as exc:
                return JSONResponse({"error": str(exc)}, status_code=409)
            except TriggerBoardError as exc:
                return JSONResponse({"error": str(exc)}, status_code=503)
            return out if isinstance(out, dict) else {"ok": True}

        @app.post("/rate")
        def rate(rate_hz: float, pulse_width_us: float):
            return call(self.set_rate, rate_hz, pulse_width_us)

        @app.post("/start")
        def start(session: int):
            return call(self.hold, session)

        @app.post("/stop")
        def stop(session: int):
            return call(self.release, session)

        @app.get("/status")
        def status():
            return {"report": self.board.report(), "rate_hz": self.board.rate_hz, "pulse_width_us": self.board.pulse_width_us,
                    "running": self._running, "holders": len(self._holds)}

        return app

    def run(self) -> None:
        from rig.daemon import notify

        watchdog = notify.Watchdog()
        while not self.stop_event.wait(CLOCK_EVERY_S):
            self._send_clock()
            self._release_lapsed()
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
