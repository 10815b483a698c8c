"""Host driver of the trigger board: handshake, commands, pulse events, clock model, reconnection.

    board = TriggerBoard("serial:///dev/ttyACM0")      # or socket://127.0.0.1:7000, or a device path
    board.connect()                                      # HELLO handshake, starts the clock model
    board.subscribe(on_pulse=lambda p: ..., on_event=lambda e: ...)
    board.set_rate(30.0, 100.0)
    board.warm_up(1.5)                                   # time queries until the clock model is good
    board.start()                                        # PULSE events flow to on_pulse
    host_ns = board.clock.board_to_host_ns(pulse.board_us)
    board.stop(); board.close()

The port itself (any pyserial URL, lines in and out, losing it) is `sync.link.SerialLink`; the
types the driver reports are in `sync.board_events` and importable from here too.

Threads: the link's reader thread hands every line to `_dispatch` (replies wake the waiting
request, pulses and events go to the subscribers, in the reader thread: keep callbacks short); a
supervisor thread sends time queries to keep the clock model current and, when the port is lost,
reopens it until the board answers again. Bad lines are counted, never raised. `sim://` boards are
emulated: `rig.capture.session` opens them.
"""
from __future__ import annotations

import itertools
import threading
import time
from typing import Callable, Optional

from sync.board_events import BoardEvent, BoardInfo, LinkCounters, Pulse, PulseOrder
from sync.clock import ClockModel, TimeSample
from sync.errors import TriggerBoardError
from sync.link import BAUDRATE, SerialLink, open_port, port_url
from sync.protocol import HOST, Message, encode, rate_to_mhz

__all__ = ["BAUDRATE", "BoardEvent", "BoardInfo", "LinkCounters", "Pulse", "TriggerBoard", "open_port", "port_url"]

_REPLY_KINDS = {"HELLO": {"ID"}, "TIME": {"TIME"}, "STATUS": {"STATUS"}}  # others answer OK; any may answer ERR


class _Pending:
    __slots__ = ("kind", "event", "reply", "recv_ns", "error")

    def __init__(self, kind: str):
        self.kind = kind
        self.event = threading.Event()
        self.reply: Optional[Message] = None
        self.recv_ns = 0
        self.error: Optional[str] = None


class TriggerBoard:
    """A connection to one trigger board. Thread-safe."""

    def __init__(self, uri: str, *, baudrate: int = BAUDRATE, request_timeout: float = 0.3, retries: int = 3,
                 query_interval: float = 0.05, reconnect: bool = True, reconnect_interval: float = 0.25,
                 clock: Optional[ClockModel] = None):
        self.uri = uri
        self.baudrate = baudrate
        self.request_timeout = request_timeout
        self.retries = retries
        self.query_interval = query_interval
        self.reconnect = reconnect
        self.reconnect_interval = reconnect_interval
        self.clock = clock or ClockModel()
        self.young_s = 5.0  # for this long after a (re)connect, time queries run at 100 Hz
        self.info: Optional[BoardInfo] = None
        self.counters = LinkCounters()
        self.link = SerialLink(uri, on_message=self._dispatch, on_lost=self._on_port_lost)
        self.rate_hz: Optional[float] = None
        self.pulse_width_us: Optional[float] = None
        self.last_error: Optional[str] = None

        self._connected = threading.Event()
        self._closed = threading.Event()
        self._lock = threading.Lock()  # pending requests, and the connected flag when the port is lost
        self._time_lock = threading.Lock()
        self._pending: dict[int, _Pending] = {}
        self._numbers = itertools.count(1)
        self._pulse_listeners: list[Callable[[Pulse], None]] = []
        self._event_listeners: list[Callable[[BoardEvent], None]] = []
        self._pulse_order = PulseOrder(self.counters)
        self._flash_events: list[BoardEvent] = []
        self._flash_cv = threading.Condition()
        self._done_cv = threading.Condition()
        self._done: Optional[int] = None
        self._supervisor: Optional[threading.Thread] = None

    @property
    def reader(self):
        """The link's LineReader (its counters are the line statistics)."""
        return self.link.reader

    # --- connection -------------------------------------------------------------------------------
    def connect(self, timeout: float = 3.0) -> BoardInfo:
        """Open the port and handshake; raises TriggerBoardError when no board answers."""
        port = self.link.open(self.baudrate)
        self.link.start()
        if self._supervisor is None:
            self._supervisor = threading.Thread(target=self._supervise, name="trigger-board-supervisor", daemon=True)
            self._supervisor.start()
        try:
            self._handshake(timeout)
        except TriggerBoardError:
            self.link.drop(port, None)
            raise
        self._emit(BoardEvent("connected", f"{self.uri}: {self.info.board_id} firmware {self.info.firmware}", time.monotonic_ns(),
                              {"board_id": self.info.board_id, "firmware": self.info.firmware}))
        return self.info

    def _handshake(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        last: Optional[Exception] = None
        while time.monotonic() < deadline:
            try:
                msg, _, _ = self._request("HELLO", timeout=min(self.request_timeout, max(0.05, deadline - time.monotonic())),
                                          retries=0, need_connected=False, count_timeout=False)
            except TriggerBoardError as exc:
                last = exc
                if self.link.port is None:
                    break
                continue
            if msg["proto"] != 1:
                raise TriggerBoardError(f"{self.uri}: board speaks protocol {msg['proto']}, this host speaks 1")
            self.info = BoardInfo(int(msg["proto"]), str(msg["fw"]), str(msg["board"]))
            self.clock.reset()
            self._connected.set()
            return
        raise TriggerBoardError(f"{self.uri}: no trigger board answers on this port ({last or 'no reply'})")

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def wait_connected(self, timeout: float) -> bool:
        return self._connected.wait(timeout)

    def close(self) -> None:
        """Stop the threads and release the port (a running train is stopped first when possible)."""
        if self._closed.is_set():
            return
        if self.connected:
            try:
                self._request("STOP", retries=0, timeout=0.2)
            except TriggerBoardError:
                pass
        self._closed.set()
        self._connected.clear()
        self.link.close()
        if self._supervisor is not None:
            self._supervisor.join(timeout=2)
            self._supervisor = None

    def __enter__(self) -> "TriggerBoard":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- commands ---------------------------------------------------------------------------------
    def set_rate(self, rate_hz: float, pulse_width_us: float) -> None:
        mhz = rate_to_mhz(rate_hz)
        width = int(round(pulse_width_us))
        if not 1 <= mhz <= 10_000_000:
            raise TriggerBoardError(f"trigger rate {rate_hz} Hz is out of range (0.001 to 10000 Hz)")
        if not 1 <= width < 1e9 / mhz:
            raise TriggerBoardError(f"pulse width {pulse_width_us} us must be at least 1 us and shorter than the period")
        self._request("RATE", mhz, width)
        self.rate_hz = mhz / 1000.0
        self.pulse_width_us = float(width)

    def start(self, count: int = 0) -> None:
        """Start a pulse train (count = 0: until stop()); pulse indices restart at 0."""
        with self._done_cv:
            self._done = None
        self._request("START", int(count))

    def stop(self) -> None:
        self._request("STOP")

    def flash(self, ms: int, timeout: float = 1.0) -> Optional[BoardEvent]:
        """Flash the LED output for `ms` milliseconds; returns the board's FLASH event (its board time)."""
        with self._flash_cv:
            self._flash_events.clear()
        self._request("FLASH", int(ms))
        with self._flash_cv:
            self._flash_cv.wait_for(lambda: self._flash_events, timeout)
            return self._flash_events[0] if self._flash_events else None

    def status(self) -> dict:
        msg, _, _ = self._request("STATUS")
        return {"running": bool(msg["running"]), "rate_hz": msg["rate_mhz"] / 1000.0, "pulse_width_us": msg["width_us"],
                "pulses": msg["pulses"], "bad_lines": msg["errors"]}

    def wait_done(self, timeout: float) -> Optional[int]:
        """Wait for the end of the train (DONE); returns how many pulses it had, or None on timeout."""
        with self._done_cv:
            self._done_cv.wait_for(lambda: self._done is not None, timeout)
            return self._done

    def query_time(self) -> Optional[TimeSample]:
        """One time round trip, fed to the clock model; None when the reply did not come in time."""
        with self._time_lock:  # one round trip at a time: overlapping ones would delay each other
            try:
                msg, send_ns, recv_ns = self._request("TIME", retries=0, timeout=self.request_timeout, count_timeout=False)
            except TriggerBoardError:
                return None
        self.clock.add(send_ns, int(msg["board_us"]), recv_ns)
        return TimeSample(send_ns, int(msg["board_us"]), recv_ns)

    def warm_up(self, seconds: float = 3.0, interval: float = 0.01) -> None:
        """Time queries at a brisk pace so the clock model has a slope before pulses matter."""
        end = time.monotonic() + seconds
        while time.monotonic() < end and self.connected:
            self.query_time()
            time.sleep(interval)
        if not self.clock.ready:
            raise TriggerBoardError(f"{self.uri}: no time replies from the board (clock model empty)")

    # --- events -----------------------------------------------------------------------------------
    def subscribe(self, on_pulse: Optional[Callable[[Pulse], None]] = None,
                  on_event: Optional[Callable[[BoardEvent], None]] = None) -> None:
        if on_pulse is not None:
            self._pulse_listeners.append(on_pulse)
        if on_event is not None:
            self._event_listeners.append(on_event)

    def unsubscribe(self, fn: Callable) -> None:
        for lst in (self._pulse_listeners, self._event_listeners):
            if fn in lst:
                lst.remove(fn)

    def report(self) -> dict:
        """Link statistics as a JSON-ready dict."""
        c = self.counters
        lines = self.reader.counters
        return {
            "connected": self.connected,
            "board": None if self.info is None else {"id": self.info.board_id, "firmware": self.info.firmware},
            "lines": lines.lines,
            # a line the parser itself failed on was not read either (lines.last_error says why)
            "corrupt_lines": lines.corrupt + lines.parser_errors,
            "unknown_lines": lines.unknown,
            "out_of_order_lines": c.late_pulses + c.duplicate_pulses + c.unexpected_replies,
            "pulses": c.pulses,
            "missing_pulse_reports": self._pulse_order.missing,
            "late_pulses": c.late_pulses,
            "duplicate_pulses": c.duplicate_pulses,
            "unexpected_replies": c.unexpected_replies,
            "board_errors": dict(c.board_errors),
            "timeouts": c.timeouts,
            "retries": c.retries,
            "disconnects": c.disconnects,
            "reconnects": c.reconnects,
            "clock": self.clock.stats(),
            "last_error": self.last_error,
        }

    # --- requests ---------------------------------------------------------------------------------
    def _request(self, kind: str, *args: int, timeout: Optional[float] = None, retries: Optional[int] = None,
                 need_connected: bool = True, count_timeout: bool = True) -> tuple[Message, int, int]:
        if need_connected and not self.connected:
            raise TriggerBoardError(f"{self.uri}: trigger board not connected ({self.last_error or 'not opened'})")
        timeout = self.request_timeout if timeout is None else timeout
        retries = self.retries if retries is None else retries
        n = next(self._numbers)
        slot = _Pending(kind)
        with self._lock:
            self._pending[n] = slot
        try:
            for attempt in range(retries + 1):
                if attempt:
                    self.counters.retries += 1
                send_ns = self._write(encode(kind, n, *args, direction=HOST))
                if slot.event.wait(timeout):
                    if slot.error is not None:
                        raise TriggerBoardError(slot.error)
                    reply = slot.reply
                    if reply.kind == "ERR":
                        raise TriggerBoardError(f"{self.uri}: the board refused {kind} {' '.join(map(str, args))}: {reply['code']}")
                    return reply, send_ns, slot.recv_ns
            if count_timeout:
                self.counters.timeouts += 1
            raise TriggerBoardError(f"{self.uri}: no reply to {kind} from the trigger board")
        finally:
            with self._lock:
                self._pending.pop(n, None)

    def _write(self, data: bytes) -> int:
        if self.link.port is None:
            raise TriggerBoardError(f"{self.uri}: trigger board not connected ({self.last_error or 'port closed'})")
        return self.link.write(data)

    # --- losing and regaining the port --------------------------------------------------------------
    def _on_port_lost(self, reason: Optional[str]) -> None:
        """The link dropped the port: fail waiting requests, tell subscribers (once per loss)."""
        with self._lock:
            was_connected = self._connected.is_set()
            self._connected.clear()
            pending = list(self._pending.values())
        message = f"{self.uri}: trigger board disconnected ({reason})" if reason else f"{self.uri}: closed"
        for slot in pending:
            slot.error = message
            slot.event.set()
        if reason is not None:
            self.last_error = message
        if was_connected and not self._closed.is_set():
            self.counters.disconnects += 1
            self._emit(BoardEvent("disconnected", message, time.monotonic_ns()))

    def _supervise(self) -> None:
        while not self._closed.is_set():
            try:
                self._supervise_loop()
            except Exception as exc:  # never let the thread that reconnects die
                self.last_error = f"supervisor: {exc!r}"
                self._closed.wait(0.1)

    def _supervise_loop(self) -> None:
        next_query = 0.0
        while not self._closed.is_set():
            if self.connected:
                now = time.monotonic()
                if now >= next_query:
                    # a young model (short span) learns its slope faster from more round trips
                    young = self.clock.age_s() < self.young_s
                    next_query = now + (min(self.query_interval, 0.01) if young else self.query_interval)
                    self.query_time()
                self._closed.wait(max(0.0, min(self.query_interval, next_query - time.monotonic())))
                continue
            if not self.reconnect or self.info is None:  # never connected: connect() reports failures
                self._closed.wait(0.1)
                continue
            self._closed.wait(self.reconnect_interval)
            if self._closed.is_set():
                break
            self._reconnect_once()

    def _reconnect_once(self) -> None:
        try:
            port = self.link.open(self.baudrate)
        except TriggerBoardError as exc:
            self.last_error = str(exc)
            return
        try:
            self._handshake(timeout=1.0)
        except TriggerBoardError as exc:
            self.last_error = str(exc)
            self.link.drop(port, None)
            return
        self.counters.reconnects += 1
        self._pulse_order.reset()
        self._emit(BoardEvent("connected", f"{self.uri}: reconnected to {self.info.board_id}", time.monotonic_ns(),
                              {"board_id": self.info.board_id, "firmware": self.info.firmware, "reconnect": True}))

    # --- incoming ---------------------------------------------------------------------------------
    def _dispatch(self, msg: Message, now: int) -> None:
        kind = msg.kind
        if kind == "PULSE":
            self._on_pulse(int(msg["index"]), int(msg["board_us"]), now)
        elif kind in ("ID", "OK", "TIME", "STATUS") or (kind == "ERR" and msg["n"] != 0):
            with self._lock:
                slot = self._pending.get(int(msg["n"]))
            if slot is None or slot.event.is_set() or not _answers(slot.kind, kind):
                self.counters.unexpected_replies += 1
                return
            if slot.kind == "START" and kind == "OK":
                self._pulse_order.reset()
            slot.reply = msg
            slot.recv_ns = now
            slot.event.set()
        elif kind == "ERR":
            code = str(msg["code"])
            self.counters.board_errors[code] = self.counters.board_errors.get(code, 0) + 1
            self._emit(BoardEvent("board_error", f"{self.uri}: the board could not read a line ({code})", now, {"code": code}))
        elif kind == "DONE":
            with self._done_cv:
                self._done = int(msg["pulses"])
                self._done_cv.notify_all()
            self._emit(BoardEvent("done", f"pulse train ended after {msg['pulses']} pulses", now, {"pulses": int(msg["pulses"])}))
        elif kind == "FLASH":
            event = BoardEvent("flash", f"LED flash of {msg['ms']} ms", now, {"board_us": int(msg["board_us"]), "ms": int(msg["ms"])})
            with self._flash_cv:
                self._flash_events.append(event)
                self._flash_cv.notify_all()
            self._emit(event)
        elif kind == "BOOT":
            # The board restarted on its own (power glitch, watchdog): its clock and train are gone.
            self.clock.reset()
            self._emit(BoardEvent("boot", f"{self.uri}: the board restarted (firmware {msg['fw']})", now,
                                  {"firmware": str(msg["fw"]), "board_id": str(msg["board"])}))

    def _on_pulse(self, index: int, board_us: int, now: int) -> None:
        late = self._pulse_order.accept(index)
        if late is None:
            return  # a duplicate report
        pulse = Pulse(index, board_us, now, late)
        for fn in list(self._pulse_listeners):
            try:
                fn(pulse)
            except Exception as exc:  # a subscriber's bug must not stop the link
                self.counters.listener_errors += 1
                self.last_error = f"pulse subscriber failed: {exc!r}"

    def _emit(self, event: BoardEvent) -> None:
        for fn in list(self._event_listeners):
            try:
                fn(event)
            except Exception as exc:  # a subscriber's bug must not stop the link
                self.counters.listener_errors += 1
                self.last_error = f"event subscriber failed: {exc!r}"


def _answers(request: str, reply: str) -> bool:
    if reply == "ERR":
        return True
    return reply in _REPLY_KINDS.get(request, {"OK"})
