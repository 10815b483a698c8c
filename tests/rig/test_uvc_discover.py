"""uvc:// discovery on a sysfs tree laid out as the kernel lays it out (no /dev/video here), and the
errors of a webcam that is not there."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from rig.cameras import open_camera
from rig.cameras.uvc import discover, parse_uri
from rig.config import CameraConfig
from rig.errors import ConfigError, DeviceNotFound


def _webcam(sys: Path, port: str, nodes: list[int], usb: dict) -> None:
    """A USB webcam on port `port` (e.g. 1-1) with video4linux nodes `nodes`, sysfs style: the class
    entries are links into /sys/devices, and the USB device's files sit two levels above the node."""
    dev = sys / "devices" / "pci0000:00" / "0000:00:14.0" / "usb1" / port
    dev.mkdir(parents=True)
    for key, value in usb.items():
        (dev / key).write_text(value + "\n")
    interface = dev / f"{port}:1.0"
    for i, n in enumerate(nodes):
        node = interface / "video4linux" / f"video{n}"
        node.mkdir(parents=True)
        (node / "name").write_text(usb.get("product", "Camera") + "\n")
        (node / "index").write_text(f"{i}\n")
        os.symlink(os.path.relpath(interface, node), node / "device")
        cls = sys / "class" / "video4linux"
        cls.mkdir(parents=True, exist_ok=True)
        os.symlink(os.path.relpath(node, cls), cls / f"video{n}")


def test_webcams_are_listed_with_their_usb_identity(tmp_path):
    sys = tmp_path / "sys"
    _webcam(sys, "1-1", [0, 1], {"idVendor": "046d", "idProduct": "0825", "serial": "7A8B1C2D", "manufacturer": "Logitech",
                                 "product": "HD Webcam C270"})
    _webcam(sys, "1-2", [2, 3], {"idVendor": "32e4", "idProduct": "9230", "product": "USB Camera"})
    found = discover(sys)
    assert [d.uri for d in found] == ["uvc:///dev/video0", "uvc:///dev/video2"]  # metadata nodes (index 1) skipped
    c270, other = found
    assert (c270.vendor, c270.model, c270.serial, c270.extra["vendor_id"], c270.extra["product_id"]) == (
        "Logitech", "HD Webcam C270", "7A8B1C2D", "046d", "0825")
    assert (other.serial, other.vendor, other.extra["vendor_id"]) == ("", "", "32e4")  # files a camera lacks: empty
    assert discover(tmp_path / "nothing") == []


def test_uvc_uris_and_a_missing_webcam_say_what_is_wrong():
    assert parse_uri("uvc:///dev/video0") == ("/dev/video0", "MJPG")
    assert parse_uri("uvc:///dev/video4?fourcc=yuyv") == ("/dev/video4", "YUYV")
    for uri, words in [("uvc://video0", "uvc:///dev/videoN"), ("uvc:///tmp/x", "uvc:///dev/videoN"),
                       ("uvc:///dev/video0?fourcc=H264", "fourcc must be"), ("uvc:///dev/video0?fps=3", "unknown URI option")]:
        with pytest.raises(ConfigError, match=words):
            parse_uri(uri)
    cfg = CameraConfig(name="cam", uri="uvc:///dev/video97", width=640, height=480, pixel_format="RGB8", trigger="free")
    with pytest.raises(DeviceNotFound, match="no webcam at /dev/video97"):
        open_camera(cfg)
    cfg.trigger = "hardware"
    with pytest.raises(ConfigError, match="cannot be triggered"):
        open_camera(cfg)
