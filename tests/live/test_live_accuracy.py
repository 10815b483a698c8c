"""The live path adds no error: with the shipped model, a simulated take replayed through `rig live`'s
engine gives, at a supervision camera's pose, the PSNR `rig model eval` gives for that set and camera."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from tests.rig.cli_helpers import REPO, run_rig

pytestmark = pytest.mark.timeout(600)

SHIPPED = REPO / "models" / "splat-sap-preview.pt"


def test_a_live_view_at_a_supervision_camera_scores_as_model_eval(tmp_path):
    from inference.metrics import psnr
    from inference.runtime.preprocess import Resampler
    from rig.cameras.sim import sim_rig_config
    from rig.config import parse_config
    from rig.live.app import LiveApp
    from rig.storage.dataset import Sequence
    from simulator.takes import write_take

    size = (640, 360)  # the shipped model's output size
    take = tmp_path / "take"
    write_take(take, seed=90_001, seconds=0.2, fps=5, size=size)  # one frame set, a seed no training take used
    proc = run_rig("model", "eval", "--model", SHIPPED, "--sequence", take, "--no-references", "--json", timeout=400)
    assert proc.returncode == 0, proc.stderr
    figures = json.loads(proc.stdout)
    assert figures["sets"] == 1

    cfg = parse_config(sim_rig_config(6, *size))
    app = LiveApp.build(cfg, replay=take, threads=2)  # the shipped model, the take's own cameras
    with app:
        png = app.engine.snapshot({"type": "viewpoint", "preset": "sup2"}, timeout=300)
    assert png is not None
    live = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) / 255.0
    seq = Sequence(take)
    sample = seq.sample(0, ["sup2"])
    truth = Resampler(sample.cameras["sup2"], size).image(sample.images["sup2"])
    live_psnr = psnr(live, truth)
    eval_psnr = figures["cameras"]["sup2"]["psnr"]
    print(f"\nsup2: live {live_psnr:.2f} dB, rig model eval {eval_psnr:.2f} dB")
    assert abs(live_psnr - eval_psnr) <= 0.5
