"""The `rig` command line: help everywhere, one line for an unknown command (discovery: test_discover.py)."""
from __future__ import annotations

import pytest

from rig.commands import build_parser
from tests.rig.cli_helpers import run_rig
from tests.rig.test_args import _leaves

# every command, found by walking the parser: one added later is covered too
SUBCOMMANDS = [list(words) for words, _ in _leaves(build_parser())]


def test_help():
    proc = run_rig("--help")
    assert proc.returncode == 0 and "grab" in proc.stdout and "discover" in proc.stdout
    assert len(SUBCOMMANDS) >= 16 and ["record"] in SUBCOMMANDS and ["sim", "snapshot"] in SUBCOMMANDS


@pytest.mark.parametrize("cmd", SUBCOMMANDS, ids=[" ".join(c) for c in SUBCOMMANDS])
def test_every_subcommand_has_help(cmd):
    proc = run_rig(*cmd, "--help")
    assert proc.returncode == 0, proc.stderr
    assert "usage:" in proc.stdout


def test_unknown_command_is_one_line():
    proc = run_rig("frobnicate")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
