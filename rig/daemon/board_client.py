"""A session's view of a trigger board owned by its daemon (rig.daemon.board_daemon), with the part of
`sync.board.TriggerBoard`'s interface a `RigSession` uses: connect, set_rate, start, stop, wait_done,
warm_up, subscribe, connected, clock, report, close.

Pulses and events arrive as datagrams; `clock` mirrors the owner's clock model (the fit that came with
the last pulse or clock message), so board times map to host times as the owner maps them. When the
owner's messages stop for `LOST_S` the board is reported disconnected; when a (restarted) owner
speaks again, connected again (`reconnect`), and the session restarts its train as it does for a
board plugged back in.

The board is shared (`rig live` beside `rig record`): `start` holds the daemon's train, joining it if
another session runs it, and `stop` lets go. This session's train is the pulses from its start on,
numbered from 0 as a train of its own; a train of N pulses ends here after N (a "done" event made
here), never for the other sessions.
"""
from __future__ import annotations

import http.client
import json
import socket
import threading
import time
from typing import Any, Callable, Optional
from urllib.parse import urlencode, urlsplit

from rig.boards import open_board as open_in_process
from rig.daemon import paths
from sync.board import BoardEvent, Pulse
from sync.clock import ClockFit
from sync.errors import TriggerBoardError
from sync.frames import monotonic_ns

LOST_S = 1.5
RENEW_S = 1.0
BOARD_BACK_S = 15.0  # how long a session waits for a board daemon that died to be restarted


def board_daemon(rig: str) -> Optional[dict[str, Any]]:
    """The info of the live trigger board daemon of this rig on this host, or None."""
    info = paths.read_json(paths.board_info_path(rig))
    return info if info is not None and paths.pid_alive(info.get("pid")) else None


def open_board(config, inputs: dict[str, Callable[[int, int], None]]):
    """The rig's trigger board through its daemon: the one on another host that the trigger URI names
    (`daemon://HOST:PORT?token=T`, `daemon://RIG/@board?token=T` by mDNS), or the one that owns it on
    this host; else opened in this process by its backend (rig.boards), with the cameras of `inputs`
    opened here too. Returns the board and the device behind it to close after it (None through a
    daemon)."""
    if config.trigger.uri.startswith("daemon://"):
        return NetworkBoard(config.name, config.trigger.uri), None
    owner = board_daemon(config.name) or board_daemon_back(config.name)
    if owner is not None:
        return RemoteBoard(config.name, owner), None
    return open_in_process(config.trigger, inputs, config)


def board_daemon_back(rig: str, within_s: Optional[float] = None) -> Optional[dict[str, Any]]:
    """The info of this rig's board daemon once it is back, when one died and left its info behind
    (its supervisor restarts it within seconds); None when no daemon ran the board. Opening the board
    in this process in that gap ran a second pulse train beside the restarted daemon's: the cameras
    were fired at twice the rate, and a take paired frames of different pulses."""
    path = paths.board_info_path(rig)
    stale = paths.read_json(path)
    if stale is None:
        return None
    within_s = BOARD_BACK_S if within_s is None else within_s
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        info = board_daemon(rig)
        if info is not None:
            return info
        time.sleep(0.1)
    raise TriggerBoardError(f"the trigger board daemon of rig '{rig}' (pid {stale.get('pid')}) is gone and did not come back within "
                            f"{within_s:.0f} s: run `rig up`, or remove {path} to drive the board from this process")


class MirrorClock:
    """The owner's clock fit, as last received; with `peer` (the owner on another host), host times
    on this host's clock (sync.peer_clock)."""

    def __init__(self, peer=None) -> None:
        self.fit: Optional[ClockFit] = None
        self._age = 0.0
        self.peer = peer

    def update(self, d: Optional[dict]) -> None:
        if d:
            self._age = float(d.pop("age_s", 0.0))
            self.fit = ClockFit(**d)

    @property
    def ready(self) -> bool:
        return self.fit is not None

    def board_to_host_ns(self, board_us: float) -> int:
        if self.fit is None:
            raise RuntimeError("clock model has no samples yet")
        ns = self.fit.board_to_host_ns(board_us)
        return self.peer.to_local(ns) if self.peer is not None else ns

    def host_to_board_us(self, host_ns: int) -> float:
        if self.fit is None:
            raise RuntimeError("clock model has no samples yet")
        return self.fit.host_to_board_us(self.peer.to_peer(host_ns) if self.peer is not None else host_ns)

    def age_s(self) -> float:
        return self._age

    def stats(self) -> dict:
        f = self.fit
        return {"fit_samples": f.samples if f else 0, "span_s": f.span_us / 1e6 if f else 0.0, "drift_ppm": f.drift_ppm if f else None,
                "fit_residual_p99_us": f.residual_p99_us if f else None, "margin_us": f.margin_us if f else None, "relayed": True}


class RemoteBoard:
    """The board through its daemon on this host (found by its info file)."""

    BIND = "127.0.0.1"
    HEADERS: dict[str, str] = {}

    def __init__(self, rig: str, info: dict[str, Any]):
        self.rig = rig
        self.info = info
        self.uri = f"{info.get('uri')} (through its daemon, pid {info.get('pid')})"
        self.clock = MirrorClock()
        self.rate_hz: Optional[float] = None
        self.pulse_width_us: Optional[float] = None
        self._pulse_listeners: list[Callable[[Pulse], None]] = []
        self._event_listeners: list[Callable[[BoardEvent], None]] = []
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((self.BIND, 0))
        self._sock.settimeout(0.1)
        self._connected = threading.Event()
        self._closed = threading.Event()
        self._done_cv = threading.Condition()
        self._done: Optional[int] = None
        self._train_lock = threading.Lock()
        self._holding = False  # between start and stop: pulses are this session's
        self._first: Optional[int] = None  # the daemon's index of this train's pulse 0
        self._count = 0  # pulses wanted (0: until stop)
        self._forwarded = 0
        self._last_message = 0.0
        self._ever = False
        self._owner_fit = False  # a clock fit came from the current owner
        self._thread: Optional[threading.Thread] = None

    # --- control -------------------------------------------------------------------------------------
    def _post(self, path: str, **query) -> dict:
        parts = urlsplit(self.info["api"])
        conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=5)
        try:
            conn.request("POST", f"{path}?{urlencode(query)}" if query else path, headers=self.HEADERS)
            resp = conn.getresponse()
            body = resp.read()
        except (OSError, http.client.HTTPException) as exc:
            raise TriggerBoardError(f"trigger board daemon {self.info['api']}: {exc}") from None
        finally:
            conn.close()
        if resp.status != 200:
            raise TriggerBoardError(f"trigger board daemon: {json.loads(body or b'{}').get('error', resp.status)}")
        try:
            return json.loads(body or b"{}")
        except ValueError:
            return {}

    def connect(self, timeout: float = 3.0) -> None:
        self._thread = threading.Thread(target=self._listen, name="rig-board-client", daemon=True)
        self._thread.start()
        if not self._connected.wait(timeout):
            raise TriggerBoardError(f"the trigger board daemon of rig '{self.rig}' (pid {self.info.get('pid')}) does not answer")

    def set_rate(self, rate_hz: float, pulse_width_us: float) -> None:
        self._post("/rate", rate_hz=rate_hz, pulse_width_us=pulse_width_us)
        self.rate_hz, self.pulse_width_us = rate_hz, pulse_width_us

    @property
    def session(self) -> int:
        """This session's name to the daemon: its event port (its hold lapses with its subscription)."""
        return self._sock.getsockname()[1]

    def start(self, count: int = 0) -> None:
        with self._done_cv:
            self._done = None
        with self._train_lock:
            self._holding, self._first, self._count, self._forwarded = True, None, int(count), 0
        try:
            self._post("/start", session=self.session)
        except TriggerBoardError:
            with self._train_lock:
                self._holding = False
            raise

    def stop(self) -> None:
        with self._train_lock:
            was = self._holding
            self._holding = False
        try:
            self._post("/stop", session=self.session)
        finally:
            if was:
                self._train_ended("stopped")

    def _train_ended(self, how: str) -> None:
        """This session's train is over: the "done" its session waits for (the board's own DONE
        belongs to the daemon's train, which may run on for others)."""
        pulses = self._forwarded
        with self._done_cv:
            self._done = pulses
            self._done_cv.notify_all()
        self._emit(BoardEvent("done", f"pulse train {how} after {pulses} pulses", monotonic_ns(), {"pulses": pulses}))

    def _own_pulse(self, pulse: Pulse) -> Optional[Pulse]:
        """The daemon's pulse as this session's train numbers it, or None when it is not one of ours."""
        with self._train_lock:
            if not self._holding:
                return None
            if self._first is None:
                self._first = pulse.index
            k = pulse.index - self._first
            if k < 0 or (self._count and k >= self._count):
                return None
            self._forwarded = max(self._forwarded, k + 1)
            last = bool(self._count) and k == self._count - 1
            if last:
                self._holding = False
        own = Pulse(k, pulse.board_us, pulse.received_ns, pulse.late)
        if last:  # N pulses: this session's train is done; the daemon's goes on for the others
            threading.Thread(target=self._let_go_after, args=(own,), name="rig-board-release", daemon=True).start()
        return own

    def _let_go_after(self, pulse: Pulse) -> None:
        try:
            self._post("/stop", session=self.session)
        except TriggerBoardError:
            pass  # the hold lapses with the subscription
        self._train_ended("done")

    def wait_done(self, timeout: float) -> Optional[int]:
        with self._done_cv:
            self._done_cv.wait_for(lambda: self._done is not None, timeout)
            return self._done

    def warm_up(self, seconds: float = 3.0, interval: float = 0.01) -> None:
        """The owner keeps its clock model warm: wait (at most `seconds`) for its fit."""
        end = time.monotonic() + seconds
        while not self.clock.ready and time.monotonic() < end:
            time.sleep(0.02)
        if not self.clock.ready:
            raise TriggerBoardError("the trigger board daemon has no clock model yet")

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def subscribe(self, on_pulse=None, on_event=None) -> None:
        if on_pulse is not None:
            self._pulse_listeners.append(on_pulse)
        if on_event is not None:
            self._event_listeners.append(on_event)

    def report(self) -> dict:
        return {"connected": self.connected, "through_daemon": self.info.get("api"), "clock": self.clock.stats()}

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self._datagram(b"UNSUB")
        if self._thread is not None:
            self._thread.join(2)
        self._sock.close()

    # --- messages ------------------------------------------------------------------------------------
    def _emit(self, event: BoardEvent) -> None:
        for fn in list(self._event_listeners):
            fn(event)

    def _owner_changed(self) -> None:
        self._owner_fit = False  # the old fit stays until the new owner's replaces it (readers never see none)
        with self._train_lock:  # the new owner's pulses count from 0 again: ours once the session starts again
            self._holding, self._first = False, None
        if self._connected.is_set():
            self._connected.clear()
            self._emit(BoardEvent("disconnected", f"trigger board daemon of rig '{self.rig}' (pid {self.info.get('pid')}) is gone",
                                  monotonic_ns()))

    def _listen(self) -> None:
        renew = 0.0
        while not self._closed.is_set():
            now = time.monotonic()
            if now >= renew:
                self._subscribe()
                renew = now + RENEW_S
            if self._connected.is_set() and now - self._last_message > LOST_S:
                self._connected.clear()
                self._emit(BoardEvent("disconnected", f"trigger board daemon of rig '{self.rig}' stopped answering", monotonic_ns()))
            try:
                data, source = self._sock.recvfrom(65536)
            except socket.timeout:
                continue
            except OSError:
                return
            if source != self._owner_address():
                continue  # a message the old owner sent before it went
            try:
                msg = json.loads(data)
            except ValueError:
                continue
            self._last_message = time.monotonic()
            if msg.get("clock"):
                self.clock.update(msg["clock"])
                self._owner_fit = True
            if not self._connected.is_set() and self._owner_fit:
                self._connected.set()
                if self._ever:
                    self._emit(BoardEvent("connected", f"trigger board daemon of rig '{self.rig}' answers again", monotonic_ns(),
                                          {"reconnect": True}))
                self._ever = True
            if msg.get("t") == "pulse":
                pulse = self._own_pulse(Pulse(int(msg["index"]), int(msg["board_us"]), self._local(int(msg["received_ns"])), bool(msg["late"])))
                if pulse is not None:
                    for fn in list(self._pulse_listeners):
                        fn(pulse)
            elif msg.get("t") == "event":
                event = BoardEvent(str(msg["kind"]), str(msg["detail"]), self._local(int(msg["time_ns"])), dict(msg.get("values") or {}))
                if event.kind == "done":
                    continue  # the daemon's train: this session's ends here (_train_ended)
                self._emit(event)  # the owner's board too may go and come back

    def _subscribe(self) -> None:
        """Subscribe (and renew): to the daemon now in the info file (a restarted one has a new port).
        A new owner (another pid) is a board that went and came back, however quickly the supervisor
        restarted it: its board has a train of its own to start and a clock of its own (the old fit
        maps another board's times), so the old owner is reported lost and the new one is heard only
        once its own clock fit arrives."""
        info = self._locate()
        if info is not None:
            if info.get("pid") != self.info.get("pid"):
                self._owner_changed()
            self.info = info
        self._datagram(b"SUB")

    def _locate(self) -> Optional[dict[str, Any]]:
        """The daemon that owns the board now."""
        return board_daemon(self.rig)

    def _owner_address(self) -> tuple:
        return ("127.0.0.1", int(self.info["event_port"]))

    def _local(self, owner_ns: int) -> int:
        """A time the owner stamped, on this host's clock (the same clock here)."""
        return owner_ns

    def _datagram(self, data: bytes) -> None:
        try:
            self._sock.sendto(data, self._owner_address())
        except (OSError, KeyError, TypeError, ValueError):
            pass


class NetworkBoard(RemoteBoard):
    """The board through its daemon on another host: `daemon://HOST:PORT?token=T` (its network API) or
    `daemon://RIG/@board?token=T` (found by mDNS). Control requests carry the token; pulses, events
    and the clock come to this session's event port from the daemon's network event port, and the
    subscription carries the token's tag (rig.cameras.daemon.signed).

    The board's clock model maps board times to the owner host's monotonic clock: across machines,
    that host's clock and this one must be the same clock (one machine's network namespaces) or
    aligned (PTP), as docs/daemons.md says."""

    BIND = "0.0.0.0"

    def __init__(self, rig: str, uri: str):
        from rig.cameras.daemon import _api_url

        parts = urlsplit(uri)
        self.board_uri = uri
        self._by_mdns = parts.port is None
        try:
            self.api_url, self.token = _api_url(uri)
        except Exception as exc:  # not found on mDNS, a bad address: the one line the session reports
            raise TriggerBoardError(str(exc)) from None
        if not self.token:
            raise TriggerBoardError(f"{uri}: a board daemon on another host needs its token (?token=T)")
        self.HEADERS = {"Authorization": f"Bearer {self.token}"}
        from sync.peer_clock import PeerClock

        # the owner's pulses, events and clock model are on its host's monotonic clock: measured
        # against this host's at every renewal (its status carries its clock)
        self.peer = PeerClock(lambda: 0)
        info = self._locate()
        if info is None:
            raise TriggerBoardError(f"{uri}: the trigger board daemon at {self.api_url} does not answer")
        for _ in range(4):  # a few more exchanges before the first pulse
            self._locate()
        super().__init__(rig, info)
        self.clock = MirrorClock(self.peer)
        self.uri = f"{uri.split('?')[0]} (through its daemon on another host, pid {info.get('pid')})"

    def _locate(self) -> Optional[dict[str, Any]]:
        from rig.daemon.board_daemon import daemon_status

        t0 = monotonic_ns()
        status = daemon_status(self.api_url, self.token)
        if status is not None and status.get("monotonic_ns"):
            self.peer.sample(t0, int(status["monotonic_ns"]), monotonic_ns())
        if status is None and self._by_mdns:  # a restarted owner may listen elsewhere: ask mDNS again
            from rig.cameras.daemon import _api_url

            try:
                self.api_url, _ = _api_url(self.board_uri)
            except Exception:  # noqa: BLE001 - not there now: asked again at the next renewal
                return None
            status = daemon_status(self.api_url, self.token)
        if not status or not status.get("network_event_port"):
            return None
        return {"pid": status.get("pid"), "uri": status.get("uri"), "api": self.api_url, "event_port": int(status["network_event_port"]),
                "host": urlsplit(self.api_url).hostname}

    def _owner_address(self) -> tuple:
        return (self.info["host"], int(self.info["event_port"]))

    def _local(self, owner_ns: int) -> int:
        return self.peer.to_local(owner_ns)

    def _datagram(self, data: bytes) -> None:
        from rig.cameras.daemon import signed

        super()._datagram(signed(self.token, data))
