"""`rig doctor`: checks this host for this rig, one line per check (ok, warn or fail), with what was
measured, what the rig needs, and the command that fixes it. It reads and measures; it never changes
the host (`--fix-script` writes the fixes for the user to review).

Modules, one job each: `host` (files under a root folder, programs through one runner, who runs the
rig), `needs` (what the config asks of a host), `routes` and `firewall` (the network's view of a
camera), `space` (room on a filesystem), the checks by area (`usb`, `network`, `devices`, `memory`,
`disk`, `compute`), and `report` (text, JSON, fix script).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from rig.config import RigConfig
from rig.doctor import compute, devices, disk, memory, network, usb
from rig.doctor.check import Check
from rig.doctor.host import Host
from rig.doctor.needs import rig_needs

AREAS = ("usb", "network", "devices", "memory", "disk", "compute")


def run_checks(cfg: RigConfig, host: Host, *, output: Path, minutes: float, bench: Optional[dict] = None,
               bench_path: Optional[Path] = None, test_bytes: int = disk.TEST_BYTES) -> list[Check]:
    needs = rig_needs(cfg)
    return [*usb.checks(host, needs), *network.checks(host, needs), *devices.checks(host, needs),
            *memory.checks(host, needs), *disk.checks(host, needs, output, minutes, test_bytes),
            *compute.checks(host, needs, bench, bench_path)]
