"""The live path adds no error: with the shipped model `rig live` runs on a CPU (the shipped checkpoint
at the live size, models/splat-sap-live.onnx, its scale search reused between sets), a simulated take
replayed through `rig live`'s engine gives, at a supervision camera's pose, the PSNR `rig model eval`
gives for that set and camera with the same export."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from tests.rig.cli_helpers import REPO, run_rig

pytestmark = pytest.mark.timeout(600)

SHIPPED_LIVE = REPO / "models" / "splat-sap-live.onnx"  # rig model eval runs its checkpoint at its sizes


def test_a_live_view_at_a_supervision_camera_scores_as_model_eval(tmp_path):
    from inference.metrics import psnr
    from inference.runtime.preprocess import Resampler
    from rig.sim.rig_config import sim_rig_config
    from rig.config import parse_config
    from rig.live.app import LiveApp
    from rig.storage.dataset import Sequence
    from simulator.takes import write_take

    size = (640, 360)  # the cameras' size
    take = tmp_path / "take"
    write_take(take, seed=90_001, seconds=0.2, fps=5, size=size)  # one frame set, a seed no training take used
    proc = run_rig("model", "eval", "--model", SHIPPED_LIVE, "--sequence", take, "--no-references", "--json", timeout=400)
    assert proc.returncode == 0, proc.stderr
    figures = json.loads(proc.stdout)
    assert figures["sets"] == 1

    cfg = parse_config(sim_rig_config(6, *size))
    app = LiveApp.build(cfg, replay=take, threads=2, providers=["CPUExecutionProvider"])  # the shipped model on a CPU, the take's own cameras
    assert app.engine.model.path == SHIPPED_LIVE
    with app:
        png = app.engine.snapshot({"type": "viewpoint", "preset": "sup2"}, timeout=300)
    assert png is not None
    live = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) / 255.0
    seq = Sequence(take)
    sample = seq.sample(0, ["sup2"])
    truth = Resampler(sample.cameras["sup2"], app.engine.output_size).image(sample.images["sup2"])
    live_psnr = psnr(live, truth)
    eval_psnr = figures["cameras"]["sup2"]["psnr"]
    print(f"\nsup2: live {live_psnr:.2f} dB, rig model eval {eval_psnr:.2f} dB")
    assert abs(live_psnr - eval_psnr) <= 0.5
