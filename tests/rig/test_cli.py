"""The `rig` command line: help everywhere, discovery of every backend."""
from __future__ import annotations

import json

import pytest

from tests.rig.cli_helpers import run_rig

SUBCOMMANDS = [["config", "init"], ["config", "check"], ["discover"], ["grab"], ["demo"]]


def test_help():
    proc = run_rig("--help")
    assert proc.returncode == 0 and "grab" in proc.stdout and "discover" in proc.stdout


@pytest.mark.parametrize("cmd", SUBCOMMANDS, ids=[" ".join(c) for c in SUBCOMMANDS])
def test_every_subcommand_has_help(cmd):
    proc = run_rig(*cmd, "--help")
    assert proc.returncode == 0, proc.stderr
    assert "usage:" in proc.stdout


def test_discover_lists_sim_devices_as_json():
    proc = run_rig("discover", "--json")
    assert proc.returncode == 0, proc.stderr
    devices = json.loads(proc.stdout)
    sims = [d for d in devices if d["backend"] == "sim"]
    assert {d["uri"] for d in sims} >= {"sim://left", "sim://right"}
    for d in devices:
        assert {"uri", "backend", "model", "serial"} <= set(d)


def test_discover_finds_the_fake_gige_camera(fake_camera):
    proc = run_rig("discover", "--json")
    devices = json.loads(proc.stdout)
    aravis = [d for d in devices if d["backend"] == "aravis"]
    assert any(d["uri"] == "aravis://127.0.0.1" and d["serial"] == "GV01" for d in aravis), aravis


def test_unknown_command_is_one_line():
    proc = run_rig("frobnicate")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
