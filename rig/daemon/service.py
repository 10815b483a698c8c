"""The rig's daemons as systemd services on a venue box: the unit files, the target and udev rules.

`rig service install -c RIG.toml` writes (docs/services.md):

- `rig-camera@.service`, a template: instance `%i` is a camera's name, run as
  `<python> -m rig daemon %i -c <config>`; `Type=notify` (the daemon sends READY once its camera
  acquires and WATCHDOG from its acquisition loop, rig.daemon.notify), restarted on failure and when
  the watchdog stops hearing it.
- `rig-board.service`, when the rig has a trigger board: `rig daemon --board`, as `rig up` runs it.
- `rig.target`: wants every camera's instance (and the board's unit) of the config; enabled, the
  rig comes up at boot.
- `99-rig.rules`: udev rules for stable device names (the trigger board, USB3 Vision cameras, UVC
  webcams, GoPro network interfaces).

The template names one config file: a box runs one rig. Run the command again after adding or
renaming a camera (the target lists the cameras). The files are generated as strings (one function
each) so that tests check them with `systemd-analyze verify` and udev's own parser.
"""
from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Optional

from rig.errors import ConfigError

UNIT_DIR = "/etc/systemd/system"
UDEV_DIR = "/etc/udev/rules.d"
SYSTEMD_RUN_DIR = "/run/systemd/system"  # exists only when systemd is PID 1 (sd_booted())

TARGET = "rig.target"
CAMERA_TEMPLATE = "rig-camera@.service"
BOARD_UNIT = "rig-board.service"
UDEV_RULES = "99-rig.rules"

# The trigger board (sync/firmware/trigger_board/trigger_board.ino): a Raspberry Pi Pico (RP2040) with
# the arduino-pico core, whose USB CDC serial port enumerates with the Raspberry Pi vendor id and the
# core's Pico product id (arduino-pico boards.txt: rpipico.build.vid=0x2e8a, rpipico.build.pid=0x000a).
TRIGGER_USB_VENDOR = "2e8a"
TRIGGER_USB_PRODUCT = "000a"
GOPRO_USB_VENDOR = "2672"
# Groups the devices are given to by the udev rules; a --user daemon joins them (SupplementaryGroups=).
# All three are Debian system groups (base-passwd).
DEVICE_GROUPS = ("dialout", "plugdev", "video")

_CAMERA_UNIT_NAME = re.compile(r"[A-Za-z0-9_-]+")  # what an instance name takes without escaping
_USER_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*\$?")


class Written(list):
    """The paths `install` wrote (a list of Path), with `notes`: what the user still has to do, and
    `reloaded`: whether systemd and udev were told to reload."""

    def __init__(self, paths=(), notes=(), reloaded: bool = False):
        super().__init__(paths)
        self.notes: list[str] = list(notes)
        self.reloaded = reloaded


# ---- quoting what goes into a unit file ------------------------------------------------------------

def _text(value: str) -> str:
    """Free text (Description=): one line, no specifier (% is systemd's specifier escape)."""
    return re.sub(r"[\x00-\x1f\x7f]", " ", value).replace("%", "%%").strip()


def exec_word(word: str, *, command: bool = False) -> str:
    """One word of ExecStart=: '%' escaped (specifiers), '$' too in an argument (environment variables
    are substituted in arguments, never in the command itself: there "$$" would stay two characters);
    quoted when it has whitespace, quotes or backslashes (systemd splits the line itself, with C-style
    escapes)."""
    if any(ch in word for ch in "\n\r\0"):
        raise ConfigError(f"{word!r}: a path with a line break cannot go into a unit file")
    word = word.replace("%", "%%")
    if not command:
        word = word.replace("$", "$$")
    if word and not re.search(r"[\s\"'\\;]", word):
        return word
    return '"' + word.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _seconds(value: float) -> str:
    """A time span as systemd reads it, in seconds (microsecond resolution): 5.0 -> "5", 2.5 -> "2.5"."""
    return f"{value:.6f}".rstrip("0").rstrip(".")


def check_watchdog(watchdog_s: float) -> float:
    try:
        value = float(watchdog_s)
    except (TypeError, ValueError):
        raise ConfigError(f"--watchdog must be a number of seconds, got {watchdog_s!r}") from None
    if not math.isfinite(value) or value < 0.001:
        raise ConfigError(f"--watchdog must be at least 0.001 seconds (systemd counts microseconds; 0 would switch the "
                          f"watchdog off), got {watchdog_s}")
    return value


def _check_account(kind: str, name: Optional[str]) -> Optional[str]:
    if name is None:
        return None
    if not _USER_NAME.fullmatch(name) or len(name) > 256:
        raise ConfigError(f"--{kind} {name!r}: not a valid {kind} name (letters, digits, '_', '.', '-')")
    return name


# ---- the files -------------------------------------------------------------------------------------

def _service_body(*, description: str, exec_args: list[str], python: str, config_path: str, watchdog_s: float,
                  user: Optional[str], group: Optional[str]) -> str:
    account = ""
    if user:
        account += f"User={user}\n"
    if group:
        account += f"Group={group}\n"
    if user or group:
        account += ("# the devices the udev rules (99-rig.rules) give to these groups: trigger board, USB3 Vision, UVC\n"
                    f"SupplementaryGroups={' '.join(DEVICE_GROUPS)}\n")
    exec_start = " ".join([exec_word(python, command=True), "-m", "rig", "daemon", *exec_args, "-c", exec_word(config_path)])
    return f"""[Unit]
Description={description}
# stopping or restarting rig.target stops or restarts this daemon too
PartOf={TARGET}
# mDNS advertisement and network cameras want the network up
Wants=network-online.target
After=network-online.target
# keep restarting, as `rig up` does: a camera plugged in late comes up when it is there (systemd's
# default gives up after 5 starts within 10 s)
StartLimitIntervalSec=0

[Service]
# the daemon sends READY=1 once it acquires, WATCHDOG=1 from its loop, STOPPING=1 at the end (rig.daemon.notify)
Type=notify
NotifyAccess=main
ExecStart={exec_start}
Environment=PYTHONUNBUFFERED=1
Restart=on-failure
RestartSec=1
# no WATCHDOG=1 for this long: the loop hangs; systemd kills the daemon (SIGABRT) and restarts it
WatchdogSec={_seconds(watchdog_s)}
# opening a camera may take a while (a simulated camera pre-renders its loop)
TimeoutStartSec=60
# the daemon stops cleanly on SIGINT (rings and info files removed)
KillSignal=SIGINT
{account}
[Install]
WantedBy={TARGET}
"""


def camera_unit(config_path: str | os.PathLike, *, python: str = sys.executable, watchdog_s: float = 5.0,
                user: Optional[str] = None, group: Optional[str] = None) -> str:
    """`rig-camera@.service`: the template of every camera's daemon (`%i`: the camera's name)."""
    return ("# rig-camera@CAMERA.service: one camera of the rig as a daemon (written by `rig service install`)\n"
            + _service_body(description="rig camera daemon %i", exec_args=["%i"], python=_abs(python),
                            config_path=_abs(config_path), watchdog_s=check_watchdog(watchdog_s),
                            user=_check_account("user", user), group=_check_account("group", group)))


def board_unit(config_path: str | os.PathLike, *, python: str = sys.executable, watchdog_s: float = 5.0,
               user: Optional[str] = None, group: Optional[str] = None) -> str:
    """`rig-board.service`: the trigger board's owner (`rig daemon --board`), for a rig with a board."""
    return ("# rig-board.service: the rig's trigger board, owned by a daemon (written by `rig service install`)\n"
            + _service_body(description="rig trigger board daemon", exec_args=["--board"], python=_abs(python),
                            config_path=_abs(config_path), watchdog_s=check_watchdog(watchdog_s),
                            user=_check_account("user", user), group=_check_account("group", group)))


def unit_names(cfg) -> list[str]:
    """The units rig.target wants: one instance per camera of the config, and the board's unit."""
    bad = [c.name for c in cfg.cameras if not (c.name.isascii() and _CAMERA_UNIT_NAME.fullmatch(c.name))]
    if bad:
        raise ConfigError(f"camera name {bad[0]!r} cannot name a systemd unit (use ASCII letters, digits, '-' and '_')")
    from rig.cameras import records_to_card

    # no daemon for a camera that records to its card: it has no frames to serve (each take opens it)
    names = [f"rig-camera@{c.name}.service" for c in cfg.cameras if not records_to_card(c)]
    if cfg.trigger is not None:
        names.append(BOARD_UNIT)
    return names


def target_unit(cfg) -> str:
    """`rig.target`: every daemon of the rig. After= as well as Wants=: the target is reached once every
    daemon has said READY (Type=notify), and on the way down it stops before them. Wants, not Requires:
    one camera that fails does not keep the others down."""
    units = " ".join(unit_names(cfg))
    where = f" ({_text(str(cfg.path))})" if cfg.path is not None else ""
    return f"""# rig.target: the daemons of rig '{_text(cfg.name)}'{where}, written by `rig service install`;
# run it again after adding or renaming a camera. `systemctl enable --now rig.target` starts them at boot.
[Unit]
Description=rig {_text(cfg.name)}: camera daemons
Wants={units}
After={units}

[Install]
WantedBy=multi-user.target
"""


def udev_rules() -> str:
    """`99-rig.rules`: stable names and access for the rig's devices. Late (99) so that the properties
    the system rules import (usb_id, v4l_id, path_id: ID_SERIAL_SHORT, ID_USB_INTERFACES, ...) are set."""
    return f"""# 99-rig.rules: stable device names for the rig (written by `rig service install`; docs/services.md).
# Reload with `udevadm control --reload`, then replug or `udevadm trigger`.

# nothing to name or grant when a device goes away
ACTION=="remove", GOTO="rig_end"

# The trigger board (sync/firmware/trigger_board): a Raspberry Pi Pico (RP2040) with the arduino-pico
# core, a USB CDC serial port with vendor {TRIGGER_USB_VENDOR} (Raspberry Pi) and product {TRIGGER_USB_PRODUCT} (the core's Pico id).
# /dev/rig-trigger, for [trigger] uri = "serial:///dev/rig-trigger". ModemManager is told to leave it
# alone (its AT probes would garble the line protocol). Two Picos on one box: add ATTRS{{serial}}=="..."
# (`udevadm info -a /dev/ttyACM0` shows it) to tell them apart.
SUBSYSTEM=="tty", ATTRS{{idVendor}}=="{TRIGGER_USB_VENDOR}", ATTRS{{idProduct}}=="{TRIGGER_USB_PRODUCT}", SYMLINK+="rig-trigger", MODE="0660", GROUP="dialout", ENV{{ID_MM_DEVICE_IGNORE}}="1"

# USB3 Vision cameras, any vendor: the control interface has class ef, subclass 05, protocol 00 (the
# USB3 Vision standard); usb_id lists a device's interfaces in ID_USB_INTERFACES (":ccsspp:" each).
# Aravis opens the device node (/dev/bus/usb/BBB/DDD) through libusb: readable and writable by plugdev,
# and /dev/rig/u3v/<vendor id>-<serial> names it.
SUBSYSTEM=="usb", ENV{{DEVTYPE}}=="usb_device", ENV{{ID_USB_INTERFACES}}=="*:ef0500:*", MODE="0660", GROUP="plugdev"
SUBSYSTEM=="usb", ENV{{DEVTYPE}}=="usb_device", ENV{{ID_USB_INTERFACES}}=="*:ef0500:*", ENV{{ID_SERIAL_SHORT}}=="?*", SYMLINK+="rig/u3v/$env{{ID_VENDOR_ID}}-$env{{ID_SERIAL_SHORT}}"

# UVC webcams (driver uvcvideo): the capture node (index 0; a UVC camera also has a metadata node) as
# /dev/rig/video/<vendor id>-<serial>, or, for a webcam without a serial number,
# /dev/rig/video/<vendor id>-<product id>-<USB port path> (stable while it stays in the same port).
SUBSYSTEM=="video4linux", ENV{{ID_USB_DRIVER}}=="uvcvideo", MODE="0660", GROUP="video"
SUBSYSTEM=="video4linux", ENV{{ID_USB_DRIVER}}=="uvcvideo", ATTR{{index}}=="0", ENV{{ID_V4L_CAPABILITIES}}=="*:capture:*", ENV{{ID_SERIAL_SHORT}}=="?*", SYMLINK+="rig/video/$env{{ID_VENDOR_ID}}-$env{{ID_SERIAL_SHORT}}"
SUBSYSTEM=="video4linux", ENV{{ID_USB_DRIVER}}=="uvcvideo", ATTR{{index}}=="0", ENV{{ID_V4L_CAPABILITIES}}=="*:capture:*", ENV{{ID_SERIAL_SHORT}}=="", ENV{{ID_PATH_TAG}}=="?*", SYMLINK+="rig/video/$env{{ID_VENDOR_ID}}-$env{{ID_MODEL_ID}}-$env{{ID_PATH_TAG}}"

# GoPro cameras (USB vendor {GOPRO_USB_VENDOR}) in USB network (NCM) mode: their network interface named
# rig-gopro-XYZ, XYZ the last three digits of the camera's serial number: the camera answers on
# 172.2X.1YZ.51 (Open GoPro HTTP API). Not the whole serial: an interface name has at most 15 characters.
SUBSYSTEM=="net", ACTION=="add", ATTRS{{idVendor}}=="{GOPRO_USB_VENDOR}", ENV{{ID_SERIAL_SHORT}}=="???*", PROGRAM="/bin/sh -c 'echo rig-gopro-$${{0#$${{0%%???}}}}' $env{{ID_SERIAL_SHORT}}", NAME="%c"

# the end of the rig's rules
LABEL="rig_end"
"""


# ---- writing them ----------------------------------------------------------------------------------

def _abs(path: str | os.PathLike) -> str:
    """Absolute, without resolving symlinks: a virtualenv's python is a symlink that must stay one."""
    return os.path.abspath(os.fspath(path))


def systemd_is_pid1() -> bool:
    return os.path.isdir(SYSTEMD_RUN_DIR)


def _folder(dry_run_dir: Optional[Path], system_dir: str | os.PathLike) -> Path:
    system_dir = Path(_abs(system_dir))
    return system_dir if dry_run_dir is None else Path(dry_run_dir) / system_dir.relative_to(system_dir.anchor)


def _check_writable(folder: Path) -> None:
    base = folder
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        raise ConfigError(f"{folder}: {base} is a file, not a folder")
    if not os.access(base, os.W_OK):
        raise ConfigError(f"cannot write in {base}: installing services needs root (sudo), or give --dry-run DIR")


def install(config_path: str | os.PathLike, *, dry_run_dir: Optional[str | os.PathLike] = None,
            unit_dir: str | os.PathLike = UNIT_DIR, udev_dir: str | os.PathLike = UDEV_DIR,
            python: str = sys.executable, watchdog_s: float = 5.0, user: Optional[str] = None,
            group: Optional[str] = None) -> Written:
    """Write the units, the target and the udev rules, and return their paths (`Written`, a list of
    Path, with `.notes` and `.reloaded`).

    With `dry_run_dir` the files go to dry_run_dir/<the system folder's path> (e.g.
    DIR/etc/systemd/system/rig.target) and nothing else happens. Otherwise they go into `unit_dir` and
    `udev_dir`, and when systemd is PID 1 `systemctl daemon-reload` and `udevadm control --reload`
    run; when it is not, the notes say to reload. Bad input raises ConfigError (nothing written)."""
    from rig.config import load_config

    watchdog_s = check_watchdog(watchdog_s)
    _check_account("user", user)
    _check_account("group", group)
    python = _abs(python)
    if not (os.path.isfile(python) and os.access(python, os.X_OK)):
        raise ConfigError(f"{python}: not an executable Python (ExecStart= needs it)")
    cfg = load_config(config_path, check_calibration=False)
    config_abs = _abs(config_path)
    dry = Path(dry_run_dir) if dry_run_dir is not None else None
    if dry is not None and dry.exists() and not dry.is_dir():
        raise ConfigError(f"--dry-run {dry}: is a file; name a folder")
    units, rules = _folder(dry, unit_dir), _folder(dry, udev_dir)
    if dry is None and os.geteuid() != 0:
        raise ConfigError(f"writing into {units} and {rules} needs root: run it with sudo, or give --dry-run DIR")
    _check_writable(units)
    _check_writable(rules)

    files = {units / CAMERA_TEMPLATE: camera_unit(config_abs, python=python, watchdog_s=watchdog_s, user=user, group=group)}
    if cfg.trigger is not None:
        files[units / BOARD_UNIT] = board_unit(config_abs, python=python, watchdog_s=watchdog_s, user=user, group=group)
    files[units / TARGET] = target_unit(cfg)
    files[rules / UDEV_RULES] = udev_rules()
    written = Written()
    for path, text in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(text)
        tmp.chmod(0o644)
        os.replace(tmp, path)
        written.append(path)

    if cfg.trigger is not None and cfg.trigger.uri.startswith("serial://") and cfg.trigger.uri != "serial:///dev/rig-trigger":
        written.notes.append(f"the trigger board is {cfg.trigger.uri}: with the udev rule, serial:///dev/rig-trigger "
                             "stays the same whichever port it is plugged into")
    if user is not None:
        try:
            import pwd

            pwd.getpwnam(user)
        except KeyError:
            written.notes.append(f"user {user!r} does not exist on this machine: create it before starting the services")
    if dry is not None:
        written.notes.append(f"dry run: nothing installed; the units name {python} and {config_abs}: on a box with "
                             f"both, copy the tree under {dry} to / (cp -r {dry}/. /)")
    elif systemd_is_pid1():
        written.reloaded = True
        for cmd in (["systemctl", "daemon-reload"], ["udevadm", "control", "--reload"]):
            if shutil.which(cmd[0]) is None:
                written.reloaded = False
                written.notes.append(f"{cmd[0]} not found: run `{' '.join(cmd)}` where it is")
                continue
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                written.reloaded = False
                why = (proc.stderr.strip().splitlines() or [f"exit {proc.returncode}"])[-1]
                written.notes.append(f"`{' '.join(cmd)}` failed ({why}): run it again")
    else:
        written.notes.append("systemd is not running here (not PID 1): run `systemctl daemon-reload` and "
                             "`udevadm control --reload` on the box once it runs")
    return written


def next_commands() -> list[str]:
    return [f"systemctl enable --now {TARGET}", "systemctl status 'rig-camera@*'", "journalctl -u 'rig-camera@*' -f"]
