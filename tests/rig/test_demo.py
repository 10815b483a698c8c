"""`rig demo` end to end on the smallest rig that does the whole job: two simulated cameras are
calibrated from a board held at stations through the volume, a short take is recorded with the
calibration, and the take validates as readable and calibrated.

Kept short: half a second of take and 12 calibration views (a two-camera session interleaves views
both cameras see with views of each camera alone, so the first 12 give each camera more than the
four the solver needs). The simulated calibration session counts its time in views, not in host
time, so what the capture sees does not depend on start-up time or render speed: the test is
deterministic. Bad arguments are refused before anything is rendered or written.
"""
from __future__ import annotations

import json

import cv2
import time

import pytest

from rig.cli import main
from tests.rig.cli_helpers import run_rig


@pytest.mark.slow
def test_demo_calibrates_records_and_validates_a_two_camera_rig(tmp_path):
    out = tmp_path / "demo"
    proc = run_rig("demo", "-o", out, "--cameras", 2, "--seconds", 0.25, "--views", 12, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "4/5  validated: readable" in proc.stdout and "calibrated: True" in proc.stdout
    # The calibration report's warnings are shown (12 views are too few to trust the intrinsics),
    # and the result is compared with the simulator's exact cameras.
    assert "warning: camera 'left': only" in proc.stdout
    assert "against the simulator's exact cameras (worst camera): focal" in proc.stdout
    # Disk: estimated before, measured after.
    assert "the demo writes about" in proc.stdout and "disk: " in proc.stdout and " written into " in proc.stdout
    # With the shipped model: an orbit video and a strip (left | novel views | right) of the take,
    # and how to run the same rig live.
    from rig.live.video import read_frame_count

    strip = cv2.imread(str(out / "novel-strip.png"))
    assert strip is not None and strip.shape[1] == 5 * strip.shape[0] * 16 // 9
    assert read_frame_count(out / "orbit.mp4") >= 5
    assert f"live: `rig live -c {out / 'rig.toml'}`" in proc.stdout

    take = out / "take"
    assert (take / "calibration.json").is_file()
    proc = run_rig("record", "validate", take, "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["readable"] is True and report["calibrated"] is True
    assert report["sets"] >= 5 and report["errors"] == []
    assert set(report["frames"]) == {"left", "right"}


def test_demo_gopro_records_two_gopros_beside_the_sources_and_aligns_them(tmp_path):
    """`rig demo --gopro`: two GoPro emulators through the gopro:// backend beside the triggered
    sources; after `rig record align` every GoPro frame is in its true set (the simulator's truth)."""
    out = tmp_path / "demo"
    proc = run_rig("demo", "--gopro", "-o", out, "--seconds", 4, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    truth = [line for line in proc.stdout.splitlines() if "against the simulator's truth" in line]
    assert len(truth) == 2 and all(" 0 in the wrong set" in line for line in truth), proc.stdout
    report = json.loads((out / "take" / "alignment.json").read_text())
    assert set(report["cameras"]) == {"sup1", "sup2"} and all(c["problem"] is None and c["placed"] > 20 for c in report["cameras"].values())
    proc = run_rig("record", "validate", out / "take", "--json")
    assert proc.returncode == 0 and json.loads(proc.stdout)["readable"] is True


@pytest.mark.parametrize("argv, fragment", [
    (["--cameras", "1"], "--cameras"),
    (["--cameras", "65"], "--cameras"),
    (["--seconds", "-1"], "--seconds"),
    (["--seconds", "nan"], "--seconds"),
    (["--width", "0"], "--width"),
    (["--views", "2"], "--views"),
    (["--gopro", "0"], "--gopro"),
    (["--gopro", "9"], "--gopro"),
    (["--gopro", "2", "--cameras", "4"], "--cameras"),
    (["--gopro", "--views", "8"], "--views"),
])
def test_bad_arguments_are_refused_before_any_work(tmp_path, capsys, argv, fragment):
    start = time.monotonic()
    rc = main(["demo", "-o", str(tmp_path / "d"), *argv])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and err.startswith("rig: error:") and fragment in err, err
    assert time.monotonic() - start < 5 and not (tmp_path / "d").exists()


def test_a_folder_with_an_earlier_demo_or_other_files_is_refused(tmp_path, capsys):
    (tmp_path / "take").mkdir()
    assert main(["demo", "-o", str(tmp_path)]) == 2 and "earlier demo" in capsys.readouterr().err
    other = tmp_path / "other"
    other.mkdir()
    (other / "rig.toml").write_text("mine\n")
    assert main(["demo", "-o", str(other)]) == 2 and "not empty" in capsys.readouterr().err
    assert (other / "rig.toml").read_text() == "mine\n"
