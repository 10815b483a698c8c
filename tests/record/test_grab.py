"""`rig grab` on the simulated rig: N whole PNGs per camera, listed in frames.jsonl, even on a full disk."""
from __future__ import annotations

import json

import cv2

from tests.record.test_record import rig_file
from tests.rig.cli_helpers import run_rig


def listed(out):
    return [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]


def files_in(out):
    return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())


def test_grab_writes_n_whole_pngs_per_camera(tmp_path):
    out = tmp_path / "grab"
    proc = run_rig("grab", "-c", rig_file(tmp_path), "-n", 4, "-o", out, "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["frames"] == {"left": 4, "right": 4} and summary["errors"] == []
    records = listed(out)
    assert sorted((r["camera"], r["file"]) for r in records) == [
        (cam, f"{cam}/{i:06d}.png") for cam in ("left", "right") for i in range(4)]
    for r in records:
        assert cv2.imread(str(out / r["file"])).shape == (90, 160, 3)
    assert files_in(out) == sorted(["frames.jsonl"] + [r["file"] for r in records])  # no temporary file is left


def test_full_disk_ends_the_grab_with_every_listed_frame_whole(tmp_path, small_filesystem):
    out = small_filesystem(1) / "grab"  # room for two or three 640x360 PNGs
    proc = run_rig("grab", "-c", rig_file(tmp_path, 640, 360), "-n", 5, "-o", out, "--json")
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1].startswith("rig: error: ") and "could not write image" in proc.stderr
    summary = json.loads(proc.stdout)  # the summary is still printed, with the error
    assert len(summary["errors"]) == 1 and "could not write image" in summary["errors"][0]
    records = listed(out)
    assert 0 < len(records) < 10 and sum(summary["frames"].values()) == len(records)
    for r in records:
        assert cv2.imread(str(out / r["file"])).shape == (360, 640, 3)
    assert files_in(out) == sorted(["frames.jsonl"] + [r["file"] for r in records])  # nor the failed write's
