"""`rig train --resume` with another stage-1 length than the checkpoint's (trial-model): a
checkpoint inside stage 1 resumed with --stage1-steps below its step loaded stage 1's optimiser
state into stage 2's (a ValueError traceback, exit 1); a schedule a resume changed was forgotten by
the next plain --resume (train.json kept the first run's), which then went back into stage 1."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from simulator.takes import write_take
from tests.rig.cli_helpers import assert_one_line_error

pytestmark = pytest.mark.slow

ARGS = ["--size", "test", "--batch", "1", "--eval-every", "100", "--threads", "1"]
LIGHT = {"supervision_per_step": 1, "eval_sets": 1}


def rig(*args) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "rig", *map(str, args)], capture_output=True, text=True, timeout=600, env=env)


def test_resume_with_another_stage1_length(tmp_path):
    take = Path(write_take(tmp_path / "take", seed=7, seconds=0.3, fps=10, size=(320, 180))["out"])
    light = tmp_path / "light.json"
    light.write_text(json.dumps(LIGHT))
    out = tmp_path / "run"
    r = rig("train", take, "-o", out, *ARGS, "--config", light, "--stage1-steps", "6", "--stage2-steps", "3", "--stop-after", "3")
    assert r.returncode == 0, r.stderr
    before = (out / "checkpoint.pt").read_bytes()

    # step 3 of stage 1; a stage 1 of 2 steps would start stage 2 half way with stage 1's optimiser
    r = rig("train", take, "-o", out, "--resume", "--stage1-steps", "2", "--stop-after", "1")
    assert_one_line_error(r, "at step 3, in stage 1", "--stage1-steps 3")
    assert (out / "checkpoint.pt").read_bytes() == before  # nothing saved was lost

    # ending stage 1 at the checkpoint is allowed: stage 2 starts
    r = rig("train", take, "-o", out, "--resume", "--stage1-steps", "3", "--stop-after", "1")
    assert r.returncode == 0, r.stderr
    assert torch.load(out / "checkpoint.pt", weights_only=False)["train"]["step"] == 4
    assert json.loads((out / "train.json").read_text())["config"]["stage1"]["steps"] == 3

    # a plain --resume continues that schedule (it went back into stage 1 with stage 2's state)
    r = rig("train", take, "-o", out, "--resume", "--stop-after", "1")
    assert r.returncode == 0, r.stderr
    last = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines() if '"lr"' in line][-1]
    assert (last["step"], last["stage"]) == (5, 2)

    # in stage 2, stage 1's length is fixed
    r = rig("train", take, "-o", out, "--resume", "--stage1-steps", "6", "--stop-after", "1")
    assert_one_line_error(r, "in stage 2", "--stage1-steps 3")


def test_a_diverging_run_stops_in_one_line_and_keeps_its_last_good_checkpoint(tmp_path):
    # a learning rate of 1e30 made the weights NaN after one step, and the next step's backward
    # pass crashed the process (segmentation fault, exit 139); a checkpoint of those weights would
    # have been written over the last good one. An infinite rate (JSON 1e400) was accepted.
    take = Path(write_take(tmp_path / "take", seed=8, seconds=0.3, fps=10, size=(320, 180))["out"])
    good = tmp_path / "good.json"
    good.write_text(json.dumps({**LIGHT, "checkpoint_every": 1}))
    out = tmp_path / "run"
    r = rig("train", take, "-o", out, *ARGS, "--config", good, "--stage1-steps", "6", "--stage2-steps", "0", "--stop-after", "1")
    assert r.returncode == 0, r.stderr

    wild = tmp_path / "wild.json"
    wild.write_text(json.dumps({**LIGHT, "checkpoint_every": 1, "stage1": {"lr": 1e30}}))
    r = rig("train", take, "-o", out, *ARGS, "--config", wild, "--stage1-steps", "6", "--stage2-steps", "0", "--resume")
    assert_one_line_error(r, "training diverged", code=1)
    kept = torch.load(out / "checkpoint.pt", weights_only=False)  # whole, and no weight in it NaN or infinite
    assert kept["train"]["step"] >= 1
    assert all(bool(torch.isfinite(v).all()) for v in kept["state_dict"].values() if v.is_floating_point())

    (tmp_path / "inf.json").write_text('{"stage1": {"lr": 1e400}}')
    r = rig("train", take, "-o", tmp_path / "run2", *ARGS, "--config", tmp_path / "inf.json")
    assert_one_line_error(r, "stage1.lr", "finite")
    assert not (tmp_path / "run2").exists()
