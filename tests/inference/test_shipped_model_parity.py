"""The shipped exports (models/) compute what their checkpoint computes in torch, within the parity bar."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from inference.model.checkpoint import model_from_record
from inference.runtime import NovelViewPipeline
from inference.runtime.shipped import LIVE_NAME, MODELS, NAME
from inference.runtime.synthetic import example_inputs

TOLERANCE = 1e-3  # `rig model check`'s, on images in [0, 1]
EXPORTS = [MODELS / f"{NAME}.onnx", MODELS / f"{LIVE_NAME}.onnx"]


@pytest.mark.parametrize("path", EXPORTS, ids=[p.stem for p in EXPORTS])
def test_the_shipped_export_matches_its_checkpoint_on_several_draws(path):
    if not path.is_file():
        pytest.skip(f"{path} is not in this installation")
    pipe = NovelViewPipeline(path, providers=["CPUExecutionProvider"])
    cfg = pipe.info.config
    model = model_from_record(cfg, pipe.info.weights, None, None)
    worst = 0.0
    for seed in range(4):  # seed 0 is `rig model check`'s own draw
        feeds = {n: a for n, a in example_inputs(cfg.sizes, pipe.info.needs_depth, seed=seed).arrays.items() if n in pipe.info.inputs}
        image, depth = pipe.run(feeds)
        with torch.no_grad():
            ref_image, ref_depth = model(*[torch.from_numpy(feeds[n]) for n in model.input_names])
        worst = max(worst, float(np.abs(image - ref_image.numpy()).max()))
        assert float(np.abs(depth - ref_depth.numpy()).max()) <= TOLERANCE, f"seed {seed}: depth"
    assert worst <= TOLERANCE
