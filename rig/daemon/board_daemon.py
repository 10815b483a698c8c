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

Across hosts (`--host ADDR --token T`, the board on one host and cameras or sessions on another):
- the same API on ADDR, every request needing the token, and a second event port there whose
  subscriptions must carry the token's tag (rig.cameras.daemon.signed); `GET /status` names it
  (`network_event_port`); the daemon advertises itself on mDNS as camera `@board`, role `board`;
- the board's pulse output reaches the hardware-triggered cameras whose daemons run on other hosts
  (found by mDNS, looked up again every few seconds, so a restarted daemon's new port is found) at
  their network trigger inputs, each trigger tagged with the token: the emulated wire. A real
  board's cable reaches them by itself.
A session on another host names the board `daemon://ADDR:PORT?token=T` (or `daemon://RIG/@board`,
by mDNS) as its trigger URI (rig.daemon.board_client).

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

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from common.files import atomic_write_json
from rig.boards import open_board
from rig.cameras.daemon import TRIGGER, signed, verify
from rig.config import RigConfig
from rig.daemon import paths
from rig.errors import ConfigError, DeviceError
from rig.http_access import AccessGuard
from sync.board import BoardEvent, Pulse, TriggerBoard
from sync.errors import TriggerBoardError
from sync.frames import monotonic_ns
from sync.peer_clock import PeerClock

SUBSCRIPTION_S = 5.0
REWIRE_S = 3.0  # how often the cameras of other hosts are looked up on mDNS
LOOPBACK = ("127.0.0.1", "localhost", "::1")
BOARD_NAME = "@board"  # the board's name among a rig's daemons (rig up, mDNS)


def daemon_status(api_url: str, token: Optional[str], path: str = "/status") -> Optional[dict]:
    """A daemon's `GET /status` (or another GET route), or None when it does not answer."""
    import urllib.request

    req = urllib.request.Request(f"{api_url}{path}", headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=3) as resp:
            return json.loads(resp.read())
    except (OSError, ValueError):
        return None


class _Busy(TriggerBoardError):
    """The board runs for other sessions at another rate."""
CLOCK_EVERY_S = 0.5


def fit_dict(clock) -> Optional[dict[str, Any]]:
    fit = clock.fit
    return None if fit is None else {**dataclasses.asdict(fit), "age_s": clock.age_s()}


class BoardDaemon:
    def __init__(self, config: RigConfig, host: str = "127.0.0.1", port: int = 0, token: Optional[str] = None,
                 advertise: bool = True, interfaces: Optional[list[str]] = None):
        if config.trigger is None:
            raise ConfigError(f"rig '{config.name}' has no [trigger] board to own")
        self.config = config
        self.host, self.port, self.token = host, port, token
        self.networked = token is not None and host not in LOOPBACK
        self.advertise, self.interfaces = advertise and self.networked, interfaces
        self._advert = None
        self._net_sock: Optional[socket.socket] = None
        self.net_api = None
        self._remote: dict[str, tuple[str, int]] = {}  # camera on another host -> its network trigger input
        self._remote_clock: dict[str, Any] = {}  # camera on another host -> its host's clock (sync.peer_clock)
        self.board: Optional[TriggerBoard] = None
        self.emulator = None
        self.stop_event = threading.Event()
        self._subs: dict[tuple, tuple] = {}  # subscriber address -> (lapses at (monotonic s), the socket it came on)
        self._holds: set[str] = set()  # sessions holding the pulse train ("ADDR:EVENT_PORT")
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
        payload, address = TRIGGER.pack(b"H", pulse, host_ns), ("127.0.0.1", port)
        if not port and name in self._remote:
            # an edge's time on the camera's host clock (its simulated exposure is placed by it)
            clock = self._remote_clock.get(name)
            payload = TRIGGER.pack(b"H", pulse, clock.to_peer(host_ns) if clock is not None else host_ns)
            payload, address = signed(self.token, payload), self._remote[name]
        if address[1]:
            try:
                self._udp_out.sendto(payload, (address[0], int(address[1])))
            except OSError:
                pass

    def _rewire(self) -> None:
        """Find the network trigger inputs of the hardware-triggered cameras whose daemons run on
        other hosts (mDNS, then each daemon's status with the token), again every REWIRE_S."""
        from rig.cameras.discovery import browse

        hardware = [c.name for c in self.config.cameras if c.trigger == "hardware"]
        while not self.stop_event.wait(0 if not self._remote else REWIRE_S):
            away = [n for n in hardware if not self._camera_port(n)]
            if not away:
                continue
            try:
                found = {d.camera: d for d in browse(1.0, rig=self.config.name, interfaces=self.interfaces) if d.camera in away}
            except Exception:  # noqa: BLE001 - mDNS unavailable now: try again later
                continue
            for name, d in found.items():
                status = daemon_status(d.api_url, self.token)
                if status and status.get("network_trigger_port"):
                    clock = PeerClock(lambda url=d.api_url: (daemon_status(url, self.token, "/clock") or {})["monotonic_ns"])
                    if clock.refresh():
                        self._remote_clock[name] = clock
                    self._remote[name] = (d.host, int(status["network_trigger_port"]))

    # --- relaying ------------------------------------------------------------------------------------
    def _send(self, message: dict) -> None:
        data = json.dumps(message, separators=(",", ":")).encode()
        now = time.monotonic()
        with self._lock:
            subs = [(a, sock) for a, (until, sock) in self._subs.items() if until > now]
            self._subs = {a: v for a, v in self._subs.items() if v[0] > now}
        for address, sock in subs:
            try:
                sock.sendto(data, address)
            except OSError:
                pass

    def _on_pulse(self, pulse: Pulse) -> None:
        self._send({"t": "pulse", "index": pulse.index, "board_us": pulse.board_us, "received_ns": pulse.received_ns,
                    "late": pulse.late, "clock": fit_dict(self.board.clock)})

    def _on_event(self, event: BoardEvent) -> None:
        self._send({"t": "event", "kind": event.kind, "detail": event.detail, "time_ns": event.time_ns, "values": event.values})

    def _listen(self, sock: socket.socket, tagged: bool) -> None:
        while not self.stop_event.is_set():
            try:
                data, address = sock.recvfrom(128)
            except socket.timeout:
                continue
            except OSError:
                return
            if tagged:  # the network event port: only subscriptions with the token's tag
                data = verify(self.token, data)
                if data is None:
                    continue
            if data == b"SUB":
                with self._lock:
                    self._subs[address] = (time.monotonic() + SUBSCRIPTION_S, sock)
                self._send_clock()
            elif data == b"UNSUB":
                with self._lock:
                    self._subs.pop(address, None)

    # --- holds on the pulse train ------------------------------------------------------------------------
    def hold(self, session: str) -> dict:
        """`session` holds the train: it starts one when none runs, or joins the running one."""
        with self._hold_lock:
            joined = self._running
            if not self._running:
                self.board.start(0)
                self._running = True
            self._holds.add(session)
            return {"ok": True, "joined": joined, "holders": len(self._holds)}

    def release(self, session: str) -> dict:
        """`session` lets go; the last one to let go stops the board."""
        with self._hold_lock:
            self._holds.discard(session)
            stopped = False
            if self._running and not self._holds:
                self.board.stop()
                self._running, stopped = False, True
            return {"ok": True, "stopped": stopped, "holders": len(self._holds)}

    def _release_lapsed(self) -> None:
        """A session that died holding the train (its subscription lapsed) lets go of it."""
        now = time.monotonic()
        with self._lock:
            alive = {f"{a[0]}:{a[1]}" for a, (until, _) in self._subs.items() if until > now}
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
        threading.Thread(target=self._listen, args=(self._sock, False), name="rig-board-relay", daemon=True).start()
        self.api = ApiServer(self._app(None), "127.0.0.1", 0).start()
        if self.networked:
            self._net_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._net_sock.bind((self.host, 0))
            self._net_sock.settimeout(0.2)
            threading.Thread(target=self._listen, args=(self._net_sock, True), name="rig-board-net-relay", daemon=True).start()
            self.net_api = ApiServer(self._app(self.token), self.host, self.port).start()
            threading.Thread(target=self._rewire, name="rig-board-rewire", daemon=True).start()
            if self.advertise:
                self._advertise()
        self._publish()
        notify.ready(f"trigger board {trig.uri}")
        return self

    def _advertise(self) -> None:
        try:
            from rig.cameras.discovery import DaemonInfo, advertise

            info = DaemonInfo(rig=self.config.name, camera=BOARD_NAME, role="board", uri=self.config.trigger.uri, model="", serial="",
                              shm="", host=self.host, port=self.net_api.port, pid=os.getpid(), token_required=True)
            self._advert = advertise(info, interfaces=self.interfaces, wait=False)
        except Exception as exc:  # noqa: BLE001 - mDNS is a convenience: the board works without it
            print(f"rig daemon --board: not advertised on mDNS: {exc}", flush=True)

    def _publish(self) -> None:
        atomic_write_json(paths.board_info_path(self.config.name), {
            "rig": self.config.name, "pid": os.getpid(), "uri": self.config.trigger.uri, "api": self.api.url,
            "event_port": self._sock.getsockname()[1], "heartbeat_ns": monotonic_ns(), "kind": "board"})

    def _app(self, token: Optional[str]) -> FastAPI:
        """The control API: on loopback without a token, on the network address with it."""
        app = FastAPI(title="rig trigger board daemon", docs_url=None, redoc_url=None, openapi_url=None)
        app.add_middleware(AccessGuard, token=token)

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

        # a session is named by the address its requests and its subscription come from, and its event port
        @app.post("/start")
        def start(session: int, request: Request):
            return call(self.hold, f"{request.client.host}:{session}")

        @app.post("/stop")
        def stop(session: int, request: Request):
            return call(self.release, f"{request.client.host}:{session}")

        @app.get("/status")
        def status():
            return {"report": self.board.report(), "rate_hz": self.board.rate_hz, "pulse_width_us": self.board.pulse_width_us,
                    "running": self._running, "holders": len(self._holds), "uri": self.config.trigger.uri, "pid": os.getpid(),
                    "network_event_port": self._net_sock.getsockname()[1] if self._net_sock else None,
                    "remote_cameras": sorted(self._remote), "monotonic_ns": monotonic_ns()}

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
        for step in (lambda: self._advert and self._advert.close(), lambda: self.net_api and self.net_api.stop(),
                     lambda: self._net_sock and self._net_sock.close(), lambda: self.api and self.api.stop(), lambda: paths.board_info_path(self.config.name).unlink(missing_ok=True),
                     lambda: self.board and self.board.close(), lambda: self.emulator and self.emulator.close(),
                     lambda: self._sock and self._sock.close(), self._udp_out.close):
            try:
                step()
            except Exception:  # noqa: BLE001 - closing: every step is tried
                pass
