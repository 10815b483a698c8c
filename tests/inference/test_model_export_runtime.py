"""Export, ONNX Runtime parity, the torch-free runtime and the `rig model` commands."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import onnx
import pytest
from fp16_support import skip_without_float16_cpu_kernels

from inference.errors import InferenceError
from inference.runtime import NovelViewPipeline
from inference.runtime.preprocess import pinhole
from inference.runtime.synthetic import example_inputs, rig_camera
from rig.cli import main

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]


def run_cli(capsys, *argv) -> tuple[int, dict]:
    rc = main(list(argv))
    lines = capsys.readouterr().out.strip().splitlines()
    return rc, json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}


@pytest.mark.parametrize("which", ["tiny_onnx", "oracle_onnx"])
def test_onnx_runtime_matches_torch(which, request, capsys):
    model = request.getfixturevalue(which)
    rc, info = run_cli(capsys, "model", "check", str(model.path), "--json")
    with capsys.disabled():
        print(f"\n{model.backbone}: max |ORT - torch| image {info['max_abs_diff_image']:.2e}, depth {info['max_abs_diff_depth']:.2e} m")
    assert rc == 0 and info["ok"]
    assert info["max_abs_diff_image"] <= 1e-3
    assert info["max_abs_diff_depth"] <= 1e-3


def test_exported_graph_is_opset_18_with_the_documented_interface(tiny_onnx, oracle_onnx):
    for exported, extra in ((tiny_onnx, []), (oracle_onnx, ["left_depth", "right_depth"])):
        m = onnx.load(str(exported.path))
        assert max(o.version for o in m.opset_import if o.domain in ("", "ai.onnx")) >= 18
        names = [i.name for i in m.graph.input]
        assert names == ["left_image", "right_image", "left_K", "right_K", "left_pose", "right_pose", "target_K", "target_pose"] + extra
        assert [o.name for o in m.graph.output] == ["image", "depth"]
        # Plain ONNX operators only (no custom domains): it runs on any ONNX Runtime build and TensorRT.
        assert {n.domain for n in m.graph.node} <= {"", "ai.onnx"}
        assert "GridSample" in {n.op_type for n in m.graph.node}


def test_fp16_variant_keeps_float32_interface_and_geometry(tiny_onnx):
    import onnxruntime as ort

    half = tiny_onnx.path.with_name(tiny_onnx.path.stem + ".fp16.onnx")
    m = onnx.load(str(half))
    assert all(i.type.tensor_type.elem_type == onnx.TensorProto.FLOAT for i in list(m.graph.input) + list(m.graph.output))
    # Every learned layer's weights are float16 (measured: all 72 Conv/MatMul/Gemm weights).
    dtypes = {i.name: i.data_type for i in m.graph.initializer}
    weights = [dtypes[n.input[1]] for n in m.graph.node if n.op_type in ("Conv", "MatMul", "Gemm") and n.input[1] in dtypes]
    assert len(weights) > 50 and set(weights) == {onnx.TensorProto.FLOAT16}
    skip_without_float16_cpu_kernels(m)
    feeds = example_inputs(NovelViewPipeline(tiny_onnx.path).sizes, False).arrays
    full = ort.InferenceSession(str(tiny_onnx.path), providers=["CPUExecutionProvider"]).run(None, feeds)
    halfs = ort.InferenceSession(str(half), providers=["CPUExecutionProvider"]).run(None, feeds)
    image, depth = np.abs(halfs[0] - full[0]), np.abs(halfs[1] - full[1])
    print(f"\nfp16 vs fp32: image max {image.max():.2e}, mean {image.mean():.2e}; depth max {depth.max():.2e} m")
    # Measured 1.05e-5 (image) and 1.2e-5 m (depth): the untrained output heads carry little of
    # the float16 rounding through.
    assert image.max() < 1e-4 and depth.max() < 1e-4


def test_runtime_renders_simulator_frames_from_camera_models(oracle_onnx, sim_frames):
    """Distorted 640x360 frames and CameraModels in, a novel view and its metric depth out."""
    pipe = NovelViewPipeline(oracle_onnx.path)
    rig = sim_frames.rig
    target = rig["sup2"]
    view = pipe.render(sim_frames.rgb["left"], sim_frames.rgb["right"], rig["left"], rig["right"], target,
                       sim_frames.depth["left"], sim_frames.depth["right"])
    ow, oh = pipe.sizes.output
    assert view.image.shape == (oh, ow, 3) and view.depth.shape == (oh, ow)
    assert view.image_uint8().dtype == np.uint8
    truth = sim_frames.render(pinhole(target, (ow, oh)))
    rel = np.abs(view.depth - truth.depth) / truth.depth
    print(f"\nruntime depth vs ground truth at {ow}x{oh}: median relative error {np.median(rel):.4f}, within 5 %: {np.mean(rel < 0.05):.3f}")
    assert np.median(rel) < 0.02
    # The viewpoint is an input: another target, another image, same session.
    other = pipe.render(sim_frames.rgb["left"], sim_frames.rgb["right"], rig["left"], rig["right"], rig["sup3"],
                        sim_frames.depth["left"], sim_frames.depth["right"])
    assert np.abs(other.image - view.image).mean() > 0.05  # measured 0.087


def test_runtime_reports_bad_input_clearly(oracle_onnx, tiny_onnx, tmp_path):
    pipe = NovelViewPipeline(tiny_onnx.path)
    left, right, target = rig_camera("left", -30, (64, 48)), rig_camera("right", 30, (64, 48)), rig_camera("t", 0, (64, 48))
    frame = np.zeros((48, 64, 3), np.uint8)
    with pytest.raises(InferenceError, match="left.*is 32x48, but its calibration is for 64x48"):
        pipe.render(frame[:, :32], frame, left, right, target)
    with pytest.raises(InferenceError, match="needs left_depth and right_depth"):
        NovelViewPipeline(oracle_onnx.path).render(frame, frame, left, right, target)
    with pytest.raises(InferenceError, match="no such model file"):
        NovelViewPipeline(tmp_path / "missing.onnx")
    foreign = tmp_path / "foreign.onnx"
    g = onnx.helper.make_graph([onnx.helper.make_node("Identity", ["x"], ["y"])], "g",
                               [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
                               [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])])
    onnx.save(onnx.helper.make_model(g, ir_version=8, opset_imports=[onnx.helper.make_opsetid("", 18)]), foreign)
    with pytest.raises(InferenceError, match="not a Splat-SAP model"):
        NovelViewPipeline(foreign)
    (tmp_path / "torn.onnx").write_bytes(b"\x08\x07garbage")
    with pytest.raises(InferenceError, match="cannot load it"):
        NovelViewPipeline(tmp_path / "torn.onnx")


NO_TORCH = textwrap.dedent(
    """
    import importlib.abc, json, sys

    class BlockTorch(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "torch" or name.startswith("torch."):
                raise ImportError("torch is not installed here")
            return None

    sys.meta_path.insert(0, BlockTorch())
    import numpy as np
    from inference.runtime import NovelViewPipeline
    from inference.runtime.synthetic import rig_camera, smooth_image

    pipe = NovelViewPipeline(sys.argv[1])
    rng = np.random.default_rng(0)
    left, right = rig_camera("left", -30, (320, 180)), rig_camera("right", 30, (320, 180))
    target = rig_camera("target", 5, (1280, 720))
    frames = [(smooth_image(rng, (320, 180)) * 255).astype(np.uint8) for _ in range(2)]
    view = pipe.render(frames[0], frames[1], left, right, target)
    print(json.dumps({"torch_loaded": any(m == "torch" or m.startswith("torch.") for m in sys.modules),
                      "shape": list(view.image.shape), "finite": bool(np.isfinite(view.image).all()),
                      "providers": pipe.providers}))
    """
)


def test_sessions_take_omp_num_threads_where_no_thread_count_is_given(tiny_onnx, monkeypatch):
    # ONNX Runtime ignores OMP_NUM_THREADS: a process given one core ran a spinning thread per core
    from inference.runtime import open_session

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert open_session(tiny_onnx.path).get_session_options().intra_op_num_threads == 1
    assert open_session(tiny_onnx.path, threads=2).get_session_options().intra_op_num_threads == 2
    monkeypatch.setenv("OMP_NUM_THREADS", "many")
    assert open_session(tiny_onnx.path).get_session_options().intra_op_num_threads == 0  # ONNX Runtime's own default


def test_runtime_runs_with_torch_absent(tiny_onnx):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", NO_TORCH, str(tiny_onnx.path)], capture_output=True, text=True, env=env, cwd=REPO, timeout=120)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["torch_loaded"] is False
    assert result["shape"] == [180, 320, 3] and result["finite"]


def test_model_commands_fail_cleanly(tmp_path, capsys):
    assert main(["model", "check", str(tmp_path / "none.onnx")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such model file" in err
    assert main(["model", "export", "--checkpoint", str(tmp_path / "none.pt"), "-o", str(tmp_path / "m.onnx")]) == 2
    assert "no such checkpoint" in capsys.readouterr().err
    assert main(["model", "export", "--opset", "17", "-o", str(tmp_path / "m.onnx")]) == 2
    assert "opset 18" in capsys.readouterr().err


def test_bench_reports_per_stage_times_of_both(tiny_onnx, capsys):
    rc, info = run_cli(capsys, "model", "bench", "--model", str(tiny_onnx.path), "--repeat", "1", "--json")
    assert rc == 0
    stages = ["point_init", "affine_transform", "depth_init", "depth_refine", "colour_init", "gaussian_plane", "splatting", "total"]
    for key in stages:
        assert info["torch_ms"][key] > 0
        assert info["ort_ms"][key] > 0
    assert info["size"] == {"coarse": "128x64", "fine": "256x144", "output": "320x180"}
    # The speedup is rounded to 3 decimals (at most 5e-4 off; measured 2.9e-4 at 1.924x).
    assert info["speedup"] == pytest.approx(info["torch_ms"]["total"] / info["ort_ms"]["total"], abs=1e-3)
    with capsys.disabled():
        print(f"\nbench at test size: torch {info['torch_ms']['total']:.0f} ms, ORT {info['ort_ms']['total']:.0f} ms, speedup {info['speedup']:.2f}x")


def test_check_on_a_simulator_snapshot(oracle_onnx, tmp_path, capsys):
    """The check a user runs on real-looking inputs: `rig sim snapshot`, then `rig model check --snapshot`."""
    cfg = tmp_path / "rig.toml"
    assert main(["config", "init", "--sim", "--cameras", "3", "--width", "320", "--height", "180", str(cfg)]) == 0
    assert main(["sim", "snapshot", "-c", str(cfg), "-t", "1.0", "-o", str(tmp_path / "snap")]) == 0
    capsys.readouterr()
    rc, info = run_cli(capsys, "model", "check", str(oracle_onnx.path), "--snapshot", str(tmp_path / "snap"), "--json")
    with capsys.disabled():
        print(f"\nsnapshot check: {info['inputs']}: image {info['max_abs_diff_image']:.2e}, depth {info['max_abs_diff_depth']:.2e} m")
    assert rc == 0 and info["ok"] and "sup1" in info["inputs"]
    # Real occlusion edges: the splatting's geometry runs bit-identically in both, so depth agrees too.
    assert info["max_abs_diff_depth"] <= 1e-3
    assert main(["model", "check", str(oracle_onnx.path), "--snapshot", str(tmp_path / "snap"), "--target", "nobody"]) == 2
    assert "no camera 'nobody'" in capsys.readouterr().err
