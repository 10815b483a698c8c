"""The trainer's wall clock: a checkpoint every `checkpoint_minutes`, a clean stop after `max_minutes`,
steps/s in the log; and a checkpoint written on a GPU resumed on the CPU."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from inference.config import ModelConfig, Sizes
from inference.train.config import TrainConfig
from inference.train.trainer import CHECKPOINT, Trainer
from rig.storage.dataset import TrainingSet
from simulator.takes import write_take

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> TrainingSet:
    root = tmp_path_factory.mktemp("take")
    return TrainingSet([Path(write_take(root / "take", seed=57, seconds=0.2, fps=10, size=(160, 96), cameras=4)["out"])])


def _config(steps: int) -> TrainConfig:
    cfg = TrainConfig()
    cfg.model = ModelConfig.for_backbone("stereo", Sizes.preset("test"))
    cfg.stage1.steps, cfg.stage2.steps = steps, 0
    cfg.stage1.batch = 1
    cfg.supervision_per_step, cfg.eval_sets = 1, 1
    cfg.mvs_depth = 0.0  # the clock is under test, not the loss terms
    cfg.eval_every = cfg.checkpoint_every = 1000
    return cfg


def _saved_step(out: Path):
    path = out / CHECKPOINT
    return torch.load(path, map_location="cpu", weights_only=True)["train"]["step"] if path.is_file() else None


def test_checkpoints_on_the_clock_and_a_clean_stop_after_max_minutes(data, tmp_path):
    seen = []
    trainer = Trainer(_config(3), data, tmp_path / "clock", device=torch.device("cpu"),
                      progress=lambda step, total, m: seen.append((step, _saved_step(tmp_path / "clock"), m["steps_per_s"])))
    summary = trainer.run(checkpoint_minutes=1e-6)
    # When step k is reported, the clock's checkpoint of step k - 1 is on disk (checkpoint_every is 1000).
    assert [(k, s) for k, s, _ in seen] == [(1, None), (2, 1), (3, 2)]
    assert all(r > 0 for *_, r in seen) and summary["steps_per_s"] > 0 and summary["stopped_by"] is None

    stopped = Trainer(_config(3), data, tmp_path / "stop", device=torch.device("cpu"))
    summary = stopped.run(max_minutes=1e-6)  # past the deadline after the first step
    assert summary["steps"] == 1 and summary["stopped_by"] == "max_minutes"
    assert _saved_step(tmp_path / "stop") == 1 and not (tmp_path / "stop" / "model.pt").exists()
    with pytest.raises(Exception, match="max_minutes"):
        stopped.run(max_minutes=0)


class _TagAsCuda:
    """torch.save under this context records every CPU storage as "cuda:0", byte for byte what a
    checkpoint written on a GPU holds (its location tag), so a CPU-only machine can test reading one."""
    active = False
    registered = False

    def __enter__(self):
        if not _TagAsCuda.registered:
            torch.serialization.register_package(0, lambda s: "cuda:0" if _TagAsCuda.active and s.device.type == "cpu" else None,
                                                 lambda s, location: None)
            _TagAsCuda.registered = True
        _TagAsCuda.active = True

    def __exit__(self, *exc):
        _TagAsCuda.active = False


def as_gpu_checkpoint(path: Path) -> None:
    data = torch.load(path, map_location="cpu", weights_only=True)
    with _TagAsCuda():
        torch.save(data, path)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is here: a CUDA checkpoint loads without map_location")
def test_a_checkpoint_written_on_a_gpu_resumes_on_the_cpu_with_its_optimiser_state(data, tmp_path):
    cfg = _config(2)
    whole = Trainer(cfg, data, tmp_path / "whole", device=torch.device("cpu"))
    losses = []
    whole.progress = lambda step, total, m: losses.append(m["loss"])
    whole.run()
    part = Trainer(_config(2), data, tmp_path / "part", device=torch.device("cpu"))
    part.run(stop_after=1)
    as_gpu_checkpoint(tmp_path / "part" / CHECKPOINT)
    with pytest.raises(RuntimeError, match="CUDA"):  # what a reader without map_location meets
        torch.load(tmp_path / "part" / CHECKPOINT, weights_only=True)
    resumed = Trainer(_config(2), data, tmp_path / "part", resume=True, device=torch.device("cpu"))
    after = []
    resumed.progress = lambda step, total, m: after.append(m["loss"])
    resumed.run()
    assert after == pytest.approx(losses[1:], rel=1e-5)  # the optimiser's moments came back: the same second step
    state = [t for s in resumed.optimizer.state.values() for t in s.values() if isinstance(t, torch.Tensor)]
    assert state and all(t.device == torch.device("cpu") for t in state)
