"""`rig sync check` from the command line, as a user runs it."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from rig.config import dump_config, parse_config

REPO = Path(__file__).resolve().parents[2]


def rig(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "rig", *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=REPO)


def write_rig(tmp_path) -> Path:
    from test_sync_session import sim_rig

    path = tmp_path / "rig.toml"
    path.write_text(dump_config(parse_config(sim_rig({"drift_ppm": 100.0, "reply_jitter_us": 200.0, "seed": 9}))))
    return path


def test_sync_check_json_reports_every_figure(tmp_path):
    proc = rig("sync", "check", "-c", write_rig(tmp_path), "--seconds", "2", "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    for key in ("pulses", "frames", "complete_sets", "mismatched_sets", "drops_detected", "skew_us", "clock_residual_us", "drift_ppm"):
        assert key in report
    assert report["pulses"] == 60 and report["mismatched_sets"] == 0
    assert set(report["frames"]) == {"left", "right"} and set(report["skew_us"]) == {"p50", "p99", "max"}
    assert report["clock_residual_source"] == "emulator truth"
    assert proc.stdout.count("\n") == 1


def test_sync_check_prints_a_summary(tmp_path):
    proc = rig("sync", "check", "-c", write_rig(tmp_path), "--seconds", "1")
    assert proc.returncode == 0, proc.stderr
    assert "mismatched 0" in proc.stdout and "skew us" in proc.stdout and "truth:" in proc.stdout


def test_sync_check_bad_input_is_one_line(tmp_path):
    missing = rig("sync", "check", "-c", tmp_path / "none.toml")
    assert missing.returncode == 2 and len(missing.stderr.strip().splitlines()) == 1 and "no such config file" in missing.stderr
    zero = rig("sync", "check", "-c", write_rig(tmp_path), "--seconds", "0")
    assert zero.returncode == 2 and "--seconds must be positive" in zero.stderr and "Traceback" not in zero.stderr
    helped = rig("sync", "check", "--help")
    assert helped.returncode == 0 and "--seconds" in helped.stdout
