"""`uvc:///dev/videoN`: a USB webcam (UVC) through Video4Linux.

    uvc:///dev/video0                         MJPG from the camera (the default), decoded here
    uvc:///dev/video0?fourcc=YUYV             uncompressed YUYV (less CPU, less size/rate at USB 2 speeds)

Frames come through the capture path network streams use (rig.cameras.video_reader: FFmpeg's v4l2
input), at the configured size and rate; exposure (`exposure_us`: manual, or automatic when unset)
and gain (`gain`) are set as V4L2 controls on the device before it streams. A webcam free-runs
(trigger = "free"); its frames carry the driver's timestamps as device time.

`discover()` lists /sys/class/video4linux: each capture node (index 0; the metadata nodes of the
same camera are skipped) with the USB vendor and product ids, manufacturer, product name and serial
of the USB device it belongs to.
"""
from __future__ import annotations

import fcntl
import os
import struct
from pathlib import Path
from typing import Optional
from urllib.parse import parse_qs, urlsplit

from rig.cameras.base import DeviceInfo, free_running_problems, raise_problems
from rig.cameras.video_reader import ReaderCamera, VideoReader
from rig.errors import ConfigError, DeviceError, DeviceNotFound

SCHEME = "uvc"
FOURCCS = {"MJPG": "mjpeg", "YUYV": "yuyv422"}  # wire format -> FFmpeg's v4l2 input_format
STALL_S = 2.0

# V4L2 controls (linux/v4l2-controls.h) and VIDIOC_S_CTRL = _IOWR('V', 28, struct v4l2_control)
VIDIOC_S_CTRL = 0xC008561C
CID_EXPOSURE_AUTO, CID_EXPOSURE_ABSOLUTE, CID_GAIN = 0x009A0901, 0x009A0902, 0x00980913
EXPOSURE_MANUAL, EXPOSURE_APERTURE_PRIORITY = 1, 3  # UVC cameras: manual, or automatic exposure


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError:
        return ""


def discover(sysfs_root: str | os.PathLike = "/sys") -> list[DeviceInfo]:
    found = []
    root = Path(sysfs_root) / "class" / "video4linux"
    if not root.is_dir():
        return found
    for node in sorted(root.glob("video*"), key=lambda p: int(p.name[5:]) if p.name[5:].isdigit() else 1 << 30):
        if _read(node / "index") not in ("", "0"):
            continue  # a second node of the same camera (its metadata stream)
        usb = _usb_device(node)
        info = {k: _read(usb / k) for k in ("idVendor", "idProduct", "serial", "manufacturer", "product")} if usb else {}
        found.append(DeviceInfo(uri=f"uvc:///dev/{node.name}", backend=SCHEME, model=info.get("product") or _read(node / "name"),
                                serial=info.get("serial", ""), vendor=info.get("manufacturer", ""), address=f"/dev/{node.name}",
                                extra={"vendor_id": info.get("idVendor", ""), "product_id": info.get("idProduct", ""),
                                       "name": _read(node / "name")}))
    return found


def _usb_device(node: Path) -> Optional[Path]:
    """The USB device a video4linux node belongs to: the first parent of its device with idVendor."""
    try:
        here = (node / "device").resolve()
    except OSError:
        return None
    for parent in (here, *here.parents):
        if (parent / "idVendor").is_file():
            return parent
    return None


def open(uri: str, settings) -> "UvcCamera":  # noqa: A001 - the backend contract's name
    return UvcCamera(uri, settings)


def parse_uri(uri: str) -> tuple[str, str]:
    """(device path, wire fourcc)."""
    parts = urlsplit(uri)
    if parts.scheme != SCHEME or parts.netloc or not parts.path.startswith("/dev/"):
        raise ConfigError(f"{uri}: a webcam URI is uvc:///dev/videoN[?fourcc=MJPG|YUYV], e.g. uvc:///dev/video0")
    query = parse_qs(parts.query)
    unknown = set(query) - {"fourcc"}
    if unknown:
        raise ConfigError(f"{uri}: unknown URI option {', '.join(sorted(unknown))} (allowed: fourcc)")
    fourcc = query.get("fourcc", ["MJPG"])[0].upper()
    if fourcc not in FOURCCS:
        raise ConfigError(f"{uri}: fourcc must be one of {', '.join(FOURCCS)}, got {fourcc}")
    return parts.path, fourcc


def problems(uri: str, settings) -> list[str]:
    """What keeps these settings from working with a webcam (`rig config check` and opening ask)."""
    out = []
    try:
        parse_uri(uri)
    except ConfigError as exc:
        out.append(str(exc))
    out += free_running_problems("a webcam", settings)
    return out


class UvcCamera(ReaderCamera):
    def __init__(self, uri: str, settings):
        super().__init__(uri, settings)
        raise_problems(settings, uri, problems(uri, settings))
        self.device, self.fourcc = parse_uri(uri)
        if not os.path.exists(self.device):
            raise DeviceNotFound(f"{settings.name}: no webcam at {self.device} (`rig discover` lists the ones plugged in)")
        options = {"video_size": f"{settings.width}x{settings.height}", "framerate": f"{settings.fps:g}",
                   "input_format": FOURCCS[self.fourcc], "timestamps": "mono2abs"}
        self.reader = VideoReader(self.device, settings.name, format="v4l2", options=options, stall_s=STALL_S,
                                  pixel_format=settings.pixel_format, size=(settings.width, settings.height))
        self._started = False

    def _before_start(self) -> None:
        """Exposure (manual when exposure_us is set, else automatic) and gain, as V4L2 controls."""
        s = self.settings
        controls = []
        if s.exposure_us is not None:
            controls += [(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL), (CID_EXPOSURE_ABSOLUTE, max(1, round(s.exposure_us / 100)))]
        else:
            controls.append((CID_EXPOSURE_AUTO, EXPOSURE_APERTURE_PRIORITY))
        if s.gain is not None:
            controls.append((CID_GAIN, int(round(s.gain))))
        try:
            fd = os.open(self.device, os.O_RDWR | os.O_NONBLOCK)
        except OSError as exc:
            raise DeviceError(f"{self.name}: cannot open {self.device} ({exc.strerror})") from None
        try:
            for cid, value in controls:
                try:
                    fcntl.ioctl(fd, VIDIOC_S_CTRL, struct.pack("<Ii", cid, value))
                except OSError as exc:
                    raise DeviceError(f"{self.name}: {self.device} refused control 0x{cid:08x} = {value} ({exc.strerror})") from None
        finally:
            os.close(fd)

    def reconnect(self) -> bool:
        if not os.path.exists(self.device):
            return False
        self.reader.reopen()
        return True

    def software_trigger(self) -> None:
        raise ConfigError(f"{self.name} ({self.uri}): a webcam cannot be triggered")
