"""Devices: the trigger board's serial port, the cameras' device nodes, and the udev rules that
`rig service install` writes (rig/daemon/service.py)."""
from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Optional

from rig.daemon.service import UDEV_DIR, UDEV_RULES, udev_rules
from rig.doctor.check import FAIL, OK, WARN, Check
from rig.doctor.host import Host
from rig.doctor.needs import RigNeeds
from rig.doctor.usb import match, usb3_vision_devices

AREA = "devices"
STABLE_TRIGGER = "/dev/rig-trigger"  # the name 99-rig.rules gives the trigger board


def _install_command(needs: RigNeeds) -> str:
    # absolute: the fix script runs from wherever the user is, not from where the doctor ran
    config = shlex.quote(str(Path(needs.config_path).absolute()) if needs.config_path else "RIG.toml")
    return f"sudo {shlex.quote(sys.executable)} -m rig service install -c {config}"


def _access(host: Host, what: str, node: str, fix_group_hint: str) -> Optional[Check]:
    """A failing Check when the identity cannot open `node` read-write, else None."""
    if host.can_read_write(node):
        return None
    st = host.path(node).stat()
    group = host.group_name(st.st_gid)
    ident = host.identity
    members = host.groups().get(group, (None, []))[1]
    measured = f"{node}: mode {st.st_mode & 0o777:o}, group {group}; {ident.name} cannot open it"
    if ident.name in members:
        return Check(AREA, what, FAIL, measured, f"read-write for {ident.name}", None,
                     f"{ident.name} is in group {group} but this login predates it: log out and in again (or `newgrp {group}`)")
    return Check(AREA, what, FAIL, measured, f"read-write for {ident.name}",
                 f"sudo usermod -aG {group} {shlex.quote(ident.name)}", f"then log out and in again; {fix_group_hint}")


def _trigger_check(host: Host, needs: RigNeeds) -> Check:
    name = "trigger board port"
    port = needs.serial_port
    if port is None:
        what = needs.trigger_uri or "no trigger board"
        return Check(AREA, name, OK, what, "a serial port only for a serial:// board")
    if not host.path(port).exists():
        hint = (f"{STABLE_TRIGGER} is made by the udev rule of `rig service install`" if port == STABLE_TRIGGER
                else "is the board plugged in? (ls /dev/ttyACM* /dev/ttyUSB*)")
        return Check(AREA, name, FAIL, f"{port} missing", f"{port} present", None, hint)
    denied = _access(host, name, port, "the udev rule gives the board to group dialout")
    if denied:
        return denied
    if port != STABLE_TRIGGER and not (host.path(port).is_symlink()):
        return Check(AREA, name, WARN, f"{port}, read-write", f"a stable name ({STABLE_TRIGGER})", None,
                     f"{port} can change at the next plug-in: with the udev rules installed, set "
                     f"[trigger] uri = \"serial://{STABLE_TRIGGER}\"")
    return Check(AREA, name, OK, f"{port}, read-write", "read-write")


def _rules_check(host: Host, needs: RigNeeds) -> Check:
    name = f"udev rules ({UDEV_RULES})"
    path = f"{UDEV_DIR}/{UDEV_RULES}"
    text = host.read(path)
    fix = _install_command(needs)
    named = bool(needs.serial_port or needs.of("aravis-id") or needs.of("uvc") or needs.of("gopro"))
    if text is None and not named:
        return Check(AREA, name, OK, f"{path} missing", "none: no device of the rig that the rules name")
    if text is None:
        return Check(AREA, name, WARN, f"{path} missing", "installed (stable names, device groups)", fix,
                     "without them devices keep their kernel names and root-only access")
    # udev's own parser (systemd 254 and later; older udevadm has no "verify" and says so)
    verify = host.run(["udevadm", "verify", str(host.path(path))])
    if verify is not None and not verify.ok and "unknown command" not in (verify.stderr + verify.stdout).lower():
        why = (verify.stderr.strip() or verify.stdout.strip()).splitlines()
        return Check(AREA, name, FAIL, f"{path}: udevadm verify rejects it ({why[-1] if why else f'exit {verify.rc}'})",
                     "rules udev accepts", fix)
    if text != udev_rules().strip():
        return Check(AREA, name, WARN, f"{path} differs from what this version writes", "this version's rules", fix)
    return Check(AREA, name, OK, f"{path} installed", "installed")


def _camera_device_checks(host: Host, needs: RigNeeds) -> list[Check]:
    out = []
    named = needs.of("aravis-id")
    devices = usb3_vision_devices(host) if named else []
    for cam in named:
        dev = match(cam, devices)
        if dev is None:
            continue  # a GigE camera named by id, or one not plugged in: the USB line says so
        what = f"USB3 Vision {cam.name}"
        if not host.path(dev.node).exists():
            out.append(Check(AREA, what, FAIL, f"{dev.node} missing", "the device node", note="is udev running?"))
            continue
        out.append(_access(host, what, dev.node, "the udev rules give USB3 Vision cameras to group plugdev")
                   or Check(AREA, what, OK, f"{dev.node} ({dev.name or dev.vendor}), read-write", "read-write"))
    for cam in needs.of("uvc"):
        what = f"webcam {cam.name}"
        node = cam.device or ""
        if not node or not host.path(node).exists():
            out.append(Check(AREA, what, FAIL, f"{node or '(no device)'} missing", "the device node",
                             note="plugged in? `rig discover` lists the webcams (names under /dev/rig/video stay put)"))
            continue
        out.append(_access(host, what, node, "the udev rules give webcams to group video")
                   or Check(AREA, what, OK, f"{node}, read-write", "read-write"))
    if not out:
        out.append(Check(AREA, "camera devices", OK, "n/a", "no USB camera device in the rig"))
    return out


def checks(host: Host, needs: RigNeeds) -> list[Check]:
    return [_trigger_check(host, needs), _rules_check(host, needs), *_camera_device_checks(host, needs)]
