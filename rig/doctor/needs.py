"""What a rig asks of its host, computed from its config alone (no device is opened).

Per camera: how it is reached (GigE Vision by IP address, USB3 Vision, a UVC device node, a GoPro,
a stream, the simulator), its rate (the trigger board's for a hardware-triggered camera, else its
fps), the bytes a frame takes on the wire and on disk, and the shared-memory ring its daemon creates.
"""
from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from typing import Optional
from urllib.parse import urlsplit

from rig.cameras import records_to_card
from rig.cameras.pixels import BYTES_PER_PIXEL
from rig.config import CameraConfig, RigConfig
from rig.daemon import ring as ring_file
from rig.daemon.camera_daemon import default_slots, ring_geometry
from rig.storage.disk import camera_rate_hz

# Aravis's GigE Vision stream asks the kernel for a receive buffer of max(4 payloads, 4 MiB)
# (rig/cameras/aravis.py, AravisCamera.start); the kernel caps it at net.core.rmem_max.
from rig.cameras.aravis import SOCKET_BUFFER_MIN

SOCKET_BUFFER_FRAMES = 4


@dataclass
class CameraNeeds:
    name: str
    uri: str
    transport: str            # gige | aravis-id | uvc | gopro | stream | sim | card
    rate_hz: float            # frames per second it delivers (the board's rate when it is triggered)
    wire_bytes: int           # one frame as the camera sends it (the sensor's pixel format)
    disk_bytes: int           # one frame as a take stores it (Bayer as its mosaic)
    ring_bytes: int           # the daemon's shared-memory ring file (0: no daemon for it)
    hardware: bool = False    # fired by the trigger board
    address: Optional[str] = None  # IPv4 address of a GigE camera
    device: Optional[str] = None   # device node of a UVC camera, or the id of an aravis camera named by id

    @property
    def data_rate(self) -> float:
        """Bytes per second a take writes for this camera."""
        return self.disk_bytes * self.rate_hz

    @property
    def wire_rate(self) -> float:
        return self.wire_bytes * self.rate_hz

    @property
    def socket_buffer(self) -> int:
        """The receive buffer Aravis asks for this camera's stream."""
        return max(SOCKET_BUFFER_FRAMES * self.wire_bytes, SOCKET_BUFFER_MIN)


@dataclass
class RigNeeds:
    rig: str
    config_path: Optional[str]
    cameras: list[CameraNeeds]
    serial_port: Optional[str] = None       # the trigger board's device node, when it is on a serial port
    trigger_uri: Optional[str] = None
    live_rate_hz: Optional[float] = None    # the rate sets arrive at, which the live view aims for
    card_cameras: list[str] = field(default_factory=list)

    @property
    def data_rate(self) -> float:
        return sum(c.data_rate for c in self.cameras)

    def of(self, transport: str) -> list[CameraNeeds]:
        return [c for c in self.cameras if c.transport == transport]

    @property
    def ring_bytes(self) -> int:
        return sum(c.ring_bytes for c in self.cameras)


def _ipv4(host: str) -> Optional[str]:
    try:
        return str(ipaddress.IPv4Address(host))
    except ValueError:
        return None


def _transport(cam: CameraConfig) -> tuple[str, Optional[str], Optional[str]]:
    scheme = cam.scheme
    rest = cam.uri.split("://", 1)[1]
    if scheme == "aravis":
        name = rest.strip("/")
        ip = _ipv4(name)
        # An IP address is a GigE Vision camera; an id (vendor-serial) may be either kind: the USB
        # check looks for it among the USB3 Vision devices, the network checks cannot route to it.
        return ("gige", ip, None) if ip else ("aravis-id", None, name)
    if scheme == "uvc":
        return "uvc", None, urlsplit(cam.uri).path or None
    if scheme in ("gopro", "stream", "sim"):
        return scheme, None, None
    return scheme, None, None


def ring_file_bytes(cam: CameraConfig) -> int:
    """The size of the ring file the camera's daemon creates (rig.daemon.ring's layout)."""
    shape, dtype = ring_geometry(cam)
    channels = shape[2] if len(shape) == 3 else 1
    itemsize = 2 if dtype == "uint16" else 1
    return ring_file.file_size(default_slots(cam), cam.height, cam.width, channels, itemsize)


def rig_needs(cfg: RigConfig) -> RigNeeds:
    trigger = cfg.trigger
    cameras, cards = [], []
    for cam in cfg.cameras:
        if records_to_card(cam):
            cards.append(cam.name)  # it records to its own card: nothing reaches this host during a take
            continue
        transport, address, device = _transport(cam)
        rate = camera_rate_hz(cfg, cam)  # the board's for a triggered camera (hardware or software), as rig record counts
        bpp = BYTES_PER_PIXEL.get(cam.pixel_format, 3)
        frame = cam.width * cam.height * bpp
        cameras.append(CameraNeeds(name=cam.name, uri=cam.uri, transport=transport, rate_hz=float(rate),
                                   wire_bytes=frame, disk_bytes=frame, ring_bytes=ring_file_bytes(cam),
                                   hardware=cam.trigger == "hardware", address=address, device=device))
    serial_port = None
    if trigger is not None and trigger.uri.startswith("serial://"):
        serial_port = urlsplit(trigger.uri).path or None
    live = None
    pair = [c for c in cameras if c.name in {x.name for x in cfg.cameras if x.role in ("left", "right")}]
    if pair:
        live = min(c.rate_hz for c in pair)
    return RigNeeds(rig=cfg.name, config_path=str(cfg.path) if cfg.path else None, cameras=cameras, serial_port=serial_port,
                    trigger_uri=trigger.uri if trigger else None, live_rate_hz=live, card_cameras=cards)
