"""Cameras served by daemons, behind the same `Camera` contract as an in-process backend.

`open_camera(settings)` is what `RigSession` opens a camera with: when a live daemon serves that
camera of that rig on this host (its info file names a running process, rig.daemon.paths), the
session reads the daemon's frame ring (`LocalDaemonCamera`); otherwise the camera is opened in-process
as before. Either way the session groups the same Frames into the same FrameSets.

A daemon on another host is read over its API by the `daemon://` backend (rig/cameras/daemon.py),
whose `DaemonCamera` both kinds share.

Triggers reach a daemon's camera by one UDP datagram to its trigger input (rig.daemon.camera_daemon);
a session's emulated trigger board fires every daemon's camera that way.

A daemon that dies (or is restarted by `rig up`) is a camera that vanished: `get_frame` raises
CameraDisconnected, and `reconnect()` (the session asks about once a second) attaches to the new
daemon once it serves. Frame ids continue across the restart.
"""
from __future__ import annotations

import socket
import time
from typing import Any, Optional

from rig.cameras import open_camera as open_in_process
from rig.cameras.daemon import DaemonCamera
from rig.daemon import paths
from rig.daemon.ring import FrameNotReady, FrameOverwritten, RingError, RingReader
from rig.errors import CameraDisconnected, CameraTimeout, DeviceError
from sync.frames import Frame

STALE_S = 2.0  # a daemon whose ring heartbeat is older than this is gone (hung or dead)


def local_daemon(settings) -> Optional[dict[str, Any]]:
    """The info of the live daemon serving this camera of this rig on this host, or None."""
    rig = getattr(getattr(settings, "rig", None), "name", None)
    if rig is None or getattr(settings, "calibration_session", None) is not None:
        return None  # (a simulated camera showing a calibration session is not what its daemon shows)
    info = paths.read_json(paths.info_path(rig, settings.name))
    if info is None or info.get("uri") != settings.uri or not paths.pid_alive(info.get("pid")):
        return None
    return info


def open_camera(settings):
    """The camera through its daemon when one serves it here, else opened in this process."""
    info = local_daemon(settings)
    if info is not None:
        return LocalDaemonCamera(settings, info)
    return open_in_process(settings)


class LocalDaemonCamera(DaemonCamera):
    """A camera read from its daemon's frame ring on this host: no copy but the one out of the ring."""

    def __init__(self, settings, info: dict[str, Any]):
        super().__init__(settings, info, "127.0.0.1")
        self.reader: Optional[RingReader] = None
        self._next = 0
        self._bell = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the daemon's doorbell rings here
        self._bell.bind(("127.0.0.1", 0))
        self._renew_at = 0.0  # when to renew the doorbell subscription

    # The daemon rings a doorbell (one datagram to this camera's socket) as it begins to copy each
    # frame into the ring: the reader blocks on it without polling the ring, and its wake-up (a
    # quarter of a millisecond on a small VM, whose idle CPU must be woken) runs while the frame is
    # copied; it then copies the frame out band by band behind the writer (RingReader's streaming
    # read), yielding the CPU while it waits for the next band. The ring's write sequence stays the truth: a lost or late datagram costs at
    # most the next wait.
    RENEW_S = 1.0
    SETTLE_S = 0.003  # the longest a rung reader looks for the frame before it waits again

    def _wait(self, reader: RingReader, k: int, timeout: float) -> bool:
        """True once frame k is written or being written (the read then streams it: RingReader)."""
        end = time.monotonic() + timeout
        while True:
            if reader.write_seq > k or reader.writing(k):
                return True
            now = time.monotonic()
            if now >= end:
                return False
            if now >= self._renew_at:
                port = self.info.get("trigger_port")
                try:
                    self._bell.sendto(b"W", ("127.0.0.1", int(port)))
                except (OSError, TypeError, ValueError):
                    pass
                self._renew_at = now + self.RENEW_S
            if reader.writing(k):  # its doorbell (rung once the slot was marked) was drained with an earlier one's
                self._bell.settimeout(0.0)
            else:
                self._bell.settimeout(min(end - now, 0.05))
            rung = False
            try:
                while True:  # drain: several rings may be queued
                    self._bell.recv(16)
                    rung = True
                    self._bell.setblocking(False)
            except (BlockingIOError, socket.timeout):
                pass
            except OSError:
                time.sleep(0.001)
            if rung or reader.writing(k):  # a frame is being copied in: it is there within a copy's time
                settle = min(end, time.monotonic() + self.SETTLE_S)
                while reader.write_seq <= k and not reader.writing(k) and time.monotonic() < settle:
                    time.sleep(0)

    def _attach(self) -> None:
        reader = RingReader.attach(self.info["ring"])
        if self.reader is not None:
            self.reader.close()
        self.reader = reader
        self._next = reader.latest()  # frames from now on, as a camera started now would give

    def start(self) -> None:
        if self.reader is None:
            try:
                self._attach()
            except RingError as exc:
                raise DeviceError(f"{self.name}: {exc}") from None

    def stop(self) -> None:
        """The daemon keeps acquiring for its other readers."""

    def _read_frame(self, timeout: float) -> Frame:
        reader = self.reader
        if reader is None or self._closed:
            raise CameraDisconnected(f"{self.name}: camera is closed")
        deadline = time.monotonic() + timeout
        while True:
            if self._wait(reader, self._next, min(0.1, max(0.0, deadline - time.monotonic()))):
                try:
                    frame = reader.read(self._next)
                except FrameOverwritten:  # this reader fell a ring behind: those frames are lost to it
                    self._next = max(self._next + 1, reader.latest() - reader.slots + 1)
                    continue
                except FrameNotReady:
                    continue
                self._next += 1
                return self._renumber(frame)
            if not reader.writer_alive(STALE_S):
                raise CameraDisconnected(f"{self.name}: its daemon (pid {self.info.get('pid')}) stopped serving {self.info['ring']}")
            if time.monotonic() >= deadline:
                info = local_daemon(self.settings)
                if info is not None and info.get("state") == "lost":  # the daemon's camera vanished
                    raise CameraDisconnected(f"{self.name}: camera disconnected (its daemon is waiting for it)")
                self.stats.timeouts += 1
                raise CameraTimeout(f"{self.name}: no frame from its daemon within {timeout:.3f} s")

    def reconnect(self) -> bool:
        info = local_daemon(self.settings)
        if info is None or info.get("state") == "lost":
            return False
        if self.reader is not None and info.get("pid") == self.info.get("pid") and self.reader.writer_alive(STALE_S):
            self.info = info
            return True  # the same daemon: its camera is back
        try:
            reader = RingReader.attach(info["ring"])
        except RingError:
            return False
        if not reader.writer_alive(STALE_S):
            reader.close()
            return False
        if self.reader is not None:
            self.reader.close()
        self.info, self.reader, self._next = info, reader, reader.latest()
        self._renew_at = 0.0  # subscribe to the new daemon's doorbell
        self._restarted()
        return True

    def close(self) -> None:
        super().close()
        self._bell.close()
        if self.reader is not None:
            self.reader.close()
            self.reader = None
