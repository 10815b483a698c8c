"""The serial side of the trigger board: the port (any pyserial URL), bytes to lines and back, and
the loss of the port.

    link = SerialLink(uri, on_message=..., on_lost=...)
    link.open(baudrate)            # raises TriggerBoardError when the port cannot be opened
    link.start()                   # the reader thread: every parsed line goes to on_message
    send_ns = link.write(line)     # raises TriggerBoardError when the port is gone

A read or write that fails drops the port: it is closed, `on_lost(reason)` is called once, and
whoever reconnects opens it again. The link knows nothing of requests or pulses; `sync.board`
builds the driver on it. Bad lines are counted by the LineReader, never raised.
"""
from __future__ import annotations

import threading
import time
from typing import Callable, Optional

import serial

from sync.errors import TriggerBoardError
from sync.protocol import BOARD, LineReader, Message

BAUDRATE = 115200

# What pyserial raises from a port that another thread closed under it, besides its own errors
# (socket://: a ValueError from select() on the closed socket's fd -1).
_CLOSED_UNDER_US = (TypeError, AttributeError, ValueError)


def port_url(uri: str) -> str:
    """What pyserial opens for a board URI: serial:///dev/X is the device path; other URLs as they are."""
    if uri.startswith("serial://"):
        path = uri[len("serial://"):]
        if not path:
            raise TriggerBoardError(f"{uri}: no device path (e.g. serial:///dev/ttyACM0)")
        return path
    if uri.startswith("sim://"):
        raise TriggerBoardError(f"{uri}: an emulated board; open the rig with rig.capture.session to use it")
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


def close_quietly(port: serial.SerialBase) -> None:
    try:
        port.close()
    except Exception:  # closing a port that already failed: nothing left to report
        pass


class SerialLink:
    """One board's port and the thread that reads it. Thread-safe.

    on_message(msg, arrival_ns) runs in the reader thread for every good line, in order.
    on_lost(reason) runs once per lost port, after the port is closed (reason None: closed on
    purpose, e.g. a port where no board answered).
    """

    def __init__(self, uri: str, on_message: Callable[[Message, int], None],
                 on_lost: Callable[[Optional[str]], None]):
        self.uri = uri
        self.reader = LineReader(BOARD)
        self._on_message = on_message
        self._on_lost = on_lost
        self._port: Optional[serial.SerialBase] = None
        self._lock = threading.Lock()
        self._port_changed = threading.Condition(self._lock)
        self._write_lock = threading.Lock()
        self._closed = threading.Event()
        self._thread: Optional[threading.Thread] = None

    @property
    def port(self) -> Optional[serial.SerialBase]:
        return self._port

    def open(self, baudrate: int = BAUDRATE) -> serial.SerialBase:
        """Open the port and read from it from now on; a partial line of an earlier port is forgotten."""
        port = open_port(self.uri, baudrate)
        with self._lock:
            if self._closed.is_set():  # closed while this was opening (a reconnect racing close())
                close_quietly(port)
                raise TriggerBoardError(f"{self.uri}: the link is closed")
            self._port = port
            self.reader.clear()
            self._port_changed.notify_all()
        return port

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._read_loop, name="trigger-board-reader", daemon=True)
            self._thread.start()

    def drop(self, port: serial.SerialBase, reason: Optional[str]) -> None:
        """The port failed (or is given up): forget it and tell on_lost, once per port."""
        with self._lock:
            if self._port is not port:
                return
            self._port = None
        close_quietly(port)
        self._on_lost(reason)

    def close(self) -> None:
        """Release the port and stop the reader thread; on_lost is not called."""
        self._closed.set()
        with self._lock:
            port, self._port = self._port, None
            self._port_changed.notify_all()
        if port is not None:
            close_quietly(port)
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None

    def write(self, data: bytes) -> int:
        """Send a line; returns the host monotonic time just before it went to the port."""
        with self._write_lock:
            port = self._port
            if port is None:
                raise TriggerBoardError(f"{self.uri}: trigger board not connected (port closed)")
            now = time.monotonic_ns()
            try:
                port.write(data)
            except (serial.SerialException, OSError, *_CLOSED_UNDER_US) as exc:  # ValueError: "write on a closed port"
                self.drop(port, f"write failed: {exc or type(exc).__name__}")
                raise TriggerBoardError(f"{self.uri}: trigger board disconnected ({exc or type(exc).__name__})") from None
            return now

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
            except (serial.SerialException, OSError, *_CLOSED_UNDER_US) as exc:
                if not self._closed.is_set():
                    self.drop(port, str(exc) or type(exc).__name__)
                continue
            if not data:
                continue
            now = time.monotonic_ns()
            # A line's arrival is when its first byte came: at 115200 baud the rest takes another
            # two milliseconds, and pyserial hands over the first byte of a burst on its own.
            first = partial_since if self.reader.partial else now
            messages = self.reader.feed(data)
            for i, msg in enumerate(messages):
                self._on_message(msg, first if i == 0 else now)
            if self.reader.partial and (messages or first == now):
                partial_since = now
