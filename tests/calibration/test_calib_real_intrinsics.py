"""`rig calibrate intrinsics` on real photos: four motion-capture lab cameras, seven hand-held
chessboard photos each (../shared/data/pose2sim-4cam-chessboard), against the lab's Qualisys
calibration of the same cameras."""
from __future__ import annotations

import re

import pytest

from tests.calibration.cli_helpers import run_json


@pytest.fixture(scope="module")
def pose2sim(shared_data):
    return shared_data / "pose2sim-4cam-chessboard"


def reference_fx(folder) -> dict[str, float]:
    """focalLengthU per camera serial, in 1/64 px in the Qualisys file."""
    text = (folder / "reference-qualisys.qca.txt").read_text()
    cams = re.findall(r'serial="(cam\d+)".*?focalLengthU="([\d.]+)"', text, re.S)
    return {name: float(f) / 64.0 for name, f in cams}


@pytest.fixture(scope="module")
def intrinsics_run(pose2sim, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("intrinsics")
    board = tmp / "board.toml"
    board.write_text('type = "chessboard"\ncols = 4\nrows = 7\nsquare_size = 0.06\n')
    return run_json("calibrate", "intrinsics", "--images", pose2sim, "--board", board, "-o", tmp / "intrinsics.json")


def test_focal_lengths_match_the_mocap_calibration_within_one_percent(intrinsics_run, pose2sim):
    ref = reference_fx(pose2sim)
    cams = intrinsics_run["cameras"]
    assert sorted(cams) == ["cam01", "cam02", "cam03", "cam04"] == sorted(ref)
    for name, c in cams.items():
        assert abs(c["fx"] / ref[name] - 1) < 0.01, (name, c["fx"], ref[name])
        assert c["rms_px"] < 0.3, (name, c["rms_px"])
        assert c["verdict"] == "good" and c["focal_spread_pct"] is not None and c["focal_spread_pct"] < 1.0, (name, c)


def test_every_photo_dropped_says_one_reason(intrinsics_run):
    for name, c in intrinsics_run["cameras"].items():
        assert c["views_used"] + len(c["rejected"]) + len(c["not_found"]) == 7, (name, c)
        for r in c["rejected"]:
            assert r["reason"].startswith("reprojection RMS") and r["rms_px"] > 1.0, r
    # cam04_07 does not fit the lens the other five photos agree on; cam02_06 shows no board
    assert [r["view"] for r in intrinsics_run["cameras"]["cam04"]["rejected"]] == ["cam04_07"]
    assert intrinsics_run["cameras"]["cam02"]["not_found"] == ["cam02_06"]
