"""The live view on a GPU: the live engine with the torch runtime (inference.gpu_runtime) on a replayed
simulated take, `/status` saying where the model runs, and the command line's GPU options.

The engine takes the torch runtime as it takes ONNX Runtime's two parts (same interface): on the CPU
that is shown eagerly here; the tests marked `cuda` run it on the GPU at the paper's sizes with its
CUDA graphs and skip elsewhere (tests/conftest.py says why)."""
from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig

pytestmark = pytest.mark.timeout(600)

SHIPPED_ONNX = REPO / "models" / "splat-sap-preview.onnx"


@pytest.fixture(scope="module")
def take(tmp_path_factory) -> Path:
    from simulator.takes import write_take

    return Path(write_take(tmp_path_factory.mktemp("cuda-live") / "take", seed=77, seconds=0.4, fps=10, size=(320, 180))["out"])


@pytest.fixture(scope="module")
def rig_toml(tmp_path_factory) -> Path:
    from rig.sim.rig_config import sim_rig_config
    from rig.config import dump_config, parse_config

    path = tmp_path_factory.mktemp("cuda-live-cli") / "rig.toml"
    path.write_text(dump_config(parse_config(sim_rig_config(6, 320, 180, fps=10.0))))
    return path


def replay_engine(take: Path, model):
    """The live engine on the take, looped, with `model` (its own calibration, as `rig live --replay`)."""
    from rig.live.engine import LiveEngine
    from rig.live.source import ReplaySource

    source = ReplaySource(take, "left", "right")
    seq = source.sequence
    return LiveEngine(source, seq.calibration or seq.ground_truth, "left", "right", model)


def frames_from(engine, seconds: float, first_timeout: float = 120) -> list:
    viewer = engine.add_viewer({"type": "viewpoint", "t": 0.3})
    got = []
    try:
        first = viewer.next_frame(first_timeout)
        assert first is not None, engine.status()
        got.append(first)
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            f = viewer.next_frame(0.05)
            if f is not None:
                viewer.acknowledge(f.set_index, f.viewpoint_id)
                got.append(f)
    finally:
        engine.remove_viewer(viewer)
    return got


def test_the_engine_takes_the_torch_runtime_unchanged(take):
    """On the CPU, eager, at a small size: frames come out, and /status says torch on the CPU."""
    from inference.config import Sizes
    from inference.gpu_runtime import TorchLivePipeline

    model = TorchLivePipeline(SHIPPED_ONNX, "cpu", Sizes(coarse=(64, 32), fine=(128, 64), output=(160, 80)), compile=False)
    with replay_engine(take, model.warm()) as engine:
        frames = frames_from(engine, 3.0)
        status = engine.status()
    assert len(frames) >= 2 and all(f.jpeg[:2] == b"\xff\xd8" for f in frames)
    assert status["runtime"]["kind"] == "torch" and status["runtime"]["device"] == "cpu" and status["runtime"]["graphs"] == "eager"
    assert status["stage1_runs"] >= 2 and status["ms"]["stage1"] > 0 and status["ms"]["view"] > 0


def test_status_says_onnx_runtime_and_its_providers(take):
    from inference.runtime import SplitPipeline

    engine = replay_engine(take, SplitPipeline(SHIPPED_ONNX, threads=1))
    assert engine.status()["runtime"] == {"kind": "onnxruntime", "device": "cpu", "providers": ["CPUExecutionProvider"]}


@pytest.mark.parametrize("args, fragments", [
    (["--device", "gpu"], ["--device", "'gpu' is not a device"]),
    (["--providers", "CudaProvider"], ["--providers", "'CudaProvider' is not an ONNX Runtime execution provider"]),
    (["--providers", "TensorrtExecutionProvider"], ["TensorrtExecutionProvider is not in this onnxruntime", "onnxruntime-gpu"]),
    (["--size", "paper"], ["--size is for --device cuda"]),
    (["--device", "cuda", "--threads", "2"], ["--threads is for ONNX Runtime"]),
])
def test_bad_gpu_options_are_one_line_and_exit_2(rig_toml, args, fragments):
    assert_one_line_error(run_rig("live", "-c", rig_toml, "--port", 0, "--seconds", 1, *args), *fragments)


def test_device_cuda_without_a_gpu_is_one_line_and_exit_2(rig_toml, take, tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    assert_one_line_error(run_rig("live", "-c", rig_toml, "--port", 0, "--seconds", 1, "--device", "cuda"),
                          "--device cuda: no CUDA GPU here", "--device cpu")
    out = tmp_path / "view.png"
    assert_one_line_error(run_rig("model", "render", "--sequence", take, "--view", 0.5, "--device", "cuda", "-o", out),
                          "--device cuda: no CUDA GPU here")
    assert not out.exists()


# --- on a GPU -----------------------------------------------------------------------------------------

@pytest.mark.cuda
def test_the_engine_on_the_gpu_serves_eager_frames_then_its_cuda_graphs(take):
    """At the paper's sizes: frames flow while the graphs compile, and after."""
    from inference.gpu_runtime import TorchLivePipeline

    model = TorchLivePipeline(SHIPPED_ONNX, "cuda", "paper").warm()
    with replay_engine(take, model) as engine:
        assert engine.status()["runtime"]["graphs"] in ("compiling", "compiled")
        early = frames_from(engine, 2.0)
        assert model.wait_compiled(timeout=480), model.graphs
        late = frames_from(engine, 3.0)
        status = engine.status()
    assert len(early) >= 1 and len(late) >= 3
    r = status["runtime"]
    assert r["kind"] == "torch" and r["device"].startswith("cuda") and r["gpu"] and r["graphs"] == "compiled"
    assert status["model"]["sizes"]["output"] == "1280x720"


@pytest.mark.cuda
@pytest.mark.parametrize("compile", [False, True], ids=["eager", "compiled"])
def test_the_gpu_output_is_within_1e_3_of_the_cpu_reference(compile):
    from inference.gpu_runtime import parity

    found = parity(SHIPPED_ONNX, "cuda", "paper", compile=compile)
    assert found["graphs"] == ("compiled" if compile else "eager")
    assert found["max_abs_diff_image"] <= 1e-3, found


@pytest.mark.cuda
def test_rig_live_device_cuda_replays_a_take(rig_toml, take):
    r = run_rig("live", "-c", rig_toml, "--replay", take, "--device", "cuda", "--port", 0, "--seconds", 20, "--json", timeout=300)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["runtime"]["kind"] == "torch" and summary["runtime"]["device"].startswith("cuda")
    assert "model on cuda" in r.stderr


@pytest.mark.cuda
def test_rig_model_render_device_cuda(take, tmp_path):
    out = tmp_path / "half.png"
    r = run_rig("model", "render", "--sequence", take, "--view", 0.5, "--device", "cuda", "--size", "paper", "-o", out, "--json", timeout=300)
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["size"] == [1280, 720] and info["runtime"]["kind"] == "torch" and out.is_file()
