"""`gopro://SERIAL`: a GoPro on USB, live frames from its webcam mode, or a video on its card.

    gopro://C3501324645504                    the camera's USB address from its serial (172.2X.1YZ.51:8080)
    gopro://C3501324645504@127.0.0.1:8080     an explicit control address (a camera on another link, an emulator)
    gopro://C3501324645504?port=8570          the UDP port of its stream (default 8554 + the serial's last two digits)
    gopro://C3501324645504?record=card        record to the camera's card instead (rig.cameras.gopro_card):
                                              no live frames; `rig record` presses the shutter for the take and
                                              downloads the video into it (`record=webcam`, the default: live frames)

Opening takes wired USB control, checks the API and waits for the camera to be ready
(rig.cameras.gopro_http); `start()` starts the webcam stream (MPEG-TS over UDP to this host, one
port per camera so that several never mix) at the configured size (1920x1080, 1280x720 or 848x480)
and decodes it (rig.cameras.video_reader). A GoPro cannot take a trigger: it free-runs (trigger =
"free"), its frames carry the stream's presentation time as device time, and the session groups
them by arrival time less the camera's `latency_ms`; `rig record align` places them on the pulses
afterwards by the board's LED flashes. The control link's watchdog (keep-alive every 3 s)
reconnects a camera that stops answering and restarts its stream; a stream that goes silent
makes `get_frame` report the camera lost, and the session's reconnect brings it back.
"""
from __future__ import annotations

import re
import threading
from typing import Optional
from urllib.parse import parse_qs, urlsplit

from rig.cameras.base import Camera, DeviceInfo, free_running_problems, raise_problems
from rig.cameras.gopro_card import GoProCardCamera, card_problems
from rig.cameras.gopro_http import (DEFAULT_WEBCAM_PORT, GoProClient, LinkEvent, discover_mdns, discover_usb,
                                    _check_serial)
from rig.cameras.video_reader import VideoReader
from rig.errors import CameraDisconnected, ConfigError, DeviceError

SCHEME = "gopro"
SIZES = {(1920, 1080): 1080, (1280, 720): 720, (848, 480): 480}  # webcam resolutions, by frame size
STALL_S = 2.0  # a stream silent this long is lost
RECORD_MODES = ("webcam", "card")


def discover() -> list[DeviceInfo]:
    found = {}
    for cam in discover_usb() + discover_mdns(timeout=1.5):
        found.setdefault(cam.serial, DeviceInfo(uri=cam.uri if cam.source == "usb" else f"{cam.uri}@{cam.address}:{cam.port}",
                                                backend=SCHEME, model="GoPro", serial=cam.serial, vendor="GoPro",
                                                address=cam.base_url, extra={"found_by": cam.source, **cam.extra}))
    return list(found.values())


def open(uri: str, settings) -> Camera:  # noqa: A001 - the backend contract's name
    if records_to_card(uri):
        raise_problems(settings, uri, problems(uri, settings))
        return GoProCardCamera(uri, settings, card_client(uri))
    return GoProCamera(uri, settings)


def card_client(uri: str, **options) -> GoProClient:
    """A client (not connected) for the camera a URI names (the control address; the stream port aside)."""
    serial, base_url, _ = parse_uri(uri)
    return GoProClient(serial, base_url=base_url, **options)


def parse_uri(uri: str) -> tuple[str, Optional[str], int]:
    """(serial, control base URL or None for the USB address, UDP port of the stream)."""
    parts = urlsplit(uri)
    if parts.scheme != SCHEME or not parts.netloc:
        raise ConfigError(f"{uri}: a GoPro URI is gopro://SERIAL[@HOST:PORT][?port=UDP or ?record=card], e.g. gopro://C3501324645504")
    serial, _, address = parts.netloc.partition("@")
    serial = _check_serial(serial)
    base_url = None
    if address:
        if not re.fullmatch(r"[A-Za-z0-9.\-]+:\d{1,5}|\[[0-9a-fA-F:]+\]:\d{1,5}", address):
            raise ConfigError(f"{uri}: the control address must be HOST:PORT, got {address!r}")
        base_url = f"http://{address}"
    query = parse_qs(parts.query)
    unknown = set(query) - {"port", "record"}
    if unknown:
        raise ConfigError(f"{uri}: unknown URI option {', '.join(sorted(unknown))} (allowed: port, record)")
    record = query.get("record", ["webcam"])[-1]
    if record not in RECORD_MODES:
        raise ConfigError(f"{uri}: record must be {' or '.join(RECORD_MODES)} (live frames, or a video on the card), got {record!r}")
    if record == "card" and "port" in query:
        raise ConfigError(f"{uri}: a camera that records to its card streams nothing: drop port=")
    try:
        port = int(query["port"][0]) if "port" in query else DEFAULT_WEBCAM_PORT + int(serial[-2:])
    except ValueError:
        raise ConfigError(f"{uri}: port must be a number") from None
    if not 1024 <= port <= 65535:
        raise ConfigError(f"{uri}: the stream's UDP port must be 1024-65535, got {port}")
    return serial, base_url, port


def records_to_card(uri: str) -> bool:
    """True for `?record=card`: the camera records its video to its card (no live frames)."""
    return parse_qs(urlsplit(uri).query).get("record", ["webcam"])[-1] == "card"


def problems(uri: str, settings) -> list[str]:
    """What keeps these settings from working with a GoPro (`rig config check` and opening ask)."""
    out = []
    try:
        parse_uri(uri)
    except ConfigError as exc:
        out.append(str(exc))
    if records_to_card(uri):
        return out + card_problems(settings)
    out += free_running_problems("a GoPro", settings)
    if (settings.width, settings.height) not in SIZES:
        out.append(f"the webcam stream is {', '.join(f'{w}x{h}' for w, h in SIZES)}; got {settings.width}x{settings.height}")
    return out


class GoProCamera(Camera):
    def __init__(self, uri: str, settings):
        super().__init__(uri, settings)
        raise_problems(settings, uri, problems(uri, settings))
        self.serial, base_url, self.port = parse_uri(uri)
        size = (settings.width, settings.height)
        self.resolution = SIZES[size]
        self.link_events: list[LinkEvent] = []
        self._lock = threading.Lock()
        self.client = GoProClient(self.serial, base_url=base_url, on_event=self._on_link_event)
        # the stream comes to this host: on loopback for a camera (emulator) reached on loopback
        host = urlsplit(self.client.base_url).hostname
        listen = "127.0.0.1" if host in ("127.0.0.1", "localhost") else "0.0.0.0"
        self.reader = VideoReader(f"udp://{listen}:{self.port}?overrun_nonfatal=1&fifo_size=65536", settings.name,
                                  format="mpegts", stall_s=STALL_S, pixel_format=settings.pixel_format, size=size)
        self._started = False
        self.client.connect()

    def _on_link_event(self, event: LinkEvent) -> None:
        with self._lock:
            self.link_events.append(event)

    def start(self) -> None:
        if self._started:
            return
        self.reader.start()  # listening before the camera sends
        try:
            self.client.webcam_start(port=self.port, resolution=self.resolution, fov="linear")
        except (DeviceError, CameraDisconnected):
            self.reader.stop()
            raise
        self._started = True

    def stop(self) -> None:
        if not self._started:
            return
        self._started = False
        self.reader.stop()
        try:
            self.client.webcam_stop()
        except (DeviceError, CameraDisconnected):
            pass  # the camera is gone: nothing to stop

    def close(self) -> None:
        self.stop()
        self.client.close()

    def _read_frame(self, timeout: float):
        frame = self.reader.read(timeout)
        self.stats.extra["stream_dropped"] = self.reader.stats.dropped
        self.stats.extra["link_events"] = len(self.link_events)
        return frame

    def reconnect(self) -> bool:
        """The stream went silent: once the camera answers again, restart its stream and listen."""
        try:
            self.client.wait_ready(timeout=2.0)
            self.reader.reopen()
            self.client.webcam_start(port=self.port, resolution=self.resolution, fov="linear")
        except (DeviceError, CameraDisconnected, ConfigError):
            return False
        return True

    def software_trigger(self) -> None:
        raise ConfigError(f"{self.name} ({self.uri}): a GoPro cannot be triggered")
