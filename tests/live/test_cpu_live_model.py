"""The CPU live path: `rig live` on ONNX Runtime's CPU provider runs the shipped model at the live size
(models/splat-sap-live.onnx, the test sizes), and for a model with the scale search its stage 1
runs the search on one frame set in SCALE_SEARCH_EVERY, reusing the factor on the sets between
(docs/live.md, "On a CPU"). The search is checked on a model exported here with it on, whether or not
the shipped one has it.

The reuse is checked by what it computes and by the work it does (searched runs per stage-1 run),
not by timing: a shared 2-core machine's times drift too much to hold a threshold."""
from __future__ import annotations

import numpy as np
import pytest

from inference.runtime import SplitPipeline
from inference.runtime.shipped import MODELS, LIVE_NAME
from inference.runtime.split import UNSCALED_PART, part_path
from inference.runtime.synthetic import example_inputs

LIVE = MODELS / f"{LIVE_NAME}.onnx"

pytestmark = [pytest.mark.timeout(180)]


@pytest.fixture(scope="module")
def searching_model(tmp_path_factory):
    """A tiny-backbone model at the live size with the learned affine transform and its scale search, exported."""
    from inference.config import ModelConfig, Sizes
    from inference.export import export_onnx
    from inference.model.pipeline import build_model

    cfg = ModelConfig.for_backbone("tiny", Sizes.preset("test"))
    cfg.stage1.affine = "learned"
    cfg.stage1.scale_search = 21
    path = tmp_path_factory.mktemp("live-search") / "searching.onnx"
    export_onnx(build_model(cfg, seed=0), path)
    return path


def test_the_search_runs_on_one_set_in_n_and_the_reused_factor_gives_the_searched_points(searching_model):
    every = 3
    reusing = SplitPipeline(searching_model, threads=2, scale_every=every)
    searching = SplitPipeline(searching_model, threads=2)  # scale_every=1: every set searched, as `rig model render`
    assert reusing.unscaled_session is not None and searching.unscaled_session is None
    feeds = {k: v for k, v in example_inputs(reusing.sizes, False, seed=1).arrays.items() if k not in ("target_K", "target_pose")}
    target = example_inputs(reusing.sizes, False, seed=1).arrays
    exact = searching.stage1(feeds)
    runs = [reusing.stage1(feeds) for _ in range(2 * every + 1)]
    status = reusing.scale_status()
    # Sets 1, 4 and 7 are searched: the whole stage 1, its output as it is.
    assert (status["sets_searched"], status["sets_reusing"], status["search_every"]) == (3, 2 * every - 2, every)
    for name in exact:
        np.testing.assert_array_equal(runs[0][name], exact[name])
    assert 0.5 < status["factor"] < 2.0
    # The sets between: stage 1 without the search, scaled by the factor here, as the model scales.
    for out in runs[1:every]:
        for name in exact:
            np.testing.assert_allclose(out[name], exact[name], rtol=0, atol=1e-5)
    image, _ = searching.view(exact, feeds, target["target_K"], target["target_pose"])
    reused_image, _ = reusing.view(runs[1], feeds, target["target_K"], target["target_pose"])
    assert np.abs(reused_image - image).max() < 1e-3  # rig model check's tolerance


def test_the_unscaled_part_is_the_same_export_as_stage_1(searching_model):
    pipe = SplitPipeline(searching_model, scale_every=2)
    meta = pipe.unscaled_session.get_modelmeta().custom_metadata_map
    assert meta["splat_sap.part"] == UNSCALED_PART
    assert meta["splat_sap.weights"] == pipe.stage1_info.metadata["splat_sap.weights"]
    assert part_path(searching_model, UNSCALED_PART).name == "searching.stage1_unscaled.onnx"
    # The search is stage 1's last step: the part without it is a smaller graph of the same model.
    assert part_path(searching_model, UNSCALED_PART).stat().st_size < part_path(searching_model, "stage1").stat().st_size


@pytest.mark.skipif(not LIVE.is_file(), reason=f"{LIVE} is not in this installation")
def test_rig_live_on_a_cpu_runs_the_live_size_and_says_so(tmp_path):
    from rig.sim.rig_config import sim_rig_config
    from rig.config import parse_config
    from rig.live.app import SCALE_SEARCH_EVERY, LiveApp

    app = LiveApp.build(parse_config(sim_rig_config(2, 320, 180, fps=15.0)), providers=["CPUExecutionProvider"])
    status = app.engine.status()  # not started: nothing runs, the status already says what will
    assert status["model"]["path"] == str(LIVE)
    assert status["model"]["sizes"]["output"] == "320x180"
    stage1 = app.engine.model.info.config.stage1
    if stage1.scale_search and stage1.affine == "learned":
        assert status["model"]["scale_search"]["search_every"] == SCALE_SEARCH_EVERY > 1
    else:  # a model without the search says nothing of one
        assert "scale_search" not in status["model"]
