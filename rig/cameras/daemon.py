"""The `daemon://` backend: a camera served by a camera daemon on another host (or this one), read over
its control API (`RemoteDaemonCamera`).

    daemon://HOST:PORT[?token=T]     the daemon's API address
    daemon://RIG/CAMERA[?token=T]    found by mDNS (`_rigcam._tcp.local.`): rig RIG's camera CAMERA

`discover()` lists nothing: looking for daemons takes seconds of mDNS, which `rig discover --network`
spends on purpose; `rig discover` stays quick.
"""
from __future__ import annotations

import hashlib
import hmac
import http.client
import json
import queue
import socket
import struct
import threading
import time
from typing import Any, Optional
from urllib.parse import parse_qs, urlsplit

import numpy as np

from rig.cameras.base import Camera, DeviceInfo
from rig.cameras.discovery import browse
from rig.errors import CameraDisconnected, CameraTimeout, ConfigError, DeviceError, DeviceNotFound
from sync.frames import Frame

SCHEME = "daemon"
MDNS_TIMEOUT_S = 3.0
CLOCK_REFRESH_S = 10.0  # how often a remote daemon's clock offset is measured again
# A daemon camera's trigger input (rig.daemon.camera_daemon): one datagram per trigger.
TRIGGER = struct.Struct("<cqq")  # kind (b"S" | b"H"), pulse index, host time ns
# From another host (the daemon's network trigger input, `network_trigger_port`), a trigger carries a
# tag keyed by the daemon's token after it: a datagram cannot carry the HTTP API's bearer token, and
# a camera on a LAN must not fire for anyone who can send to its port.
TAG_BYTES = 16


def trigger_tag(token: str, payload: bytes) -> bytes:
    """The tag a networked trigger datagram ends with: HMAC-SHA256 of the payload, keyed by the token."""
    return hmac.new(token.encode(), payload, hashlib.sha256).digest()[:TAG_BYTES]


def signed(token: str, payload: bytes) -> bytes:
    return payload + trigger_tag(token, payload)


def verify(token: str, data: bytes) -> Optional[bytes]:
    """The payload of a signed datagram, or None when its tag is not the token's."""
    if len(data) <= TAG_BYTES:
        return None
    payload, tag = data[:-TAG_BYTES], data[-TAG_BYTES:]
    return payload if hmac.compare_digest(tag, trigger_tag(token, payload)) else None


def discover() -> list[DeviceInfo]:
    return []


def _api_url(uri: str) -> tuple[str, str | None]:
    parts = urlsplit(uri)
    token = (parse_qs(parts.query).get("token") or [None])[0]
    if parts.port is not None or (parts.hostname and not parts.path.strip("/")):
        if parts.port is None:
            raise ConfigError(f"{uri}: a daemon address needs its API port (daemon://HOST:PORT)")
        return f"http://{parts.hostname}:{parts.port}", token
    rig, camera = parts.netloc, parts.path.strip("/")
    if not rig or not camera or "/" in camera:
        raise ConfigError(f"{uri}: expected daemon://HOST:PORT or daemon://RIG/CAMERA")
    for found in browse(MDNS_TIMEOUT_S, rig=rig):
        if found.camera == camera:
            return found.api_url, token
    raise DeviceNotFound(f"{uri}: no daemon of rig {rig!r} serving camera {camera!r} answered on mDNS within {MDNS_TIMEOUT_S:g} s")


def open(uri: str, settings):  # noqa: A001 - the backend contract's name
    url, token = _api_url(uri)
    cam = RemoteDaemonCamera(settings, url, token)
    if urlsplit(uri).port is None:  # found by mDNS: a restarted daemon is found there again, at its new port
        cam.locate = lambda: _api_url(uri)[0]
    return cam


class DaemonCamera(Camera):
    """What both kinds share: triggers by datagram, frame ids that continue across daemon restarts."""

    IDS_CONTINUE = True  # after a reconnect the ids go on: a gap in them is frames lost (rig.capture.session)

    def __init__(self, settings, info: dict[str, Any], trigger_host: str, token: Optional[str] = None):
        super().__init__(settings.uri, settings)
        self.info = info
        self._trigger_host = trigger_host
        self._token = token
        self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._id_base = 0  # added to the daemon's frame ids: a restarted daemon counts from 1 again
        self._closed = False

    def _send(self, kind: bytes, pulse: int = 0, host_ns: int = 0) -> None:
        payload = TRIGGER.pack(kind, int(pulse), int(host_ns))
        port = self.info.get("trigger_port")
        if self._token and self.info.get("network_trigger_port"):  # a daemon on another host: its network input
            port, payload = self.info["network_trigger_port"], signed(self._token, payload)
        if not port or self._closed:
            return
        try:
            self._udp.sendto(payload, (self._trigger_host, int(port)))
        except OSError:
            pass  # the daemon is gone: its frame loop reports it

    def software_trigger(self) -> None:
        if self._closed:
            raise CameraDisconnected(f"{self.name}: camera is closed")
        self._send(b"S")

    def hardware_trigger(self, pulse_index: int, time_ns: int) -> None:
        self._send(b"H", pulse_index, time_ns)

    def prepare(self) -> None:
        """The daemon prepared its camera when it started."""

    def _renumber(self, frame: Frame) -> Frame:
        frame.frame_id = self._id_base + int(frame.frame_id)
        frame.camera = self.name
        return frame

    def _restarted(self) -> None:
        """Frames of a new daemon continue after the last id this camera gave."""
        self._id_base = self._last_unwrapped
        self._last_frame_id = None

    def close(self) -> None:
        self._closed = True
        self._udp.close()


class RemoteDaemonCamera(DaemonCamera):
    """A camera read from a daemon's API on another host: a thread long-polls `GET /frames/next`."""

    QUEUE_FRAMES = 8

    def __init__(self, settings, api_url: str, token: Optional[str] = None):
        parts = urlsplit(api_url)
        if parts.scheme != "http" or not parts.hostname or not parts.port:
            raise DeviceError(f"{settings.name}: {api_url!r} is not a daemon API address (http://HOST:PORT)")
        self.api_url = api_url
        self.locate = None  # () -> the daemon's API address now, where it can move (found by mDNS)
        self._headers = {"Authorization": f"Bearer {token}"} if token else {}
        super().__init__(settings, {}, parts.hostname, token)
        self.info = self._get_json("/status")
        # the daemon's host stamps frames with its own monotonic clock: moved onto this host's
        from sync.peer_clock import PeerClock

        self.clock = PeerClock(lambda: self._get_json("/clock")["monotonic_ns"])
        self.clock.refresh()
        self._out: queue.Queue = queue.Queue(maxsize=self.QUEUE_FRAMES)
        self._running = threading.Event()
        self._lost = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._last_seq = -1

    def _connection(self) -> http.client.HTTPConnection:
        parts = urlsplit(self.api_url)
        return http.client.HTTPConnection(parts.hostname, parts.port, timeout=10)

    def _get_json(self, path: str) -> dict[str, Any]:
        conn = self._connection()
        try:
            conn.request("GET", path, headers=self._headers)
            resp = conn.getresponse()
            body = resp.read()
            if resp.status != 200:
                raise DeviceError(f"{self.name}: daemon {self.api_url} answered {resp.status} to {path}: {body[:200].decode(errors='replace')}")
            return json.loads(body)
        except (OSError, http.client.HTTPException, ValueError) as exc:
            raise CameraDisconnected(f"{self.name}: daemon {self.api_url} unreachable ({exc})") from None
        finally:
            conn.close()

    def start(self) -> None:
        if self._running.is_set():
            return
        self._running.set()
        self._lost.clear()
        self._thread = threading.Thread(target=self._poll, name=f"rig-remote-{self.name}", daemon=True)
        self._thread.start()

    def _poll(self) -> None:
        conn = self._connection()
        while self._running.is_set():
            if time.monotonic() - self.clock.refreshed_at > CLOCK_REFRESH_S:
                self.clock.refresh()
            try:
                conn.request("GET", f"/frames/next?after={self._last_seq}&timeout=0.5", headers=self._headers)
                resp = conn.getresponse()
                body = resp.read()
            except (OSError, http.client.HTTPException):
                self._lost.set()
                conn.close()
                return
            if resp.status == 204:
                continue
            if resp.status != 200:
                self._lost.set()
                return
            meta = json.loads(resp.getheader("X-Rig-Frame"))
            image = np.frombuffer(body, dtype=meta["dtype"]).reshape(meta["shape"])
            seq = int(meta.pop("seq"))
            if self._last_seq >= 0 and seq < self._last_seq:
                self._restarted()  # a new daemon: its ring counts from 0 again
            self._last_seq = seq
            frame = Frame(image=image, camera=self.name, frame_id=meta["frame_id"], device_ts_ns=meta["device_ts_ns"],
                          host_ts_ns=self.clock.to_local(meta["host_ts_ns"]), pixel_format=meta["pixel_format"], exposure_us=meta["exposure_us"],
                          trigger_index=meta["trigger_index"], sim_time_s=meta["sim_time_s"])
            try:
                self._out.put_nowait(frame)
            except queue.Full:
                pass  # the consumer fell behind: the frame is lost, as a driver's full queue loses it
        conn.close()

    def _read_frame(self, timeout: float) -> Frame:
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self._renumber(self._out.get(timeout=min(0.05, max(0.0, deadline - time.monotonic()))))
            except queue.Empty:
                if self._lost.is_set():
                    raise CameraDisconnected(f"{self.name}: lost the connection to its daemon {self.api_url}") from None
                if time.monotonic() >= deadline:
                    self.stats.timeouts += 1
                    raise CameraTimeout(f"{self.name}: no frame from {self.api_url} within {timeout:.3f} s") from None

    def reconnect(self) -> bool:
        try:
            self.info = self._get_json("/status")
        except DeviceError:
            if self.locate is None:
                return False
            try:  # the daemon may be back elsewhere (a new port after a restart)
                self.api_url = self.locate()
                self.info = self._get_json("/status")
            except (DeviceError, ConfigError):
                return False
        self.stop()
        self._last_seq = -1
        self._restarted()
        self.clock.refresh()
        self.start()
        return True

    def stop(self) -> None:
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None

    def close(self) -> None:
        self.stop()
        super().close()
