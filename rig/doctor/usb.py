"""USB: the USB3 Vision devices on the bus (from /sys) and the kernel's usbfs memory limit."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from rig.doctor.check import FAIL, OK, WARN, Check
from rig.doctor.host import Host
from rig.doctor.needs import CameraNeeds, RigNeeds

AREA = "usb"
USBFS = "sys/module/usbcore/parameters/usbfs_memory_mb"
# Linux allows 16 MB of usbfs transfer memory for all userspace USB drivers together by default;
# FLIR/Teledyne recommend 1000 MB for USB3 Vision cameras, more for several ("Understanding USBFS on
# Linux", application note TAN2012007).
VENDOR_USBFS_MB = 1000
# The most transfer memory Aravis keeps submitted per USB3 Vision stream
# (ARV_UV_STREAM_MAXIMUM_SUBMIT_TOTAL, 8 MiB, in Aravis's src/arvuvstream.c).
ARAVIS_U3V_IN_FLIGHT = 8 * 1024 * 1024
U3V_INTERFACE = ("ef", "05", "00")  # class, subclass, protocol of the USB3 Vision control interface


@dataclass
class UsbDevice:
    sysname: str
    busnum: int
    devnum: int
    vendor: str
    product: str
    serial: str
    name: str

    @property
    def node(self) -> str:
        return f"/dev/bus/usb/{self.busnum:03d}/{self.devnum:03d}"


def usb3_vision_devices(host: Host) -> list[UsbDevice]:
    base = host.path("sys/bus/usb/devices")
    try:
        entries = sorted(p.name for p in base.iterdir())
    except OSError:
        return []
    out = []
    for name in entries:
        if ":" in name:
            continue
        interfaces = [e for e in entries if e.startswith(name + ":")]
        is_u3v = any(tuple((host.read(f"sys/bus/usb/devices/{i}/{k}") or "").lower()
                           for k in ("bInterfaceClass", "bInterfaceSubClass", "bInterfaceProtocol")) == U3V_INTERFACE
                     for i in interfaces)
        if not is_u3v:
            continue
        d = f"sys/bus/usb/devices/{name}"
        out.append(UsbDevice(name, host.read_int(f"{d}/busnum") or 0, host.read_int(f"{d}/devnum") or 0,
                             host.read(f"{d}/idVendor") or "", host.read(f"{d}/idProduct") or "",
                             host.read(f"{d}/serial") or "", " ".join(filter(None, (host.read(f"{d}/manufacturer"), host.read(f"{d}/product"))))))
    return out


def match(cam: CameraNeeds, devices: list[UsbDevice]) -> Optional[UsbDevice]:
    """The USB3 Vision device an `aravis://ID` camera names (Aravis's ids end in the serial number)."""
    return next((d for d in devices if d.serial and cam.device and d.serial in cam.device), None)


def checks(host: Host, needs: RigNeeds) -> list[Check]:
    named = needs.of("aravis-id")
    devices = usb3_vision_devices(host) if named else []
    usb3 = [c for c in named if match(c, devices)]
    elsewhere = [c.name for c in named if c not in usb3]
    value = host.read_int(USBFS)
    measured = "unreadable" if value is None else ("0 (no limit)" if value == 0 else f"{value} MB")
    if not usb3:
        why = "no USB3 Vision camera in the rig" if not elsewhere else (
            f"no USB3 Vision camera found on the bus ({', '.join(elsewhere)}: GigE, or not plugged in)")
        return [Check(AREA, "usbfs_memory_mb", OK, measured, why)]
    need_mb = -(-len(usb3) * ARAVIS_U3V_IN_FLIGHT // (1 << 20))
    want = max(need_mb, VENDOR_USBFS_MB)
    fix = (f"echo {want} | sudo tee /sys/module/usbcore/parameters/usbfs_memory_mb && "
           f"echo 'options usbcore usbfs_memory_mb={want}' | sudo tee /etc/modprobe.d/rig-usbfs.conf >/dev/null")
    names = ", ".join(c.name for c in usb3)
    needed = f">= {need_mb} MB ({len(usb3)} USB3 Vision camera{'s' if len(usb3) > 1 else ''}: {names})"
    if value is None:
        return [Check(AREA, "usbfs_memory_mb", WARN, measured, needed, note=f"/{USBFS} cannot be read")]
    if value == 0 or value >= want:
        return [Check(AREA, "usbfs_memory_mb", OK, measured, needed)]
    if value < need_mb:
        return [Check(AREA, "usbfs_memory_mb", FAIL, measured, needed, fix,
                      "the cameras' transfers do not fit: frames are lost or the stream does not start "
                      "(usbcore built into the kernel: add usbcore.usbfs_memory_mb=N to the kernel command line)")]
    return [Check(AREA, "usbfs_memory_mb", WARN, measured, f"{needed}; camera makers advise {VENDOR_USBFS_MB}", fix)]
