"""Every tensor of a training step, an evaluation and `rig model eval`'s figures follows the model's
device: checked on the CPU with the shadow placements of tests/inference/device_tracking.py (a GPU
run died at its first evaluation on a pose tensor left on the CPU)."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from inference.config import ModelConfig, Sizes
from inference.evaluate.model_eval import evaluate
from inference.train.config import TrainConfig
from inference.train.trainer import Trainer
from rig.storage.dataset import TrainingSet
from simulator.takes import write_take
from tests.inference.device_tracking import DeviceTracker


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> TrainingSet:
    root = tmp_path_factory.mktemp("take")
    return TrainingSet([Path(write_take(root / "take", seed=31, seconds=0.2, fps=10, size=(160, 96), cameras=4)["out"])])


def _config() -> TrainConfig:
    cfg = TrainConfig()
    cfg.model = ModelConfig.for_backbone("stereo", Sizes.preset("test"))
    # Every loss term on: the point splat at several scales, the plane render, the Chamfer from the
    # first step, the MVS depth term (stage 1 and, through stage2_trains_stage1, stage 2).
    cfg.stage1.steps, cfg.stage2.steps = 2, 1
    cfg.stage1.batch = cfg.stage2.batch = 1
    cfg.supervision_per_step, cfg.eval_sets = 1, 1
    cfg.chamfer_start = 0.0
    cfg.stage2_trains_stage1 = 1.0
    cfg.eval_every = 2
    return cfg


def test_tracker_sees_a_host_tensor_meeting_the_model():
    # The checker itself: what CUDA refuses is recorded, what it accepts (0-dim CPU scalars) is not.
    tracker = DeviceTracker()
    layer = torch.nn.Linear(3, 3)
    with tracker:
        tracker.mark_device(layer)
        x = torch.ones(2, 3).to(torch.device("cpu"))
        layer(x) * torch.tensor(2.0)
        assert not tracker.mixed, tracker.report()
        layer(torch.ones(2, 3))
    assert len(tracker.mixed) == 1 and "test_train_device_follow.py" in tracker.report()


def test_training_steps_and_evaluations_keep_every_tensor_on_the_model_device(data, tmp_path):
    trainer = Trainer(_config(), data, tmp_path / "run", device=torch.device("cpu"))
    tracker = DeviceTracker()
    with tracker:
        tracker.mark_device(trainer.model)
        summary = trainer.run()
    assert summary["steps"] == 3
    assert not tracker.mixed, "tensors left off the model's device:\n" + tracker.report()


def test_model_evaluation_keeps_every_tensor_on_the_model_device(data):
    from inference.model.pipeline import build_model

    model = build_model(ModelConfig.for_backbone("stereo", Sizes.preset("test")), seed=0)
    tracker = DeviceTracker()
    with tracker:
        tracker.mark_device(model)
        result = evaluate(model, data, max_sets=1, device=torch.device("cpu"))
    assert result["sets"] == 1 and result["overall"]["psnr"] > 0 and result["depth_absrel"] is not None
    assert not tracker.mixed, "tensors left off the model's device:\n" + tracker.report()
