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
    assert report["verdict"] == "pass" and report["failures"] == []
    assert report["limits"] == {"skew_p99_us": 1000.0, "clock_residual_p99_us": 1000.0, "drop_rate": 0.05, "mismatched_sets": 0, "errors": 0}


def test_sync_check_fails_a_limit_with_exit_1_and_says_which(tmp_path):
    """50 us trigger jitter per camera cannot meet a 1 us exposure-skew limit: verdict fail, exit 1."""
    proc = rig("sync", "check", "-c", write_rig(tmp_path), "--seconds", "1", "--max-skew-us", "1", "--json")
    assert proc.returncode == 1, proc.stderr
    report = json.loads(proc.stdout)
    assert report["verdict"] == "fail" and report["limits"]["skew_p99_us"] == 1.0
    assert len(report["failures"]) == 1 and "exposure skew p99" in report["failures"][0]


def test_sync_check_prints_a_summary(tmp_path):
    proc = rig("sync", "check", "-c", write_rig(tmp_path), "--seconds", "1")
    assert proc.returncode == 0, proc.stderr
    assert "mismatched 0" in proc.stdout and "exposure skew us" in proc.stdout and "truth:" in proc.stdout
    # the verdict, the limits it was judged against, and what this skew is next to validate's
    lines = proc.stdout.strip().splitlines()
    assert lines[-1] == "verdict: PASS" and lines[-2].startswith("limits: exposure skew p99 <= 1000 us")
    assert "arrival skew" in proc.stdout and "rig record validate" in proc.stdout


def test_sync_check_bad_input_is_one_line(tmp_path):
    missing = rig("sync", "check", "-c", tmp_path / "none.toml")
    assert missing.returncode == 2 and len(missing.stderr.strip().splitlines()) == 1 and "no such config file" in missing.stderr
    zero = rig("sync", "check", "-c", write_rig(tmp_path), "--seconds", "0")
    assert zero.returncode == 2 and "--seconds must be positive" in zero.stderr and "Traceback" not in zero.stderr
    negative = rig("sync", "check", "-c", write_rig(tmp_path), "--max-drop-rate", "-0.5")
    assert negative.returncode == 2 and len(negative.stderr.strip().splitlines()) == 1 and "--max-drop-rate" in negative.stderr
    helped = rig("sync", "check", "--help")
    assert helped.returncode == 0 and "--seconds" in helped.stdout
