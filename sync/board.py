"""Host driver of the trigger board: any pyserial URL, handshake, commands, pulse events, clock model,
reconnection.

    board = TriggerBoard("serial:///dev/ttyACM0")      # or socket://127.0.0.1:7000, or a device path
    board.connect()                                      # HELLO handshake, starts the clock model
    board.subscribe(on_pulse=lambda p: ..., on_event=lambda e: ...)
    board.set_rate(30.0, 100.0)
    board.warm_up(1.5)                                   # time queries until the clock model is good
    board.start()                                        # PULSE events flow to on_pulse
    host_ns = board.clock.board_to_host_ns(pulse.board_us)
    board.stop(); board.close()

Threads: a reader thread parses everything the board sends (replies wake the waiting request,
pulses and events go to the subscribers, in the reader thread: keep callbacks short); a supervisor
thread sends time queries to keep the clock model current and, when the port is lost, reopens it
until the board answers again. Bad lines are counted, never raised. `sim://` boards are emulated:
`rig.session` opens them.
"""
from __future__ import annotations

import itertools
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import serial

from sync.clock import ClockModel, TimeSample
from sync.errors import TriggerBoardError
from sync.protocol import BOARD, HOST, LineReader, Message, encode, rate_to_mhz

BAUDRATE = 115200
_REPLY_KINDS = {"HELLO": {"ID"}, "TIME": {"TIME"}, "STATUS": {"STATUS"}}  # others answer OK; any may answer ERR


@dataclass(frozen=True)
class BoardInfo:
    protocol: int
    firmware: str
    board_id: str


@dataclass(frozen=True)
class Pulse:
    """One trigger pulse as the board reported it."""

    index: int  # counts from 0 at each START
    board_us: int  # rising edge on the board's clock
    received_ns: int  # host monotonic time the report arrived
    late: bool = False  # arrived after a later pulse's report (a delayed line)


@dataclass(frozen=True)
class BoardEvent:
    """Something other than a pulse: connected, disconnected, done, flash, board_error, boot."""

    kind: str
    detail: str
    time_ns: int
    values: dict[str, Any] = field(default_factory=dict)


@dataclass
class LinkCounters:
    pulses: int = 0
    missing_pulse_reports: int = 0  # gaps in pulse indices (lines lost on the link)
    late_pulses: int = 0  # reports that came after a later one, and filled a gap
    duplicate_pulses: int = 0
    unexpected_replies: int = 0  # replies nobody waits for (late, or not matching the request)
    board_errors: dict[str, int] = field(default_factory=dict)  # ERR 0 CODE: the board could not read our line
    timeouts: int = 0
    retries: int = 0
    disconnects: int = 0
    reconnects: int = 0
    listener_errors: int = 0


class _Pending:
    __slots__ = ("kind", "event", "reply", "recv_ns", "error")

    def __init__(self, kind: str):
        self.kind = kind
        self.event = threading.Event()
        self.reply: Optional[Message] = None
        self.recv_ns = 0
        self.error: Optional[str] = None


def port_url(uri: str) -> str:
    """What pyserial opens for a board URI: serial:///dev/X is the device path; other URLs as they are."""
    if uri.startswith("serial://"):
        path = uri[len("serial://"):]
        if not path:
            raise TriggerBoardError(f"{uri}: no device path (e.g. serial:///dev/ttyACM0)")
        return path
    if uri.startswith("sim://"):
        raise TriggerBoardError(f"{uri}: an emulated board; open the rig with rig.session to use it")
    return uri


def open_port(uri: str, baudrate: int = BAUDRATE) -> serial.SerialBase:
    try:
        port = serial.serial_for_url(port_url(uri), baudrate=baudrate, timeout=0.05, write_timeout=1.0)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise TriggerBoardError(f"{uri}: cannot open the trigger board ({exc})") from None
    try:
        port.reset_input_buffer()
    except (serial.SerialException, OSError):
        pass
    return port


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
        self.reader = LineReader(BOARD)
        self.rate_hz: Optional[float] = None
        self.pulse_width_us: Optional[float] = None
        self.last_error: Optional[str] = None

        self._port: Optional[serial.SerialBase] = None
        self._connected = threading.Event()
        self._closed = threading.Event()
        self._lock = threading.RLock()  # port, pending requests
        self._write_lock = threading.Lock()
        self._time_lock = threading.Lock()
        self._pending: dict[int, _Pending] = {}
        self._numbers = itertools.count(1)
        self._pulse_listeners: list[Callable[[Pulse], None]] = []
        self._event_listeners: list[Callable[[BoardEvent], None]] = []
        self._next_pulse = 0
        self._missing: set[int] = set()
        self._flash_events: list[BoardEvent] = []
        self._flash_cv = threading.Condition()
        self._done_cv = threading.Condition()
        self._done: Optional[int] = None
        self._threads: list[threading.Thread] = []
        self._port_changed = threading.Condition(self._lock)

    # --- connection -------------------------------------------------------------------------------
    def connect(self, timeout: float = 3.0) -> BoardInfo:
        """Open the port and handshake; raises TriggerBoardError when no board answers."""
        port = open_port(self.uri, self.baudrate)
        self._set_port(port)
        if not self._threads:
            for target, name in ((self._read_loop, "reader"), (self._supervise, "supervisor")):
                t = threading.Thread(target=target, name=f"trigger-board-{name}", daemon=True)
                t.start()
                self._threads.append(t)
        try:
            self._handshake(timeout)
        except TriggerBoardError:
            self._drop_port(port, None)
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
                if self._port is None:
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
        with self._lock:
            port, self._port = self._port, None
            self._connected.clear()
            self._port_changed.notify_all()
        if port is not None:
            _close_quietly(port)
        for t in self._threads:
            t.join(timeout=2)
        self._threads.clear()

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
            "corrupt_lines": lines.corrupt,
            "unknown_lines": lines.unknown,
            "out_of_order_lines": c.late_pulses + c.duplicate_pulses + c.unexpected_replies,
            "pulses": c.pulses,
            "missing_pulse_reports": len(self._missing),
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
        with self._write_lock:
            port = self._port
            if port is None:
                raise TriggerBoardError(f"{self.uri}: trigger board not connected ({self.last_error or 'port closed'})")
            now = time.monotonic_ns()
            try:
                port.write(data)
            except (serial.SerialException, OSError, TypeError, AttributeError, ValueError) as exc:
                # TypeError/AttributeError/ValueError: pyserial's port after another thread closed it
                self._drop_port(port, f"write failed: {exc or type(exc).__name__}")
                raise TriggerBoardError(f"{self.uri}: trigger board disconnected ({exc or type(exc).__name__})") from None
            return now

    # --- port and threads -------------------------------------------------------------------------
    def _set_port(self, port: serial.SerialBase) -> None:
        with self._lock:
            self._port = port
            self.reader.clear()
            self._port_changed.notify_all()

    def _drop_port(self, port: serial.SerialBase, reason: Optional[str]) -> None:
        """The port failed: forget it, fail waiting requests, tell subscribers (once per loss)."""
        with self._lock:
            if self._port is not port:
                return
            self._port = None
            was_connected = self._connected.is_set()
            self._connected.clear()
            pending = list(self._pending.values())
        _close_quietly(port)
        message = f"{self.uri}: trigger board disconnected ({reason})" if reason else f"{self.uri}: closed"
        for slot in pending:
            slot.error = message
            slot.event.set()
        if reason is not None:
            self.last_error = message
        if was_connected and not self._closed.is_set():
            self.counters.disconnects += 1
            self._emit(BoardEvent("disconnected", message, time.monotonic_ns()))

    def _read_loop(self) -> None:
        partial_since = 0
        while not self._closed.is_set():
            with self._lock:
                port = self._port
                if port is None:
                    self._port_changed.wait(0.1)
                    continue
            try:
                data = port.read(max(1, getattr(port, "in_waiting", 0) or 1))
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                # TypeError/AttributeError: pyserial's port object after close() from another thread
                if not self._closed.is_set():
                    self._drop_port(port, str(exc) or type(exc).__name__)
                continue
            if not data:
                continue
            now = time.monotonic_ns()
            # A line's arrival is when its first byte came: at 115200 baud the rest takes another
            # two milliseconds, and pyserial hands over the first byte of a burst on its own.
            first = partial_since if self.reader.partial else now
            messages = self.reader.feed(data)
            for i, msg in enumerate(messages):
                self._dispatch(msg, first if i == 0 else now)
            if self.reader.partial and (messages or first == now):
                partial_since = now

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
            try:
                port = open_port(self.uri, self.baudrate)
            except TriggerBoardError as exc:
                self.last_error = str(exc)
                continue
            self._set_port(port)
            try:
                self._handshake(timeout=1.0)
            except TriggerBoardError as exc:
                self.last_error = str(exc)
                self._drop_port(port, None)
                continue
            self.counters.reconnects += 1
            self._reset_pulse_tracking()
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
                self._reset_pulse_tracking()
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

    def _reset_pulse_tracking(self) -> None:
        self._next_pulse = 0
        self._missing.clear()

    def _on_pulse(self, index: int, board_us: int, now: int) -> None:
        late = False
        if index == self._next_pulse:
            self._next_pulse += 1
        elif index > self._next_pulse:
            gap = index - self._next_pulse
            self.counters.missing_pulse_reports += gap
            if len(self._missing) < 100_000:
                self._missing.update(range(self._next_pulse, index))
            self._next_pulse = index + 1
        elif index in self._missing:
            self._missing.discard(index)
            self.counters.late_pulses += 1
            late = True
        else:
            self.counters.duplicate_pulses += 1
            return
        self.counters.pulses += 1
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
            except Exception as exc:
                self.counters.listener_errors += 1
                self.last_error = f"event subscriber failed: {exc!r}"


def _answers(request: str, reply: str) -> bool:
    if reply == "ERR":
        return True
    return reply in _REPLY_KINDS.get(request, {"OK"})


def _close_quietly(port: serial.SerialBase) -> None:
    try:
        port.close()
    except Exception:
        pass
