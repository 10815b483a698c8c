"""A session that opens the rig's trigger board while the board's daemon is down (killed, its
supervisor restarting it) waits for the daemon instead of opening the board in its own process.
The soak caught it: a take that began in that gap ran an emulated board of its own beside the
restarted daemon's, the cameras were fired by two pulse trains, and sets paired frames of
different pulses."""
from __future__ import annotations

import os
import subprocess
import threading
import time

import pytest

from common.files import atomic_write_json
from rig.config import parse_config
from rig.daemon import board_client, paths
from rig.sim.rig_config import sim_rig_config
from sync.errors import TriggerBoardError


def dead_pid() -> int:
    p = subprocess.Popen(["true"])
    p.wait()
    return p.pid


@pytest.fixture
def rig(tmp_path, monkeypatch):
    monkeypatch.setenv("RIG_SHM_ROOT", str(tmp_path / "shm"))
    config = parse_config({**sim_rig_config(2, 160, 90, 15.0), "rig": {"name": "gap", "storage": str(tmp_path / "takes")}})
    paths.board_info_path(config.name).parent.mkdir(parents=True, exist_ok=True)
    return config


def test_a_session_waits_for_the_restarted_board_daemon(rig):
    path = paths.board_info_path(rig.name)
    atomic_write_json(path, {"pid": dead_pid()})
    back = {"pid": os.getpid(), "api": "http://127.0.0.1:9"}
    threading.Timer(0.6, lambda: atomic_write_json(path, back)).start()
    t0 = time.monotonic()
    info = board_client.board_daemon_back(rig.name, within_s=10)
    assert info["pid"] == os.getpid() and 0.5 < time.monotonic() - t0 < 5


def test_a_board_daemon_that_stays_gone_is_one_error_not_a_board_of_the_sessions_own(rig, monkeypatch):
    atomic_write_json(paths.board_info_path(rig.name), {"pid": dead_pid()})
    monkeypatch.setattr(board_client, "BOARD_BACK_S", 1.0)
    with pytest.raises(TriggerBoardError, match="is gone and did not come back within 1 s"):
        board_client.open_board(rig, {})


def test_without_a_board_daemon_the_board_opens_in_the_session(rig):
    board, device = board_client.open_board(rig, {})
    try:
        assert device is not None  # the emulated board behind sim://trigger, in this process
    finally:
        device.close()
