"""The soak of benchmarks/soak.py for one minute: the six-camera simulated rig under `rig up`, `rig
record` writing takes back to back while `rig live` serves a viewer (the two sessions share the
trigger board's daemon), and a daemon killed with kill -9 every 15 s. Every kill recovers, every
take validates, no set is mismatched, and no process gains file descriptors. (The ten-minute run and
its figures: docs/daemons.md.) Before the board was shared, every take refused to start while the
live view held the board (BUSY)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.rig.cli_helpers import REPO

pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]


def test_one_minute_of_kills_with_takes_back_to_back_and_a_live_viewer(tmp_path):
    out = tmp_path / "soak"
    run = subprocess.run([sys.executable, str(REPO / "benchmarks" / "soak.py"), "--minutes", "1", "--kill-every", "15",
                          "--take-seconds", "15", "--warm-up", "20", "--out", str(out), "--json"],
                         cwd=REPO, capture_output=True, text=True, timeout=400)
    result = json.loads(run.stdout.strip().splitlines()[-1])
    print(json.dumps({k: v for k, v in result.items() if k not in ("takes",)}, indent=1))
    assert len(result["kills"]) >= 3
    for k in result["kills"]:
        assert k["daemon_back_s"] is not None and k["daemon_back_s"] < 10, k
        assert k["live_frames_again_s"] is not None and k["live_frames_again_s"] < 15, k
    takes = result["takes"]
    assert len(takes) >= 3 and all(t["readable"] for t in takes), takes
    assert all(t["sets"] and t["sets"] > 100 for t in takes[:-1]), takes  # each take ran its length (15 s at 15 Hz)
    assert result["mismatched_sets"] == 0
    for role, g in result["growth"].items():
        assert g["fds"] <= 0.10, (role, g)
        assert g["rss"] <= 0.25, (role, g)  # a minute is short: the ten-minute run holds it to 10 %
    assert result["viewer"]["frames"] > 50
    assert (out / "soak.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert run.returncode == (0 if result["verdict"] == "pass" else 1), run.stderr[-2000:]
