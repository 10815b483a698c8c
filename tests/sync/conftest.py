"""Fixtures of the sync tests: the shared protocol vectors, the firmware built on the host, an
emulated trigger board and a connected host driver."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
VECTORS = REPO / "sync" / "protocol_vectors.json"
FIRMWARE = REPO / "sync" / "firmware"


@pytest.fixture(scope="session")
def vectors() -> dict:
    return json.loads(VECTORS.read_text())


@pytest.fixture(scope="session")
def firmware_host(tmp_path_factory) -> Path:
    """The firmware's protocol and board logic, compiled for this machine with g++ (strict warnings)."""
    gxx = shutil.which("g++")
    if gxx is None:
        pytest.skip("g++ is not installed: cannot build the firmware's C code on the host")
    out = tmp_path_factory.mktemp("firmware") / "tb_host"
    src = FIRMWARE / "trigger_board"
    cmd = [gxx, "-std=c++17", "-O1", "-Wall", "-Wextra", "-Werror", "-x", "c++", str(src / "tb_protocol.c"),
           "-x", "c++", str(src / "tb_board.c"), "-x", "c++", str(FIRMWARE / "host" / "tb_host.cpp"), "-o", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.fixture
def emulator():
    from simulator.trigger_board import TriggerBoardEmulator

    emu = TriggerBoardEmulator({"seed": 1}).open()
    yield emu
    emu.close()


@pytest.fixture
def board(emulator):
    from sync.board import TriggerBoard

    b = TriggerBoard(emulator.url)
    b.connect()
    yield b
    b.close()
