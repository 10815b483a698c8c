"""Training on a GPU (marked cuda: skipped, with the reason, where torch sees none): a few steps with an
evaluation and a checkpoint, the batches and every tensor on the GPU; and runs that change device kind
on --resume (a GPU run continued on the CPU, a CPU run continued on the GPU)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from inference.config import ModelConfig, Sizes
from inference.train.config import TrainConfig
from inference.train.trainer import CHECKPOINT, Trainer
from rig.storage.dataset import TrainingSet
from simulator.takes import write_take

pytestmark = pytest.mark.cuda
CUDA = torch.device("cuda")
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def take(tmp_path_factory) -> Path:
    return Path(write_take(tmp_path_factory.mktemp("take") / "take", seed=77, seconds=0.3, fps=10, size=(320, 180))["out"])


def _config() -> TrainConfig:
    cfg = TrainConfig()
    cfg.model = ModelConfig.for_backbone("stereo", Sizes.preset("test"))
    cfg.stage1.steps, cfg.stage2.steps = 3, 2
    cfg.stage1.batch = cfg.stage2.batch = 2
    cfg.supervision_per_step, cfg.eval_sets = 1, 2
    cfg.chamfer_start, cfg.stage2_trains_stage1 = 0.0, 1.0  # every loss term, the MVS depth term in both stages
    cfg.eval_every = 2
    return cfg


def _losses(out: Path) -> list[float]:
    return [json.loads(l)["loss"] for l in (out / "metrics.jsonl").read_text().splitlines() if not json.loads(l).get("eval")]


@pytest.mark.parametrize("workers,precision", [(0, "fp32"), (2, "bf16")])
def test_training_steps_evaluation_and_checkpoint_on_cuda(take, tmp_path, workers, precision):
    trainer = Trainer(_config(), TrainingSet([take]), tmp_path / "run", device=CUDA, precision=precision, workers=workers)
    summary = trainer.run()
    assert summary["steps"] == 5 and summary["device"].startswith("cuda") and summary["steps_per_s"] > 0
    assert all(p.device.type == "cuda" for p in trainer.model.parameters())
    state = [t for s in trainer.optimizer.state.values() for k, t in s.items() if isinstance(t, torch.Tensor) and k != "step"]
    assert state and all(t.device.type == "cuda" for t in state)
    rows = [json.loads(l) for l in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    evals = [r for r in rows if r.get("eval")]
    assert [r["step"] for r in evals] == [2, 3, 4, 5] and all(0 < r["depth_absrel"] < 10 for r in evals[:2])
    assert all(r["loss"] == r["loss"] and r["loss"] > 0 for r in rows)  # finite
    saved = torch.load(tmp_path / "run" / "model.pt", weights_only=True)  # tensors written from the CPU
    assert all(t.device.type == "cpu" for t in saved["state_dict"].values())


def test_gpu_and_cpu_steps_agree(take, tmp_path):
    """The same schedule on both device kinds: the same losses to float tolerance."""
    cfg = _config()
    cfg.stage1.steps, cfg.stage2.steps = 2, 0
    runs = {}
    for dev in (CPU, CUDA):
        Trainer(cfg, TrainingSet([take]), tmp_path / dev.type, device=dev).run()
        runs[dev.type] = _losses(tmp_path / dev.type)
    assert runs["cuda"] == pytest.approx(runs["cpu"], rel=2e-3)


def test_resume_changes_device_kind_both_ways(take, tmp_path):
    data = TrainingSet([take])
    whole = tmp_path / "whole"
    Trainer(_config(), data, whole, device=CUDA).run()
    # Started on the GPU, continued on the CPU, finished on the GPU: the same loss curve.
    out = tmp_path / "moved"
    Trainer(_config(), data, out, device=CUDA).run(stop_after=2)
    on_cpu = Trainer(_config(), data, out, resume=True, device=CPU)
    on_cpu.run(stop_after=2)
    assert all(t.device.type == "cpu" for s in on_cpu.optimizer.state.values() for t in s.values() if isinstance(t, torch.Tensor))
    on_gpu = Trainer(_config(), data, out, resume=True, device=CUDA)
    on_gpu.run()
    state = [t for s in on_gpu.optimizer.state.values() for k, t in s.items() if isinstance(t, torch.Tensor) and k != "step"]
    assert state and all(t.device.type == "cuda" for t in state)
    assert _losses(out) == pytest.approx(_losses(whole), rel=2e-3)


def test_rig_train_and_eval_on_cuda_from_the_command_line(take, tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "rig", "train", str(take), "-o", str(run), "--size", "test", "--batch", "2",
                        "--stage1-steps", "3", "--stage2-steps", "1", "--eval-every", "2", "--json"],
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["device"]["device"].startswith("cuda") and "gpu" in summary["device"]  # the default with a GPU
    assert (run / CHECKPOINT).is_file() and (run / "model.pt").is_file()
    e = subprocess.run([sys.executable, "-m", "rig", "model", "eval", "--model", str(run / "model.pt"), "--sequence", str(take),
                        "--device", "cuda", "--max-sets", "1", "--json"], capture_output=True, text=True, timeout=600, env=env)
    assert e.returncode == 0, e.stderr
    assert json.loads(e.stdout)["device"]["device"].startswith("cuda")
