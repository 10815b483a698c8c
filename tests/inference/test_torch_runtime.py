"""The torch live runtime (inference.gpu_runtime) on the CPU: the same code path as on a GPU, eager
(CUDA graphs need a GPU: tests/live/test_cuda_live.py). Its two parts compute the whole model's
forward; a compile that fails, or a compiled function that fails later, leaves it eager with one
warning; it finds the checkpoint behind an ONNX model and runs it at another size."""
from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest
import torch

from inference.config import ModelConfig, Sizes
from inference.errors import InferenceError
from inference.gpu_runtime import TorchLivePipeline, at_size, checkpoint_model, parity
from inference.model.checkpoint import save_checkpoint
from inference.model.pipeline import build_model
from tests.rig.cli_helpers import REPO

pytestmark = pytest.mark.timeout(300)

SHIPPED_ONNX = REPO / "models" / "splat-sap-preview.onnx"
# Smaller than the test preset (the runtime takes any Sizes): a run is a fraction of a second here.
SMALL = Sizes(coarse=(64, 32), fine=(128, 64), output=(160, 80))


@pytest.fixture(scope="module")
def pipe():
    """The shipped model at a small size, eager on the CPU."""
    return TorchLivePipeline(SHIPPED_ONNX, "cpu", SMALL, compile=False)


def run_once(p: TorchLivePipeline) -> np.ndarray:
    feeds, target_K, target_pose = p.synthetic()
    image, _ = p.view(p.stage1(feeds), feeds, target_K, target_pose)
    return image


def test_stage_1_then_the_view_compute_the_whole_models_forward():
    """The runtime's cut (stage 1 once, the view per viewer) against the plain SplatSAP forward on
    the synthetic inputs of `rig model check`: the shipped checkpoint, rebuilt at another size."""
    found = parity(SHIPPED_ONNX, "cpu", SMALL)
    assert found["sizes"] == SMALL.describe() and found["graphs"] == "eager"
    assert found["max_abs_diff_image"] <= 1e-5 and found["max_abs_diff_depth"] <= 1e-4, found
    assert found["stage1_ms"] > 0 and found["view_ms"] > 0


def test_a_compile_that_fails_leaves_it_eager_with_one_warning(pipe, caplog):
    def broken(fn):
        raise RuntimeError("no C++ compiler\nsecond line")

    p = TorchLivePipeline(SHIPPED_ONNX, "cpu", SMALL, compiler=broken)
    with caplog.at_level(logging.WARNING, logger="inference.gpu_runtime"):
        p.warm(background=True)
        assert not p.wait_compiled(timeout=120)
        first = run_once(p)
        run_once(p)
    assert p.graphs == "eager (compile failed: RuntimeError: no C++ compiler)"
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "compile failed" in warnings[0].getMessage()
    assert np.array_equal(first, run_once(pipe))  # the eager frames are the model's


def test_a_compiled_graph_that_fails_later_falls_back_to_eager_once(pipe, caplog):
    calls = {"fail": False, "compiled": 0}

    def flaky(fn):
        def run(*args):
            if calls["fail"]:
                raise RuntimeError("CUDA error: an illegal memory access was encountered")
            calls["compiled"] += 1
            return fn(*args)
        return run

    p = TorchLivePipeline(SHIPPED_ONNX, "cpu", SMALL, compiler=flaky)
    with caplog.at_level(logging.WARNING, logger="inference.gpu_runtime"):
        p.warm(background=False)
        assert p.graphs == "compiled" and p.wait_compiled(0) and p.compile_s is not None
        served = calls["compiled"]
        compiled = run_once(p)
        assert calls["compiled"] == served + 2  # stage 1 and the view went through the compiled functions
        calls["fail"] = True
        fallen = run_once(p)
        run_once(p)
    assert p.graphs.startswith("eager (graph failed: RuntimeError: CUDA error: an illegal memory access")
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1
    assert np.array_equal(fallen, compiled)


def test_a_compiled_graph_that_computes_otherwise_is_not_used(pipe):
    def off_by_a_little(fn):
        return lambda *args: tuple(t + 0.01 for t in fn(*args))

    p = TorchLivePipeline(SHIPPED_ONNX, "cpu", SMALL, compiler=off_by_a_little)
    p.warm(background=False)
    assert p.graphs.startswith("eager (compile failed: InferenceError: the compiled image differs from eager by")


def test_status_says_device_graphs_and_sizes(pipe):
    s = pipe.runtime_status()
    assert s["kind"] == "torch" and s["device"] == "cpu" and s["graphs"] == "eager" and s["tf32"] is False
    assert s["sizes"]["output"] == "160x80" and s["checkpoint"].endswith("splat-sap-preview.pt")


def test_a_rendered_view_is_what_novel_view_gives(pipe):
    """render's uint8 image rounds as inference.runtime.NovelView's does, made on the device."""
    from inference.runtime import NovelView
    from inference.runtime.synthetic import example_inputs

    ex = example_inputs(pipe.sizes, False)
    feeds = {n: ex.arrays[n] for n in ("left_image", "right_image", "left_K", "right_K", "left_pose", "right_pose")}
    s1 = pipe.stage1(feeds)
    view = pipe.render(s1, feeds, ex.target)
    image, depth = pipe.view(s1, feeds, ex.arrays["target_K"], ex.arrays["target_pose"])
    assert view.image.shape == (80, 160, 3) and view.depth.shape == (80, 160)
    assert np.array_equal(view.image, image[0].transpose(1, 2, 0)) and np.array_equal(view.depth, depth[0, 0])
    assert np.array_equal(view.image_uint8(), NovelView(view.image, view.depth).image_uint8())
    assert view.ms > 0 and pipe.view_ms > 0  # the latest call's (view() ran after render())


def test_the_checkpoint_behind_an_onnx_model(tmp_path):
    """M.pt beside M.onnx; without it, the checkpoint M.onnx's metadata records; a checkpoint
    beside it that the model was not exported from, or a part file, is one line."""
    onnx = tmp_path / "M.onnx"
    shutil.copyfile(SHIPPED_ONNX, onnx)
    model, origin = checkpoint_model(onnx)  # recorded (the shipped checkpoint)
    assert origin == onnx and model.cfg.backbone.kind == "stereo"
    other = build_model(ModelConfig(sizes=Sizes.preset("test")), seed=3)
    save_checkpoint(other, tmp_path / "M.pt")
    with pytest.raises(InferenceError, match=r"M.pt: not the checkpoint M.onnx was exported from \(sha256 differs\)"):
        checkpoint_model(onnx)
    model, origin = checkpoint_model(tmp_path / "M.pt")
    assert origin == tmp_path / "M.pt" and model.cfg.backbone.kind == "tiny"
    part = tmp_path / "M.stage1.onnx"
    shutil.copyfile(REPO / "models" / "splat-sap-preview.stage1.onnx", part)
    with pytest.raises(InferenceError, match=r"the stage1 part .* give the model itself \(M.onnx\)"):
        checkpoint_model(part)


def test_the_weights_run_at_any_size_preset(pipe):
    """No weight depends on the sizes: the preview-size checkpoint's tensors fill a paper-size model."""
    paper = at_size(pipe.net.cpu(), "paper", SHIPPED_ONNX)
    assert paper.cfg.sizes == Sizes.preset("paper")
    got, want = paper.state_dict(), pipe.net.state_dict()
    assert got.keys() == want.keys() and all(torch.equal(got[k], want[k]) for k in want)


def test_an_oracle_model_is_refused(tmp_path):
    oracle = build_model(ModelConfig.for_backbone("oracle", Sizes.preset("test")), seed=0)
    save_checkpoint(oracle, tmp_path / "oracle.pt")
    with pytest.raises(InferenceError, match="oracle backbone"):
        TorchLivePipeline(tmp_path / "oracle.pt", "cpu", None, compile=False)


@pytest.mark.slow
def test_both_parts_trace_as_one_graph_each():
    """torch.compile sees each part whole (fullgraph: no graph break, so no Python between kernels
    inside a CUDA graph); traced on the CPU with Dynamo's eager backend (Inductor needs a compiler)."""
    p = TorchLivePipeline(SHIPPED_ONNX, "cpu", "test",
                          compiler=lambda fn: torch.compile(fn, backend="eager", fullgraph=True, dynamic=False))
    p.warm(background=False)
    assert p.graphs == "compiled", p.graphs
