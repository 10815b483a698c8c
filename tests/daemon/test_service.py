"""The rig's daemons as systemd services (`rig service install`, rig/daemon/service.py) and the sd_notify
protocol they speak (rig/daemon/notify.py).

systemd is not PID 1 here and no udevd runs: the unit files are checked by `systemd-analyze verify`
(with negative controls: it must reject a misspelt key and a missing binary), the udev rules by a
structural parser and by udev's own rule parser (`udevadm verify` where systemd has it, else
`udevadm test` inside private mount and network namespaces, where it can rename nothing real), and
the notify datagrams on real AF_UNIX datagram sockets standing in for systemd's."""
from __future__ import annotations

import glob
import json
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from rig.sim.rig_config import sim_rig_config
from rig.config import dump_config, load_config, parse_config
from rig.daemon import notify, service
from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig

SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
UDEVADM = shutil.which("udevadm")
needs_analyze = pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze is missing (Debian package systemd; `make install` adds it)")


def rig_file(folder: Path, n: int = 3, trigger: str = "hardware", names: list[str] | None = None) -> Path:
    """A simulated rig as `rig config init --sim` writes it (hardware trigger: it has a trigger board)."""
    data = sim_rig_config(n_cameras=n, width=160, height=90, fps=30.0, trigger=trigger)
    for cam, name in zip(data["cameras"], names or []):
        cam["name"] = name
    path = folder / "rig.toml"
    path.write_text(dump_config(parse_config(data)))
    return path


def unit_folder(root: Path) -> Path:
    return root / "etc" / "systemd" / "system"


def rules_file(root: Path) -> Path:
    return root / "etc" / "udev" / "rules.d" / "99-rig.rules"


# ---- systemd-analyze verify --------------------------------------------------------------------------

def _verify_flags() -> list[str]:
    """--man=no: Documentation= is not looked up in man pages (none here, none wanted).
    --generators=no: the system's generators (fstab, getty, ...) need a booted system and say
    nothing about our files. --recursive-errors=no (systemd >= 250): only the named units' own
    problems, not those of the system units they pull in (network-online.target, multi-user.target),
    which belong to this container, not to us."""
    helptext = subprocess.run([SYSTEMD_ANALYZE, "--help"], capture_output=True, text=True).stdout
    return [flag for flag in ("--man=no", "--generators=no", "--recursive-errors=no") if flag.split("=")[0] in helptext]


def verify(*paths: Path) -> list[str]:
    """What `systemd-analyze verify` says about the unit files (empty: accepted). An instance is
    named by a path beside its template (`DIR/rig-camera@left.service` next to `DIR/rig-camera@.service`):
    verify adds the file's folder to the unit path and loads the instance from the template. Any
    output is a complaint: systemd 252 reports an unknown key on stderr and still exits 0."""
    proc = subprocess.run([SYSTEMD_ANALYZE, "verify", *_verify_flags(), *map(str, paths)], capture_output=True, text=True,
                          timeout=60, env=dict(os.environ, SYSTEMD_LOG_COLOR="0", SYSTEMD_PAGER="cat"))
    lines = [line for line in (proc.stdout + proc.stderr).splitlines() if line.strip()]
    return lines or ([f"systemd-analyze verify exited {proc.returncode}"] if proc.returncode else [])


def install_cli(*args) -> subprocess.CompletedProcess:
    return run_rig("service", "install", *args)


@needs_analyze
def test_dry_run_writes_units_that_systemd_analyze_verify_accepts(tmp_path):
    config = rig_file(tmp_path)
    out = tmp_path / "box"
    proc = install_cli("-c", config, "--dry-run", out, "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    units = unit_folder(out)
    expected = {units / "rig-camera@.service", units / "rig-board.service", units / "rig.target", rules_file(out)}
    assert {Path(p) for p in report["files"]} == expected and all(p.is_file() for p in expected)
    assert {p for p in out.rglob("*") if p.is_file()} == expected  # nothing else, no temporary files left
    assert report["dry_run"] is True and report["reloaded"] is False
    assert "systemctl enable --now rig.target" in report["next"] and any("dry run" in n for n in report["notes"])

    template = (units / "rig-camera@.service").read_text()
    for line in ("Type=notify", "NotifyAccess=main", "Restart=on-failure", "RestartSec=1", "WatchdogSec=5",
                 "TimeoutStartSec=60", "KillSignal=SIGINT", "PartOf=rig.target", "After=network-online.target",
                 "WantedBy=rig.target", f"ExecStart={sys.executable} -m rig daemon %i -c {config.absolute()}"):
        assert line in template.splitlines(), line
    assert not re.search(r"^(User|Group)=", template, re.M)
    board = (units / "rig-board.service").read_text()
    assert f"ExecStart={sys.executable} -m rig daemon --board -c {config.absolute()}" in board.splitlines()
    target = (units / "rig.target").read_text()
    cameras = [c.name for c in load_config(config).cameras]
    assert len(cameras) == 3
    wanted = " ".join([f"rig-camera@{name}.service" for name in cameras] + ["rig-board.service"])
    assert f"Wants={wanted}" in target.splitlines() and f"After={wanted}" in target.splitlines()
    assert "WantedBy=multi-user.target" in target.splitlines()

    # every unit the target wants, each camera's instance loaded from the template, accepted as written
    instances = [units / name for name in wanted.split()]
    assert verify(units / "rig.target", *instances) == []

    # the commands a user runs next, in text form
    text = install_cli("-c", config, "--dry-run", tmp_path / "box2")
    assert text.returncode == 0 and "wrote " in text.stdout and "systemctl enable --now rig.target" in text.stdout


@needs_analyze
def test_systemd_analyze_verify_rejects_a_broken_unit(tmp_path):
    """Negative controls: the check above would fail on a misspelt key or an ExecStart binary that is not there."""
    config = rig_file(tmp_path, trigger="free")
    out = tmp_path / "box"
    assert install_cli("-c", config, "--dry-run", out).returncode == 0
    units = unit_folder(out)
    assert not (units / "rig-board.service").exists()  # no trigger board, no board unit
    good = (units / "rig-camera@.service").read_text()
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "misspelt@.service").write_text(good.replace("RestartSec=1", "RestartSecs=1"))
    (bad / "nobinary@.service").write_text(good.replace(f"ExecStart={sys.executable}", "ExecStart=/nonexistent/python"))
    assert any("RestartSecs" in line for line in verify(bad / "misspelt@left.service"))
    assert any("/nonexistent/python" in line for line in verify(bad / "nobinary@left.service"))
    assert verify(units / "rig-camera@left.service") == []


@needs_analyze
def test_options_and_awkward_paths_still_give_units_systemd_accepts(tmp_path):
    """--watchdog, --user, --group; a Python and a config whose paths have a space, '%' and '$'
    (systemd's specifier and variable characters): systemd finds the executable where it is."""
    odd = tmp_path / "odd 100% $HOME"
    odd.mkdir()
    python = odd / "python"
    python.symlink_to(sys.executable)  # a venv's python is a symlink too: kept as it is, not resolved
    config = rig_file(odd, n=2)
    written = service.install(config, dry_run_dir=tmp_path / "box", python=str(python), watchdog_s=2.5, user="rigcam", group="rigcam")
    units = unit_folder(tmp_path / "box")
    template = (units / "rig-camera@.service").read_text().splitlines()
    assert "WatchdogSec=2.5" in template and "User=rigcam" in template and "Group=rigcam" in template
    assert "SupplementaryGroups=dialout plugdev video" in template
    exec_start = next(line for line in template if line.startswith("ExecStart="))
    # '%' doubled everywhere (specifiers), '$' doubled in the argument only (variables are not expanded in the command)
    command, argument = str(odd).replace("%", "%%"), str(odd).replace("%", "%%").replace("$", "$$")
    assert exec_start == f'ExecStart="{command}/python" -m rig daemon %i -c "{argument}/rig.toml"'
    assert verify(units / "rig.target", units / "rig-camera@left.service", units / "rig-board.service") == []
    assert written[0] == units / "rig-camera@.service"
    # the CLI takes the same options
    proc = install_cli("-c", config, "--dry-run", tmp_path / "box2", "--watchdog", "0.5", "--user", "rigcam", "--json")
    assert proc.returncode == 0, proc.stderr
    assert "WatchdogSec=0.5" in (unit_folder(tmp_path / "box2") / "rig-board.service").read_text().splitlines()


# ---- udev rules ----------------------------------------------------------------------------------------

MATCH_ONLY = {"ACTION", "DEVPATH", "KERNEL", "KERNELS", "SUBSYSTEM", "SUBSYSTEMS", "DRIVERS", "ATTRS", "TAGS", "CONST", "RESULT", "TEST"}
ASSIGN_ONLY = {"OWNER", "GROUP", "MODE", "SECLABEL", "RUN", "LABEL", "GOTO", "OPTIONS", "IMPORT"}
EITHER = {"NAME", "SYMLINK", "ATTR", "SYSCTL", "ENV", "TAG", "PROGRAM", "DRIVER"}
NEEDS_ATTR = {"ATTR", "ATTRS", "SYSCTL", "ENV", "CONST", "IMPORT", "SECLABEL"}
MAY_HAVE_ATTR = {"RUN", "TEST"}
PAIR = re.compile(r'\s*([A-Z]+)(?:\{([^}]*)\})?\s*(==|!=|\+=|-=|:=|=)\s*"((?:[^"\\]|\\.)*)"\s*(?:,|$)')


def udev_rule_problems(text: str) -> list[str]:
    """Structural check of a rules file (udev(7)): every line comma-separated KEY[{attr}]OP"value"
    pairs with a known key, match keys with ==/!=, assignment keys with =/+=/-=/:=."""
    problems, logical, pending, first = [], [], "", 0
    for n, line in enumerate(text.splitlines(), 1):
        first = first if pending else n
        if line.endswith("\\"):
            pending += line[:-1]
            continue
        logical.append((first, pending + line))
        pending = ""
    for n, line in logical:
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        pos = 0
        while pos < len(line):
            m = PAIR.match(line, pos)
            if not m:
                problems.append(f"line {n}: cannot parse {line[pos:pos + 40]!r}")
                break
            key, attr, op, _ = m.groups()
            if key not in MATCH_ONLY | ASSIGN_ONLY | EITHER:
                problems.append(f"line {n}: unknown key {key}")
            elif key in MATCH_ONLY and op not in ("==", "!="):
                problems.append(f"line {n}: {key} is only matched (==, !=), got {op}")
            elif key in ASSIGN_ONLY and op in ("==", "!="):
                problems.append(f"line {n}: {key} is only assigned, got {op}")
            elif key in NEEDS_ATTR and not attr:
                problems.append(f"line {n}: {key} needs {{...}}")
            elif attr is not None and key not in NEEDS_ATTR | MAY_HAVE_ATTR:
                problems.append(f"line {n}: {key} takes no {{...}}")
            pos = m.end()
    return problems


def test_udev_rules_are_well_formed_and_cover_each_device():
    rules = service.udev_rules()
    assert udev_rule_problems(rules) == []
    # the parser is neither too strict (every rules file systemd ships passes) nor blind (negative controls)
    system = glob.glob("/lib/udev/rules.d/*.rules") + glob.glob("/usr/lib/udev/rules.d/*.rules")
    for path in system:
        assert udev_rule_problems(Path(path).read_text()) == [], path
    assert udev_rule_problems('SUBSYSTEM=="tty", SYMLNK+="x"\n') == ['line 1: unknown key SYMLNK']
    assert udev_rule_problems('ATTRS{idVendor}="2e8a"\n') and udev_rule_problems('SUBSYSTEM=="tty" GROUP="x\n')

    rule_lines = [line for line in rules.splitlines() if line and not line.startswith("#")]
    for block in rules.strip().split("\n\n"):  # every group of rules starts with a comment saying what it is for
        assert block.startswith("#"), block
    trigger = next(line for line in rule_lines if 'SYMLINK+="rig-trigger"' in line)
    assert 'ATTRS{idVendor}=="2e8a"' in trigger and 'ATTRS{idProduct}=="000a"' in trigger and 'SUBSYSTEM=="tty"' in trigger
    assert any('ENV{ID_USB_INTERFACES}=="*:ef0500:*"' in line and "rig/u3v/" in line for line in rule_lines)
    assert any('SUBSYSTEM=="video4linux"' in line and "rig/video/$env{ID_VENDOR_ID}-$env{ID_SERIAL_SHORT}" in line for line in rule_lines)
    gopro = next(line for line in rule_lines if 'ATTRS{idVendor}=="2672"' in line)
    assert 'SUBSYSTEM=="net"' in gopro and 'NAME="%c"' in gopro


def test_the_gopro_interface_name_fits_the_kernel_limit():
    """The PROGRAM of the GoPro rule as udev runs it ($$ -> $, %% -> %, $env{} substituted): the last
    three digits of the serial, which are in the camera's USB address 172.2X.1YZ.51."""
    gopro = next(line for line in service.udev_rules().splitlines() if 'ATTRS{idVendor}=="2672"' in line)
    program = re.search(r'PROGRAM="([^"]*)"', gopro).group(1)
    for serial, name in (("C0000123456789", "rig-gopro-789"), ("C3461324698034", "rig-gopro-034"), ("123", "rig-gopro-123")):
        cmd = program.replace("$env{ID_SERIAL_SHORT}", serial).replace("$$", "$").replace("%%", "%")
        out = subprocess.run(shlex.split(cmd), capture_output=True, text=True, check=True).stdout.strip()
        assert out == name and len(out) <= 15  # IFNAMSIZ - 1


def _namespaces_work() -> bool:
    if UDEVADM is None or shutil.which("unshare") is None or not Path("/etc/udev/rules.d").is_dir():
        return False
    probe = subprocess.run(["unshare", "-m", "-n", "sh", "-c", "mount --make-rprivate / && mount -t sysfs sysfs /sys && "
                            "mount -t tmpfs tmpfs /run && test -e /sys/class/net/lo"], capture_output=True, text=True)
    return probe.returncode == 0


def udev_in_a_sandbox(rules_dir: Path) -> str:
    """`udevadm test` of the loopback interface with only `rules_dir`'s rules as /etc/udev/rules.d.
    udevadm test of systemd 252 acts (it renames a network interface a rule names, writes its
    database under /run/udev): so it runs in a new network namespace (its own lo, sysfs mounted
    again to show it) and a new mount namespace with a tmpfs on /run; nothing outside changes."""
    script = ("mount --make-rprivate / && mount -t sysfs sysfs /sys && mount -t tmpfs tmpfs /run && "
              f"mount --bind {shlex.quote(str(rules_dir))} /etc/udev/rules.d && udevadm test /sys/class/net/lo")
    proc = subprocess.run(["unshare", "-m", "-n", "sh", "-c", script], capture_output=True, text=True, timeout=120)
    return proc.stdout + proc.stderr


def _mentions(log: str) -> list[str]:
    """udev's lines about a line of our file: a parse complaint, or one of our rules acting on the device."""
    return [line for line in log.splitlines() if re.search(r"99-rig\.rules:\d+", line)]


def test_udev_itself_parses_the_rules(tmp_path):
    """udev's own rule parser on the written file: `udevadm verify` (systemd >= 253), else `udevadm
    test` in namespaces (systemd 252, here), with a misspelt key as the negative control; and there,
    the GoPro rule run for real on a stand-in interface."""
    out = tmp_path / "box"
    assert install_cli("-c", rig_file(tmp_path), "--dry-run", out).returncode == 0
    rules = rules_file(out)
    bad_dir = tmp_path / "bad"
    bad_dir.mkdir()
    (bad_dir / "99-rig.rules").write_text(rules.read_text().replace('SYMLINK+="rig-trigger"', 'SYMLNK+="rig-trigger"'))
    has_verify = UDEVADM is not None and subprocess.run([UDEVADM, "verify", "--help"], capture_output=True).returncode == 0
    if has_verify:
        good = subprocess.run([UDEVADM, "verify", "--resolve-names=never", str(rules)], capture_output=True, text=True)
        assert good.returncode == 0, good.stdout + good.stderr
        bad = subprocess.run([UDEVADM, "verify", "--resolve-names=never", str(bad_dir / "99-rig.rules")], capture_output=True, text=True)
        assert bad.returncode != 0
        return
    if not _namespaces_work():
        pytest.skip("no `udevadm verify` (systemd < 253) and no private mount/network namespaces (needs root and "
                    "CAP_SYS_ADMIN) to run `udevadm test` where it can change nothing")
    log = udev_in_a_sandbox(rules.parent)
    assert "Reading rules file: /etc/udev/rules.d/99-rig.rules" in log, log[-2000:]
    assert _mentions(log) == [], log[-3000:]  # parsed without a complaint, and no rule of ours touched lo
    bad_log = udev_in_a_sandbox(bad_dir)
    assert any("Invalid key 'SYMLNK'" in line for line in _mentions(bad_log)), bad_log[-3000:]

    # the GoPro rule, run by udev: lo stands in for the camera's interface, with a GoPro serial
    gopro = next(line for line in rules.read_text().splitlines() if 'ATTRS{idVendor}=="2672"' in line)
    stand_in = tmp_path / "gopro"
    stand_in.mkdir()
    (stand_in / "99-rig.rules").write_text('SUBSYSTEM=="net", KERNEL=="lo", ENV{ID_SERIAL_SHORT}="C0000123456789"\n'
                                           + gopro.replace('ATTRS{idVendor}=="2672"', 'KERNEL=="lo"') + "\n")
    log = udev_in_a_sandbox(stand_in)
    assert "NAME 'rig-gopro-789'" in log and "renamed from 'lo' to 'rig-gopro-789'" in log, log[-3000:]
    assert socket.if_nametoindex("lo") == 1  # the host's own lo is untouched


# ---- sd_notify ------------------------------------------------------------------------------------------

def _receive_all(sock: socket.socket, n: int) -> list[bytes]:
    sock.settimeout(10)
    got = [sock.recv(4096) for _ in range(n)]
    sock.settimeout(0.2)
    with pytest.raises(socket.timeout):
        got.append(sock.recv(4096))  # and nothing more
    return got


SNIPPET = ("from rig.daemon import notify; "
           "print(notify.ready('camera left acquiring'), notify.watchdog(), notify.status('half way'), notify.stopping())")
EXPECTED = [b"READY=1\nSTATUS=camera left acquiring", b"WATCHDOG=1", b"STATUS=half way", b"STOPPING=1"]


@pytest.mark.parametrize("kind", ["path", "abstract"])
def test_notify_sends_the_datagrams_systemd_reads(tmp_path, kind):
    """A subprocess with NOTIFY_SOCKET set, as systemd starts a Type=notify service, against a bound
    AF_UNIX SOCK_DGRAM socket: a file in tmp_path, or an abstract '@name' (systemd's usual form)."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        if kind == "path":
            address = str(tmp_path / "notify.sock")
            sock.bind(address)
            env_value = address
        else:
            name = f"rig-test-notify-{uuid.uuid4().hex}"
            sock.bind("\0" + name)
            env_value = "@" + name
        env = dict(os.environ, NOTIFY_SOCKET=env_value)
        proc = subprocess.run([sys.executable, "-c", SNIPPET], capture_output=True, text=True, env=env, cwd=REPO, timeout=60)
        assert proc.returncode == 0 and proc.stdout.split() == ["True"] * 4, proc.stderr
        assert _receive_all(sock, 4) == EXPECTED
    finally:
        sock.close()


def test_notify_without_a_socket_does_nothing(tmp_path, monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert notify.notify("READY=1") is False and notify.ready() is False and notify.watchdog() is False
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "gone.sock"))  # systemd's socket vanished: no exception
    assert notify.notify("READY=1") is False and notify.stopping() is False
    monkeypatch.setenv("NOTIFY_SOCKET", f"@rig-test-nobody-{uuid.uuid4().hex}")
    assert notify.status("x") is False
    proc = subprocess.run([sys.executable, "-c", SNIPPET], capture_output=True, text=True, cwd=REPO, timeout=60,
                          env={k: v for k, v in os.environ.items() if k != "NOTIFY_SOCKET"})
    assert proc.returncode == 0 and proc.stdout.split() == ["False"] * 4


def test_watchdog_interval_and_ticks(tmp_path, monkeypatch):
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    assert notify.watchdog_interval() is None
    monkeypatch.setenv("WATCHDOG_USEC", "5000000")
    assert notify.watchdog_interval() == 5.0
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert notify.watchdog_interval() == 5.0
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))  # meant for another process (e.g. our parent)
    assert notify.watchdog_interval() is None
    monkeypatch.delenv("WATCHDOG_PID")
    for bad in ("0", "-5", "soon", ""):
        monkeypatch.setenv("WATCHDOG_USEC", bad)
        assert notify.watchdog_interval() is None, bad

    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "wd.sock"))
    try:
        monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "wd.sock"))
        monkeypatch.delenv("WATCHDOG_USEC")
        silent = notify.Watchdog()
        silent.tick()  # no watchdog configured: nothing sent
        monkeypatch.setenv("WATCHDOG_USEC", "1000000")  # 1 s: a tick sends at most every 0.5 s
        wd = notify.Watchdog()
        for _ in range(5):
            wd.tick()
        assert _receive_all(sock, 1) == [b"WATCHDOG=1"]
        time.sleep(0.6)
        wd.tick()
        wd.tick()
        assert _receive_all(sock, 1) == [b"WATCHDOG=1"]
    finally:
        sock.close()


# ---- installing for real, bad input ---------------------------------------------------------------------

def test_install_into_system_folders_reloads_only_under_systemd(tmp_path, monkeypatch):
    """The real-folder path, pointed at tmp_path: without systemd as PID 1 it says to reload; with it
    (SYSTEMD_RUN_DIR standing in for /run/systemd/system) it runs systemctl and udevadm (fakes here)."""
    config = rig_file(tmp_path, n=2)
    monkeypatch.setattr(service, "SYSTEMD_RUN_DIR", str(tmp_path / "not-booted"))
    written = service.install(config, unit_dir=tmp_path / "units", udev_dir=tmp_path / "udev")
    assert [p.name for p in written] == ["rig-camera@.service", "rig-board.service", "rig.target", "99-rig.rules"]
    assert all(p.is_file() for p in written) and written.reloaded is False
    assert any("systemctl daemon-reload" in n and "udevadm control --reload" in n for n in written.notes)

    fakes, log = tmp_path / "bin", tmp_path / "calls.log"
    fakes.mkdir()
    for tool in ("systemctl", "udevadm"):
        (fakes / tool).write_text(f'#!/bin/sh\necho "{tool} $*" >> {shlex.quote(str(log))}\n')
        (fakes / tool).chmod(0o755)
    monkeypatch.setenv("PATH", f"{fakes}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setattr(service, "SYSTEMD_RUN_DIR", str(tmp_path))
    written = service.install(config, unit_dir=tmp_path / "units", udev_dir=tmp_path / "udev")
    assert written.reloaded is True and log.read_text().splitlines() == ["systemctl daemon-reload", "udevadm control --reload"]


def test_not_root_without_dry_run_is_one_line(tmp_path, monkeypatch, capsys):
    from rig.cli import main

    config = rig_file(tmp_path)
    # even if the check failed, nothing could reach /etc: the system folders point into tmp_path
    monkeypatch.setattr(service, "UNIT_DIR", str(tmp_path / "etc-systemd"))
    monkeypatch.setattr(service, "UDEV_DIR", str(tmp_path / "etc-udev"))
    monkeypatch.setattr(service.os, "geteuid", lambda: 1000)
    assert main(["service", "install", "-c", str(config)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs root" in err[0] and "--dry-run" in err[0], err
    assert not (tmp_path / "etc-systemd").exists() and not (tmp_path / "etc-udev").exists()


def test_bad_input_is_one_line_exit_2(tmp_path):
    config = rig_file(tmp_path)
    assert_one_line_error(install_cli("-c", tmp_path / "missing.toml", "--dry-run", tmp_path / "o"), "missing.toml", "no such config file")
    for value in ("0", "-1", "nan"):
        assert_one_line_error(install_cli("-c", config, "--dry-run", tmp_path / "o", "--watchdog", value), "--watchdog")
    assert_one_line_error(install_cli("-c", config, "--dry-run", tmp_path / "o", "--user", "root\nExecStartPre=/bin/evil"), "--user")
    (tmp_path / "afile").write_text("")
    assert_one_line_error(install_cli("-c", config, "--dry-run", tmp_path / "afile"), "afile")
    odd = tmp_path / "odd"
    odd.mkdir()
    assert_one_line_error(install_cli("-c", rig_file(odd, n=2, names=["caméra", "right"]), "--dry-run", tmp_path / "o"),
                          "cannot name a systemd unit")
    assert not (tmp_path / "o").exists()  # nothing written for bad input
    proc = install_cli("-c", tmp_path / "missing.toml", "--dry-run", tmp_path / "o", "--json")
    assert proc.returncode == 2 and json.loads(proc.stdout)["exit_code"] == 2
