"""Device and shared-memory checks on a fake host: each check's ok, warn and fail."""
from __future__ import annotations

import os

from rig.config import parse_config
from rig.daemon.camera_daemon import default_slots
from rig.daemon.ring import FrameRing
from rig.daemon.service import udev_rules
from rig.doctor import devices, memory
from tests.doctor.fakehost import camera, needs_of, statuses
from tests.doctor.test_doctor_usb_network import u3v_device

BOARD = {"uri": "serial:///dev/ttyACM0"}
HW = [camera("left", "sim://left", trigger="hardware")]
GROUPS = "root:x:0:\ndialout:x:20:ana\nplugdev:x:46:\nvideo:x:44:\n"


def board_check(fake, needs, **ident):
    return next(c for c in devices.checks(fake.host(**ident), needs) if c.name == "trigger board port")


def test_trigger_port_ok_warn_fail(fake):
    fake.file("etc/group", GROUPS)
    port = fake.file("dev/ttyACM0", "", mode=0o660)
    os.chown(port, 0, 20)
    needs = needs_of(HW, trigger=BOARD)
    c = board_check(fake, needs, uid=1000, gids=frozenset({1000}), name="bob")
    assert c.status == "fail" and c.fix == "sudo usermod -aG dialout bob"
    c = board_check(fake, needs, uid=1000, gids=frozenset({1000}), name="ana")  # in /etc/group, not in this login
    assert c.status == "fail" and c.fix is None and "log out and in again" in c.note
    c = board_check(fake, needs, uid=1000, gids=frozenset({1000, 20}), name="ana")
    assert c.status == "warn" and "serial:///dev/rig-trigger" in c.note  # /dev/ttyACM0 can change at a replug
    (fake.root / "dev/rig-trigger").symlink_to("ttyACM0")
    c = board_check(fake, needs_of(HW, trigger={"uri": "serial:///dev/rig-trigger"}), uid=1000, gids=frozenset({20}), name="ana")
    assert c.status == "ok"
    c = board_check(fake, needs_of(HW, trigger={"uri": "serial:///dev/ttyUSB7"}))
    assert c.status == "fail" and "missing" in c.measured
    assert board_check(fake, needs_of(HW, trigger={"uri": "sim://trigger"})).status == "ok"


def rules_check(fake, needs):
    return next(c for c in devices.checks(fake.host(), needs) if c.name.startswith("udev rules"))


def test_udev_rules_ok_warn_fail(fake):
    needs = needs_of(HW, trigger=BOARD, path="/srv/rig.toml")
    c = rules_check(fake, needs)
    assert c.status == "warn" and "-m rig service install -c /srv/rig.toml" in c.fix
    assert rules_check(fake, needs_of([camera("s", "sim://s")])).status == "ok"  # nothing of the rig needs them
    fake.file("etc/udev/rules.d/99-rig.rules", "# an older version\n")
    assert rules_check(fake, needs).status == "warn"
    fake.file("etc/udev/rules.d/99-rig.rules", udev_rules())
    assert rules_check(fake, needs).status == "ok"
    fake.program("udevadm", "", rc=1, stderr="99-rig.rules:12 Invalid key/value pair, ignoring.\n")
    c = rules_check(fake, needs)
    assert c.status == "fail" and "Invalid key/value pair" in c.measured
    fake.program("udevadm", "", rc=1, stderr="Unknown command verb verify.\n")  # udevadm before systemd 254
    assert rules_check(fake, needs).status == "ok"


def test_camera_device_nodes(fake):
    fake.file("etc/group", GROUPS)
    assert statuses(devices.checks(fake.host(), needs_of([camera("s", "sim://s")])))["camera devices"] == "ok"
    cams = [camera("cam", "uvc:///dev/video0", trigger="free"), camera("u", "aravis://Basler-22012345")]
    u3v_device(fake, "2-1", "22012345")
    st = statuses(devices.checks(fake.host(), needs_of(cams)))
    assert st["webcam cam"] == "fail" and st["USB3 Vision u"] == "fail"  # no device nodes
    os.chown(fake.file("dev/video0", mode=0o660), 0, 44)
    os.chown(fake.file("dev/bus/usb/002/005", mode=0o660), 0, 46)
    checks = devices.checks(fake.host(uid=1000, gids=frozenset({1000}), name="bob"), needs_of(cams))
    assert statuses(checks) | {} == {"trigger board port": "ok", "udev rules (99-rig.rules)": "warn",
                                     "USB3 Vision u": "fail", "webcam cam": "fail"}
    assert {c.fix for c in checks if c.status == "fail"} == {"sudo usermod -aG plugdev bob", "sudo usermod -aG video bob"}
    st = statuses(devices.checks(fake.host(uid=1000, gids=frozenset({44, 46}), name="bob"), needs_of(cams)))
    assert st["webcam cam"] == "ok" and st["USB3 Vision u"] == "ok"


RING_CAMS = [camera("left", "sim://left", width=1280, height=720, pixel_format="RGB8"),
             camera("right", "sim://right", width=1280, height=720, pixel_format="RGB8")]


def df(fake, size: int, avail: int, mount="/dev/shm") -> None:
    fake.program("df", f"Mounted on         1B-blocks       Avail\n{mount} {size} {avail}\n")


def test_shared_memory_ok_warn_fail(fake):
    needs = needs_of(RING_CAMS)
    ring = needs.cameras[0].ring_bytes
    # what a daemon's ring of that camera really takes
    made = FrameRing.create(fake.root / "ring", slots=default_slots(parse_config({"cameras": RING_CAMS}).camera("left")), height=720, width=1280,
                            channels=3, dtype="uint8", pixel_format="RGB8", camera="left")
    made.close(unlink=False)
    assert (fake.root / "ring").stat().st_size == ring
    df(fake, 64 << 20, 64 << 20)  # a container's default /dev/shm
    [c] = memory.checks(fake.host(), needs)
    assert c.status == "fail" and c.fix.startswith("sudo mount -o remount,size=") and c.fix.endswith("M /dev/shm")
    df(fake, 1 << 30, 2 * ring + ring // 2)
    assert memory.checks(fake.host(), needs)[0].status == "warn"  # no room for a restarting daemon's new ring
    # rings this rig's daemons already hold count as room: they are replaced
    fake.file("dev/shm/rig/venue/left", "x" * 1000)
    df(fake, 1 << 30, 3 * ring)
    assert memory.checks(fake.host(), needs)[0].status == "ok"
    assert memory.checks(fake.host(), needs_of([camera("g", "gopro://C123?record=card", trigger="free", width=3840,
                                                       height=2160, fps=30.0)]))[0].status == "ok"


def test_the_udev_fix_names_the_config_by_its_absolute_path(fake, tmp_path, monkeypatch):
    """`rig doctor -c rig.toml --fix-script fix.sh`: the fix said `-c rig.toml`, which `bash fix.sh`
    run from another folder (or `sudo bash` from /root) does not find."""
    monkeypatch.chdir(tmp_path)
    c = rules_check(fake, needs_of(HW, trigger=BOARD, path="rig.toml"))
    assert c.fix.endswith(f"-m rig service install -c {tmp_path / 'rig.toml'}")
