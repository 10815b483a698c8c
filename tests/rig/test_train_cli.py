"""`rig train`: a real (tiny) training run on simulator takes, resume, DDP, bad input."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from simulator.takes import write_take

pytestmark = pytest.mark.slow

RIG = [sys.executable, "-m", "rig"]
SMALL = ["--size", "test", "--batch", "2", "--eval-every", "3", "--threads", "1"]
# One supervision view per frame set and one held-out set per evaluation: the smallest real run.
LIGHT = {"supervision_per_step": 1, "eval_sets": 1}


def rig(*args: str, cwd=None) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(RIG + [str(a) for a in args], capture_output=True, text=True, timeout=600, cwd=cwd, env=env)


@pytest.fixture(scope="module")
def takes(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("takes")
    return [Path(write_take(root / f"take-{i}", seed=100 + i, seconds=0.4, fps=10, size=(320, 180))["out"]) for i in range(2)]


@pytest.fixture(scope="module")
def light(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("config") / "train.json"
    path.write_text(json.dumps(LIGHT))
    return path


def metrics(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]


# The run of 3 + 1 steps the resume test continues in parts; the other tests start from its model.
WHOLE_STEPS = ["--batch", "1", "--stage1-steps", "3", "--stage2-steps", "1"]


@pytest.fixture(scope="module")
def whole(takes, light, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("whole") / "run"
    r = rig("train", *takes, "-o", out, *SMALL, "--config", light, *WHOLE_STEPS, "--json")
    assert r.returncode == 0, r.stderr
    return out, json.loads(r.stdout)


def test_train_runs_both_stages_and_resume_continues_the_same_loss_curve(takes, light, whole, tmp_path):
    whole, summary = whole
    parts = tmp_path / "parts"
    args = [*SMALL, "--config", light, *WHOLE_STEPS]
    check_outputs(whole, summary)
    r = rig("train", *takes, "-o", parts, *args, "--stop-after", "2")
    assert r.returncode == 0, r.stderr
    assert [m["step"] for m in metrics(parts) if not m.get("eval")] == [1, 2]
    assert not (parts / "model.pt").exists()
    # Without --resume the run is refused and nothing is touched.
    before = (parts / "checkpoint.pt").read_bytes()
    r = rig("train", *takes, "-o", parts, *args)
    assert r.returncode == 2 and "--resume" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert (parts / "checkpoint.pt").read_bytes() == before
    r = rig("train", *takes, "-o", parts, *args, "--resume")
    assert r.returncode == 0, r.stderr
    a = [m for m in metrics(whole) if not m.get("eval")]
    b = [m for m in metrics(parts) if not m.get("eval")]
    assert [m["step"] for m in b] == [1, 2, 3, 4]
    for x, y in zip(a, b):
        assert y["loss"] == pytest.approx(x["loss"], rel=1e-5, abs=1e-7), (x, y)
    wa = torch.load(whole / "model.pt", weights_only=True)["state_dict"]
    wb = torch.load(parts / "model.pt", weights_only=True)["state_dict"]
    assert max(float((wa[k] - wb[k]).abs().max()) for k in wa if wa[k].is_floating_point()) < 1e-5


def test_workers_a_clock_stop_and_bf16_continue_the_same_run(takes, light, whole, tmp_path):
    whole, _ = whole
    run = tmp_path / "run"
    args = [*SMALL, "--config", light, *WHOLE_STEPS, "--device", "cpu"]
    # A DataLoader worker builds the batches: the same ones as in this process. The clock stops the
    # run after its first step, with a checkpoint.
    r = rig("train", *takes, "-o", run, *args, "--workers", "1", "--max-minutes", "0.0001", "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["steps"] == 1 and summary["stopped_by"] == "max_minutes" and summary["workers"] == 1
    assert summary["device"] == {"device": "cpu"} and summary["steps_per_s"] > 0 and summary["last"]["steps_per_s"] > 0
    a = [m for m in metrics(whole) if not m.get("eval")]
    assert metrics(run)[0]["loss"] == pytest.approx(a[0]["loss"], rel=1e-5)
    # Continued in bf16 autocast (on the CPU too): the rest of the schedule, evaluation included.
    r = rig("train", *takes, "-o", run, *args, "--resume", "--precision", "bf16", "--checkpoint-minutes", "0.001")
    assert r.returncode == 0, r.stderr
    assert "steps/s on cpu" in r.stdout
    b = [m for m in metrics(run) if not m.get("eval")]
    assert [m["step"] for m in b] == [1, 2, 3, 4] and (run / "model.pt").is_file()
    assert b[1]["loss"] == pytest.approx(a[1]["loss"], rel=0.05)  # bfloat16: 8 bits of mantissa
    assert any(m.get("eval") and m["step"] == 3 and 0 < m["depth_absrel"] < 10 for m in metrics(run))


def test_device_cuda_without_a_gpu_is_one_line(takes, tmp_path):
    if torch.cuda.is_available():
        pytest.skip("torch sees a GPU here")
    r = rig("train", *takes, "-o", tmp_path / "run", *SMALL, "--device", "cuda")
    one_line_exit_2(r)
    assert "--device cuda" in r.stderr and not (tmp_path / "run").exists()
    for flag, value in (("--max-minutes", "0"), ("--checkpoint-minutes", "-1"), ("--workers", "-1")):
        one_line_exit_2(rig("train", *takes, "-o", tmp_path / "run", *SMALL, flag, value))


def test_two_gloo_processes_step_as_one_process_on_the_same_global_batch(takes, light, tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    args = [*SMALL, "--config", light, "--stage1-steps", "2", "--stage2-steps", "1", "--eval-every", "100"]
    r1 = rig("train", *takes, "-o", one, *args)
    assert r1.returncode == 0, r1.stderr
    r2 = rig("train", *takes, "-o", two, *args, "--nproc", "2")
    assert r2.returncode == 0, r2.stderr[-2000:]
    assert json.loads((two / "train.json").read_text())["processes"] == 2
    w1 = torch.load(one / "model.pt", weights_only=True)["state_dict"]
    w2 = torch.load(two / "model.pt", weights_only=True)["state_dict"]
    diff = max(float((w1[k] - w2[k]).abs().max()) for k in w1 if w1[k].is_floating_point())
    assert diff < 1e-5, diff
    l1 = [m["loss"] for m in metrics(one) if not m.get("eval")]
    l2 = [m["loss"] for m in metrics(two) if not m.get("eval")]
    assert l2 == pytest.approx(l1, rel=1e-5)


def check_outputs(out: Path, summary: dict) -> None:
    """What a run of 3 + 1 steps with an evaluation every 3 steps leaves in its folder."""
    assert summary["steps"] == 4
    rows = metrics(out)
    steps = [m for m in rows if not m.get("eval")]
    assert [m["step"] for m in steps] == [1, 2, 3, 4]
    assert [m["stage"] for m in steps] == [1, 1, 1, 2]
    assert all(m["loss"] > 0 and "psnr" in m for m in steps)
    # The Chamfer term ramps in from the middle of stage 1 (TrainConfig.chamfer_start): the third step has it.
    assert [m["gamma"] for m in steps[:3]] == [0.0, 0.0, 0.5] and "chamfer" in steps[2] and "chamfer" not in steps[0]
    assert "fine" in steps[-1]
    evals = [m for m in rows if m.get("eval")]
    assert [m["step"] for m in evals] == [3, 4]  # every 3 steps and at the end of each stage
    assert all(0 < m["depth_absrel"] < 10 for m in evals)  # simulator takes: stage 1's depth is monitored
    assert (out / "samples" / "step-000003.png").stat().st_size > 0
    assert (out / "loss.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    saved = torch.load(out / "checkpoint.pt", weights_only=True)
    assert saved["train"]["config"]["stage1"]["steps"] == 3 and saved["train"]["step"] == 4
    # The trained model is a model checkpoint the export path reads; every trained part moved.
    from inference.model.checkpoint import load_checkpoint
    from inference.model.pipeline import build_model

    model = load_checkpoint(out / "model.pt")
    assert model.cfg.backbone.kind == "stereo"
    init = build_model(model.cfg, seed=0).state_dict()
    trained = model.state_dict()
    moved = {k.split(".")[0] for k in trained if trained[k].is_floating_point() and not torch.equal(trained[k], init[k])}
    assert {"point_init", "affine_transform", "depth_refine", "colour_init", "gaussian_plane"} <= moved, moved


def one_line_exit_2(r: subprocess.CompletedProcess) -> None:
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr


def test_a_sequence_without_supervision_cameras_is_refused(tmp_path):
    take = Path(write_take(tmp_path / "pair", seed=7, seconds=0.1, fps=10, size=(320, 180), cameras=2)["out"])
    r = rig("train", take, "-o", tmp_path / "run", *SMALL)
    one_line_exit_2(r)
    assert "supervision" in r.stderr
    assert not (tmp_path / "run").exists()


def test_a_sequence_without_calibration_is_refused(takes, tmp_path):
    import shutil

    take = tmp_path / "uncalibrated"
    shutil.copytree(takes[0], take)
    meta = json.loads((take / "sequence.json").read_text())
    del meta["simulator"]  # a recorded take: its cameras are known only from a calibration
    (take / "sequence.json").write_text(json.dumps(meta))
    r = rig("train", take, "-o", tmp_path / "run", *SMALL)
    one_line_exit_2(r)
    assert "calibrat" in r.stderr


def test_a_checkpoint_of_another_configuration_is_refused_and_kept(takes, light, whole, tmp_path):
    out = whole[0]
    before = (out / "checkpoint.pt").read_bytes()
    r = rig("train", *takes, "-o", out, "--size", "preview", "--resume")
    one_line_exit_2(r)
    assert "configuration" in r.stderr
    assert (out / "checkpoint.pt").read_bytes() == before
    # A new run may start from the trained weights (--init), of the same weight-bearing configuration
    # only: another size is allowed (no weight depends on it), a wider stage 2 is not.
    wider = tmp_path / "wider.json"
    wider.write_text(json.dumps({**LIGHT, "model": {"stage2": {"feature_dim": 24}}}))
    r = rig("train", *takes, "-o", tmp_path / "bigger", *SMALL, "--config", wider, "--init", out / "model.pt")
    one_line_exit_2(r)
    assert "configuration" in r.stderr
    assert not (tmp_path / "bigger" / "checkpoint.pt").exists()
    # The trained weights as a checkpoint written before some configuration keys were added: a key
    # added later takes its default, the same model.
    older = torch.load(out / "model.pt", weights_only=True)
    del older["config"]["stage1"]["scale_reference"]
    # One saved before the occlusion z-buffer was trained with the reference one: no weight depends on
    # it (config.WEIGHT_FREE), so the new run starts from those weights and fine-tunes to its own.
    del older["config"]["depth_init"]["zbuffer"]
    del older["config"]["stage2"]["visibility_ramp"]
    torch.save(older, tmp_path / "older.pt")
    r = rig("train", *takes, "-o", tmp_path / "again", *SMALL, "--config", light, "--batch", "1", "--stage1-steps", "1",
            "--stage2-steps", "0", "--init", tmp_path / "older.pt")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "again" / "train.json").read_text())["init"] == str(tmp_path / "older.pt")
    first = [m for m in metrics(out) if not m.get("eval")][0]
    again = [m for m in metrics(tmp_path / "again") if not m.get("eval")][0]
    assert again["loss"] != first["loss"]  # same batch, other weights: the run started from the trained ones


def test_stage_2_trains_stage_1_through_the_view_only_when_asked(takes, whole, tmp_path):
    """TrainConfig.stage2_trains_stage1: the view's loss also steps the backbone and the affine
    transform (at that fraction of stage 2's rate); at 0 (the paper's schedule) they stay frozen."""
    start = whole[0] / "model.pt"
    init = torch.load(start, weights_only=True)["state_dict"]
    moved = {}
    for factor in (0.0, 0.5):
        cfg = tmp_path / f"e2e-{factor}.json"
        cfg.write_text(json.dumps({**LIGHT, "stage2_trains_stage1": factor}))
        out = tmp_path / f"run-{factor}"
        r = rig("train", *takes, "-o", out, *SMALL, "--config", cfg, "--batch", "1", "--stage1-steps", "0",
                "--stage2-steps", "1", "--init", start)
        assert r.returncode == 0, r.stderr
        w = torch.load(out / "model.pt", weights_only=True)["state_dict"]
        moved[factor] = {k.split(".")[0] for k in w if w[k].is_floating_point() and not torch.equal(w[k], init[k])}
        # Stage 1 trained in stage 2 stays tied to the sources' multi-view stereo depth (mvs_depth).
        step = [m for m in metrics(out) if not m.get("eval")][0]
        assert ("mvs" in step) == (factor > 0), step
    stage2 = {"depth_refine", "colour_init", "gaussian_plane"}
    assert moved[0.0] == stage2, moved[0.0]
    assert moved[0.5] == stage2 | {"point_init", "affine_transform"}, moved[0.5]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"stage2_trains_stage1": -1}))
    r = rig("train", *takes, "-o", tmp_path / "bad", *SMALL, "--config", bad)
    one_line_exit_2(r)
    assert "stage2_trains_stage1" in r.stderr


def grow_cascade(takes, start: Path, out: Path, extra: dict | None = None) -> tuple[Path, dict, dict]:
    """One stage-1 step from `start` with a 4-hypothesis stereo cascade added (and `extra` config
    keys): the run's folder and the weights before and after."""
    cfg = out.with_suffix(".json")
    cfg.write_text(json.dumps({**LIGHT, "model": {"backbone": {"stereo_cascade": 4}}, **(extra or {})}))
    r = rig("train", *takes, "-o", out, *SMALL, "--config", cfg, "--batch", "1", "--stage1-steps", "1",
            "--stage2-steps", "0", "--init", start)
    assert r.returncode == 0, r.stderr
    return out, torch.load(start, weights_only=True)["state_dict"], torch.load(out / "model.pt", weights_only=True)["state_dict"]


@pytest.fixture(scope="module")
def grown(takes, whole, tmp_path_factory) -> tuple[Path, dict, dict]:
    """The cascade grown on the whole run's model, its last layers at 50 times the rate (one run
    for both tests below: each step of a run costs its start-up many times over)."""
    return grow_cascade(takes, whole[0] / "model.pt", tmp_path_factory.mktemp("grown") / "cascade", {"lr_factors": {"point_init.cascade.": 50}})


def test_a_run_may_add_the_stereo_cascade_to_weights_trained_without_it(takes, light, grown, tmp_path):
    """config.GROWN_FROM_ZERO: --init from a model without the cascade starts the cascade at zero
    (the same model until it trains); a model with one does not fit a run without."""
    out, w0, w1 = grown
    assert any(k.startswith("point_init.cascade.") for k in w1) and not any(k.startswith("point_init.cascade.") for k in w0)
    assert any(not torch.equal(w1[k], w0[k]) for k in w0 if k.startswith("point_init.") and w0[k].is_floating_point())
    r = rig("train", *takes, "-o", tmp_path / "back", *SMALL, "--config", light, "--batch", "1",
            "--stage1-steps", "1", "--stage2-steps", "0", "--init", out / "model.pt")
    one_line_exit_2(r)
    assert "configuration" in r.stderr


def test_lr_factors_give_a_module_grown_from_zero_its_own_rate(takes, grown, tmp_path):
    """lr_factors by parameter name prefix: Adam's first step moves each weight by about its rate, so
    the cascade added to trained weights (its last layers at zero) moves about 50 times as far as
    the rest of stage 1."""
    _, w0, w1 = grown
    zero = [k for k in w1 if k.startswith(("point_init.cascade.regularise.2.", "point_init.cascade.refine.2.", "point_init.cascade.confidence.2."))]
    assert zero and not any(k in w0 for k in zero)
    moved_grown = max(float(w1[k].abs().max()) for k in zero)  # they started at zero
    moved_rest = max(float((w1[k] - w0[k]).abs().max()) for k in w0 if k.startswith("point_init.") and w0[k].is_floating_point())
    assert 25 < moved_grown / moved_rest < 75, (moved_grown, moved_rest)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"lr_factors": {"point_init.": 0}}))
    r = rig("train", *takes, "-o", tmp_path / "bad", *SMALL, "--config", bad)
    one_line_exit_2(r)
    assert "lr_factors" in r.stderr


def test_an_unwritable_output_folder_is_refused_before_any_work(takes, tmp_path):
    r = rig("train", *takes, "-o", "/proc/rig-train", *SMALL)
    one_line_exit_2(r)


def test_a_new_run_is_not_written_into_a_folder_that_holds_anything(takes, whole, tmp_path):
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "model.pt").write_bytes((whole[0] / "model.pt").read_bytes())
    before = (kept / "model.pt").read_bytes()
    r = rig("train", *takes, "-o", kept, *SMALL)
    one_line_exit_2(r)
    assert "is not empty" in r.stderr and "model.pt" in r.stderr
    assert (kept / "model.pt").read_bytes() == before and sorted(p.name for p in kept.iterdir()) == ["model.pt"]


def test_sigterm_ends_the_step_under_way_with_a_checkpoint_and_the_run_resumes(takes, light, tmp_path):
    import signal
    import time

    out = tmp_path / "stopped"
    args = [*SMALL, "--config", light, "--batch", "1", "--stage1-steps", "40", "--stage2-steps", "0", "--eval-every", "100"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(RIG + ["train", *map(str, takes), "-o", str(out), *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 300
        while not ((out / "metrics.jsonl").exists() and metrics(out)) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "rig: interrupted" and "Traceback" not in err
    logged = max(m["step"] for m in metrics(out))
    assert 1 <= logged < 40  # the default checkpoint_every (100) would have kept nothing
    ckpt = torch.load(out / "checkpoint.pt", weights_only=False)
    assert ckpt["train"]["step"] == logged
    r = rig("train", *takes, "-o", out, *args, "--resume", "--stop-after", "1")
    assert r.returncode == 0, r.stderr
    assert max(m["step"] for m in metrics(out)) == logged + 1
