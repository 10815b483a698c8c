"""`rig demo` end to end on the smallest rig that does the whole job: two simulated cameras are
calibrated from a board carried through the volume, a short take is recorded with the calibration,
and the take validates as readable and calibrated.

Kept short: half a second of take and 12 calibration views. Fewer views do not do: the board is
carried on a 20 s path and each end camera of a two-camera arc sees it on only part of it (left
from about 7 s, right until about 10 s of scene time), so a capture of 12 views, one every 0.25 s
from about 4 s on, is what gives both cameras the four board images the solver needs.
"""
from __future__ import annotations

import json

import pytest

from tests.rig.cli_helpers import run_rig


@pytest.mark.slow
def test_demo_calibrates_records_and_validates_a_two_camera_rig(tmp_path):
    out = tmp_path / "demo"
    proc = run_rig("demo", "-o", out, "--cameras", 2, "--seconds", 0.5, "--views", 12, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "4/4  validated: readable" in proc.stdout and "calibrated: True" in proc.stdout

    take = out / "take"
    assert (take / "calibration.json").is_file()
    proc = run_rig("record", "validate", take, "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["readable"] is True and report["calibrated"] is True
    assert report["sets"] >= 5 and report["errors"] == []
    assert set(report["frames"]) == {"left", "right"}
