"""systemd's sd_notify protocol: one datagram to $NOTIFY_SOCKET ("READY=1", "WATCHDOG=1", ...).

Written here in a few lines rather than taken from a library: the protocol is one AF_UNIX datagram
(a socket name starting with '@' lives in the abstract namespace), and a dependency for it would be
more than the code. Without $NOTIFY_SOCKET (not started by systemd) every call does nothing and
returns False; a socket that is gone is not an error either.
"""
from __future__ import annotations

import os
import socket
import time
from typing import Optional


def notify(state: str) -> bool:
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            sock.sendto(state.encode(), address)
        return True
    except OSError:
        return False


def ready(status: Optional[str] = None) -> bool:
    return notify("READY=1" + (f"\nSTATUS={status}" if status else ""))


def status(text: str) -> bool:
    return notify(f"STATUS={text}")


def watchdog() -> bool:
    return notify("WATCHDOG=1")


def stopping() -> bool:
    return notify("STOPPING=1")


def watchdog_interval() -> Optional[float]:
    """The watchdog period systemd set (WatchdogSec=), in seconds, or None (no watchdog for this process)."""
    pid = os.environ.get("WATCHDOG_PID")
    if pid and pid != str(os.getpid()):
        return None
    try:
        usec = int(os.environ.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    return usec / 1e6 if usec > 0 else None


class Watchdog:
    """Ticked from a main loop: sends WATCHDOG=1 at most every half period (nothing without a watchdog)."""

    def __init__(self) -> None:
        self.interval = watchdog_interval()
        self._next = 0.0

    def tick(self) -> None:
        if self.interval is None:
            return
        now = time.monotonic()
        if now >= self._next:
            watchdog()
            self._next = now + self.interval / 2
