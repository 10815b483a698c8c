"""The emulated trigger board's end of the serial link: the port the host opens (a pty pair or a
loopback socket) and the line queue that puts the board's lines on it after the link's delay.

    serial = BoardSerial(PtyTransport())   # or SocketTransport(port=...)
    serial.plug()                          # the port appears; serial.url is what pyserial opens
    serial.send(line, due_ns)              # on the wire at due_ns, in order; hold_back=True: later lines overtake
    data = serial.read(0.05)               # what the host wrote, or None
    serial.unplug()                        # the port vanishes with every line not yet sent

`transmission_error` is the fault model of one garbled line. The board's logic is in
`simulator.trigger_board`.
"""
from __future__ import annotations

import heapq
import itertools
import os
import select
import socket
import tempfile
import threading
import time
import tty
from pathlib import Path
from typing import Optional, Union

import numpy as np

INLINE_WAIT_NS = 2_000_000  # delays up to this are waited out by the sender, not the writer thread


class PtyTransport:
    """The board end of a pseudo-terminal pair; the host opens `url` (a symlink to the slave)."""

    def __init__(self, link: Optional[Path] = None):
        self._own_dir = None
        if link is None:
            self._own_dir = tempfile.mkdtemp(prefix="trigger-board-")
            link = Path(self._own_dir) / "tty"
        self.link = Path(link)
        self.master: Optional[int] = None
        self.slave: Optional[int] = None

    @property
    def url(self) -> str:
        return str(self.link)

    def open(self) -> None:
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
        self.master, self.slave = master, slave
        tmp = self.link.with_name(self.link.name + ".new")
        if tmp.is_symlink() or tmp.exists():
            tmp.unlink()
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.link)  # atomic: the host never sees a half-made link

    def close(self) -> None:
        # The device disappears with its node, as udev removes /dev/serial/by-id/... on unplug.
        if self.link.is_symlink():
            self.link.unlink()
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None

    def remove(self) -> None:
        self.close()
        if self._own_dir:
            try:
                os.rmdir(self._own_dir)
            except OSError:
                pass

    def read(self, timeout: float) -> Optional[bytes]:
        fd = self.master
        if fd is None:
            time.sleep(timeout)
            return None
        try:
            ready, _, _ = select.select([fd], [], [], timeout)
            return os.read(fd, 4096) if ready else None
        except (OSError, ValueError):
            return None  # closed under us (unplug) or nobody on the other end yet

    def write(self, data: bytes) -> bool:
        fd = self.master
        if fd is None:
            return False
        try:
            os.write(fd, data)
            return True
        except (BlockingIOError, OSError):
            return False  # host not reading: the line is lost, as a USB CDC buffer overflows


class SocketTransport:
    """The board behind a loopback TCP port (`socket://127.0.0.1:PORT`), one host at a time."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0):
        self.host = host
        self.port = port
        self._listener: Optional[socket.socket] = None
        self._client: Optional[socket.socket] = None
        self._lock = threading.Lock()

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    def open(self) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((self.host, self.port))
        s.listen(1)
        self.port = s.getsockname()[1]  # keep the port: a replugged board comes back on it
        self._listener = s

    def close(self) -> None:
        with self._lock:
            for s in (self._client, self._listener):
                if s is not None:
                    try:
                        s.close()
                    except OSError:
                        pass
            self._client = self._listener = None

    remove = close

    def read(self, timeout: float) -> Optional[bytes]:
        with self._lock:
            client, listener = self._client, self._listener
        if listener is None:
            time.sleep(timeout)
            return None
        try:
            if client is None:
                ready, _, _ = select.select([listener], [], [], timeout)
                if ready:
                    conn, _ = listener.accept()
                    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    with self._lock:
                        self._client = conn
                return None
            ready, _, _ = select.select([client], [], [], timeout)
            if not ready:
                return None
            data = client.recv(4096)
        except (OSError, ValueError):
            data = b""
        if not data:  # the host hung up: wait for the next one
            with self._lock:
                if self._client is client:
                    self._client = None
            try:
                client.close()
            except OSError:
                pass
        return data or None

    def write(self, data: bytes) -> bool:
        with self._lock:
            client = self._client
        if client is None:
            return False
        try:
            client.sendall(data)
            return True
        except OSError:
            return False


Transport = Union[PtyTransport, SocketTransport]


class BoardSerial:
    """The board's serial port: a transport, and the lines waiting their turn to go out on it.

    A serial link keeps its order: each line is due no earlier than the one before, so a delayed
    line delays the rest; only a line held back on purpose (hold_back) is overtaken. Lines written
    while nothing is plugged, or that the host does not read, are lost and counted.
    """

    def __init__(self, transport: Transport):
        self.transport = transport
        self.sent = 0  # lines on the wire
        self.lost = 0  # lines written while no host was listening (or unplugged)
        self._cv = threading.Condition()
        self._out: list[tuple[int, int, bytes]] = []  # heap (due_ns, seq, line)
        self._seq = itertools.count()
        self._last_due = 0
        self._plugged = False
        self._closed = False
        self._writer: Optional[threading.Thread] = None

    @property
    def url(self) -> str:
        return self.transport.url

    def start(self) -> None:
        """Start the writer thread, which sends lines whose delay is too long to wait out inline."""
        if self._writer is None:
            self._writer = threading.Thread(target=self._write_loop, name="emulated-trigger-writer", daemon=True)
            self._writer.start()

    def plug(self) -> None:
        with self._cv:
            self.transport.open()
            self._plugged = True

    def unplug(self) -> None:
        """The port vanishes, and every line not yet sent with it."""
        with self._cv:
            self._plugged = False
            self._out.clear()
            self.transport.close()
            self._cv.notify_all()

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._plugged = False
            self._cv.notify_all()
        if self._writer is not None:
            self._writer.join(timeout=2)
            self._writer = None
        self.transport.remove()

    def read(self, timeout: float) -> Optional[bytes]:
        return self.transport.read(timeout)

    def send(self, line: bytes, due_ns: int, hold_back: bool = False) -> None:
        """Put a line on the wire at host time `due_ns`, or after the lines before it (unless held back)."""
        with self._cv:
            if hold_back:
                due = due_ns  # later lines overtake it
            else:
                due = max(due_ns, self._last_due)  # a serial link keeps its order
                self._last_due = due
                if not self._out and due - time.monotonic_ns() <= INLINE_WAIT_NS:
                    # a short delay is waited out here: a hand-off to the writer thread would add its
                    # own wake-up latency (tens of microseconds) to the delay the options ask for
                    while time.monotonic_ns() < due:
                        time.sleep(0)
                    self._transmit(line)
                    return
            heapq.heappush(self._out, (due, next(self._seq), line))
            self._cv.notify_all()

    def _transmit(self, line: bytes) -> None:
        if self._plugged and self.transport.write(line):
            self.sent += 1
        else:
            self.lost += 1

    def _write_loop(self) -> None:
        spin_ns = 400_000  # wake this early and wait out the rest precisely: a condition wait overshoots
        while True:
            with self._cv:
                while not self._closed:
                    now = time.monotonic_ns()
                    if self._out and self._out[0][0] - spin_ns <= now:
                        break
                    wait = (self._out[0][0] - spin_ns - now) / 1e9 if self._out else 0.1
                    self._cv.wait(min(wait, 0.1))
                if self._closed:
                    return
                due = self._out[0][0]
            while time.monotonic_ns() < due:
                time.sleep(0)
            with self._cv:
                if self._out and self._out[0][0] <= time.monotonic_ns():
                    _, _, line = heapq.heappop(self._out)
                    self._transmit(line)


def transmission_error(line: bytes, rng: np.random.Generator) -> bytes:
    """One transmission error in a line: a flipped bit, a lost, a noise or a repeated byte."""
    body = bytearray(line.rstrip(b"\n"))
    if not body:
        return line
    i = int(rng.integers(len(body)))
    how = int(rng.integers(4))
    if how == 0:
        body[i] ^= 1 << int(rng.integers(8))
    elif how == 1:
        del body[i]
    elif how == 2:
        body.insert(i, int(rng.integers(256)))
    else:
        body[i:i] = body[i:i + 1]
    return bytes(body) + b"\n"
