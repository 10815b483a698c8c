"""A gap in a camera's frame ids is frames lost, whatever lost them: here `rig record` stalls past
its daemons' one-second rings (stopped for 2.5 s), so both free-running cameras lose the same span
and no set is left to mark it missing. Before, the take said 0 lost, 0 missing, no error."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest

from rig.storage.layout import INDEX
from rig.storage.validate import validate
from tests.daemon.test_daemon import Up, communicate, rig_file, wait_running
from tests.rig.cli_helpers import REPO

pytestmark = pytest.mark.timeout(240)


def test_a_recorder_stalled_past_the_daemons_rings_counts_the_gap_as_lost_frames(tmp_path):
    config = rig_file(tmp_path, n=2, trigger="free")
    up = Up(config, tmp_path / "shm")
    take = tmp_path / "take"
    try:
        wait_running(up.root, "sim-2cam", 2)
        rec = subprocess.Popen([sys.executable, "-m", "rig", "record", "-c", str(config), "-o", str(take), "--seconds", "6", "--json"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=up.env)
        deadline = time.monotonic() + 60
        while not (take / INDEX).exists() or (take / INDEX).stat().st_size < 4000:
            assert rec.poll() is None and time.monotonic() < deadline, rec.communicate()
            time.sleep(0.05)
        rec.send_signal(signal.SIGSTOP)  # the daemons keep writing their rings; nobody reads them
        time.sleep(2.5)
        rec.send_signal(signal.SIGCONT)
        out, err = communicate(rec, 120)
    finally:
        print(up.stop())
    summary = json.loads(out)
    assert rec.returncode == 1, err  # frames lost is an error of the take
    lost = summary["frames_lost"]
    for cam in ("left", "right"):
        # 2.5 s at 30 fps, less the ring's second; frames_lost also counts frames placed in sets and
        # not written
        assert lost[cam] >= summary["lost_in_transfer"][cam] >= 30, summary
        gap = summary["id_gaps"][cam][0]
        assert gap["next_id"] - gap["after_id"] - 1 == gap["lost"] and 1.0 < gap["at_s"] < 5.0, gap
    assert "frames lost" in err and "left" in err and "right" in err
    # the take keeps every set before and after, and `rig record validate` counts the same loss
    v = validate(take)
    assert v.readable, v.errors
    for cam in ("left", "right"):
        # the take's gap may be a frame or two wider: a frame that came after the stall but fitted
        # no set (paired by time) is not in the take either
        assert summary["lost_in_transfer"][cam] <= v.frames_lost[cam] <= lost[cam] + 3, (v.frames_lost, summary)
    assert any("frames lost" in w for w in v.warnings)
    shown = subprocess.run([sys.executable, "-m", "rig", "record", "validate", str(take)], capture_output=True, text=True, cwd=REPO)
    assert shown.returncode == 0
    assert f"{v.frames_lost['left']} lost (gaps in its frame ids)" in shown.stdout
    assert "arrival spread" in shown.stdout and "exposure skew: not measured" in shown.stdout
