"""The exported model's two parts (M.stage1.onnx, M.view.onnx), the torch-free SplitPipeline that runs
them, and the slimmed file (large constant tensors computed by a few nodes instead of stored).

The models are the session's exports (conftest.py: tiny and oracle at the test size, with --fp16);
no test here exports another."""
from __future__ import annotations

import os
import shutil

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from fp16_support import skip_without_float16_cpu_kernels
from onnx import helper, numpy_helper

from inference.errors import InferenceError
from inference.runtime import NovelViewPipeline, SplitPipeline, part_path
from inference.runtime.metadata import read_file_metadata
from inference.runtime.preprocess import intrinsics, pose
from inference.runtime.synthetic import example_inputs, rig_camera

SOURCES = ["left_image", "right_image", "left_K", "right_K", "left_pose", "right_pose"]
DEPTHS = ["left_depth", "right_depth"]
STAGE1 = ["stage1_points_left", "stage1_points_right", "stage1_opacity_left", "stage1_opacity_right"]
TARGET = ["target_K", "target_pose"]
CPU = ["CPUExecutionProvider"]


def fp16_of(path):
    return path.with_name(path.stem + ".fp16.onnx")


def session_inputs(path) -> list[str]:
    return [i.name for i in ort.InferenceSession(str(path), providers=CPU).get_inputs()]


def node_stages(path) -> set[str]:
    from inference.export import stage_of

    return {stage_of(n) for n in onnx.load(str(path)).graph.node}


def targets(sizes):
    """Two viewpoints: between the sources, and outside them higher up and nearer."""
    return [rig_camera("a", 8.0, sizes.output), rig_camera("b", -45.0, sizes.output, distance=2.6)]


@pytest.mark.parametrize("which", ["tiny_onnx", "oracle_onnx"])
def test_split_files_carry_the_model_metadata_and_their_own_interface(which, request):
    exported = request.getfixturevalue(which)
    depth = DEPTHS if exported.backbone == "oracle" else []
    for whole, precision in ((exported.path, "fp32"), (fp16_of(exported.path), "fp16")):
        meta = read_file_metadata(whole)
        assert "splat_sap.part" not in meta and meta["splat_sap.precision"] == precision
        expected = {"stage1": (SOURCES + depth, STAGE1), "view": (STAGE1 + SOURCES + TARGET, ["image", "depth"])}
        for part, (inputs, outputs) in expected.items():
            path = part_path(whole, part)
            assert path.name == f"{whole.stem}.{part}.onnx" and path.is_file()
            part_meta = read_file_metadata(path)
            # The model's keys, the same values, and the part's own interface.
            assert set(part_meta) == set(meta) | {"splat_sap.part"} and part_meta["splat_sap.part"] == part
            for key in ("splat_sap.format", "splat_sap.config", "splat_sap.weights", "splat_sap.precision"):
                assert part_meta[key] == meta[key]
            assert part_meta["splat_sap.inputs"].split(",") == inputs == session_inputs(path)
            m = onnx.load(str(path))
            assert [o.name for o in m.graph.output] == outputs
            assert all(v.type.tensor_type.elem_type == onnx.TensorProto.FLOAT for v in list(m.graph.input) + list(m.graph.output))
        # The cut: stage 1's networks only in stage1, the target-dependent stages only in view.
        if precision == "fp32":
            assert node_stages(part_path(whole, "stage1")) <= {"point_init", "affine_transform", None}
            view_stages = node_stages(part_path(whole, "view"))
            assert not view_stages & {"point_init", "affine_transform"}
            assert {"depth_init", "depth_refine", "colour_init", "gaussian_plane", "splatting"} <= view_stages


@pytest.mark.parametrize("which", ["tiny_onnx", "oracle_onnx"])
def test_stage1_once_then_two_views_match_the_whole_model(which, request):
    exported = request.getfixturevalue(which)
    pipe = SplitPipeline(exported.path, providers=CPU)
    whole = ort.InferenceSession(str(exported.path), providers=CPU)
    assert pipe.info.inputs == tuple(i.name for i in whole.get_inputs())
    feeds = example_inputs(pipe.sizes, pipe.info.needs_depth).arrays
    sources = {n: a for n, a in feeds.items() if n not in TARGET}
    s1 = pipe.stage1(sources)
    assert list(s1) == STAGE1 and pipe.stage1_ms > 0
    cw, ch = pipe.sizes.coarse
    assert s1["stage1_points_left"].shape == (1, 3, ch, cw) and s1["stage1_opacity_right"].shape == (1, 1, ch, cw)
    assert all(0 <= s1[n].min() and s1[n].max() < 1 for n in STAGE1[2:])
    images = []
    for cam in targets(pipe.sizes):
        target = {"target_K": intrinsics(cam, pipe.sizes.output), "target_pose": pose(cam)}
        ref_image, ref_depth = whole.run(["image", "depth"], {**sources, **target})
        image, depth = pipe.view(s1, sources, target["target_K"], target["target_pose"])
        assert pipe.view_ms > 0
        di, dd = np.abs(image - ref_image).max(), np.abs(depth - ref_depth).max()
        print(f"\n{exported.backbone} at {cam.name}: split vs whole image {di:.1e}, depth {dd:.1e} m")
        assert di <= 1e-5 and dd <= 1e-5  # measured 0: the same graph, cut in two
        view = pipe.render(s1, sources, cam)  # the same from a camera
        assert np.array_equal(view.image, image[0].transpose(1, 2, 0)) and np.array_equal(view.depth, depth[0, 0]) and view.ms > 0
        images.append(image)
    assert np.abs(images[0] - images[1]).mean() > 0.02  # two viewpoints, two views


def test_fp16_parts_match_the_fp16_model(tiny_onnx):
    half = fp16_of(tiny_onnx.path)
    skip_without_float16_cpu_kernels(onnx.load(str(half)))
    pipe = SplitPipeline(half, providers=CPU)
    assert pipe.info.precision == "fp16"
    feeds = example_inputs(pipe.sizes, False).arrays
    ref_image, ref_depth = ort.InferenceSession(str(half), providers=CPU).run(["image", "depth"], feeds)
    image, depth = pipe.view(pipe.stage1(feeds), feeds, feeds["target_K"], feeds["target_pose"])
    assert np.abs(image - ref_image).max() <= 1e-5 and np.abs(depth - ref_depth).max() <= 1e-5  # measured 0


def test_stage1_does_not_depend_on_the_target(tiny_onnx):
    import torch

    from inference.model.checkpoint import model_from_record

    pipe = SplitPipeline(tiny_onnx.path, providers=CPU)
    assert not set(TARGET) & set(pipe.stage1_info.inputs)
    feeds = example_inputs(pipe.sizes, False).arrays
    a = pipe.stage1(feeds)
    cam = targets(pipe.sizes)[1]
    b = pipe.stage1({**feeds, "target_K": intrinsics(cam, pipe.sizes.output), "target_pose": pose(cam)})
    assert all(np.array_equal(a[n], b[n]) for n in STAGE1)
    # They are the tensors torch's depth_init reads, whatever the target.
    model = model_from_record(pipe.info.config, pipe.info.weights)
    with torch.no_grad():
        for k in (feeds, {**feeds, "target_K": intrinsics(cam, pipe.sizes.output), "target_pose": pose(cam)}):
            ref = model.run(*[torch.from_numpy(k[n]) for n in model.input_names])["stage1"]
            diffs = {n: float(np.abs(a[n] - ref[n].numpy()).max()) for n in STAGE1}
            assert max(diffs.values()) < 1e-4, diffs  # float rounding of ONNX Runtime vs torch


def test_a_missing_or_foreign_part_is_one_line_error(tiny_onnx, oracle_onnx, tmp_path):
    def folder(name: str, files: dict[str, os.PathLike]):
        d = tmp_path / name
        d.mkdir()
        for target, source in files.items():
            (d / target).symlink_to(source)
        return d / "m.onnx"

    tiny = tiny_onnx.path
    no_view = folder("no_view", {"m.onnx": tiny, "m.stage1.onnx": part_path(tiny, "stage1")})
    with pytest.raises(InferenceError) as err:
        SplitPipeline(no_view)
    assert "\n" not in str(err.value)
    assert str(err.value).startswith(f"{no_view.with_name('m.view.onnx')}: no such file") and "re-export" in str(err.value)
    with pytest.raises(InferenceError, match=r"m\.stage1\.onnx: no such file .*re-export"):
        SplitPipeline(folder("none", {"m.onnx": tiny}))
    # The whole file is not needed: the parts are what runs.
    SplitPipeline(folder("parts_only", {"m.stage1.onnx": part_path(tiny, "stage1"), "m.view.onnx": part_path(tiny, "view")}))
    oracle_view = part_path(oracle_onnx.path, "view")  # its weights are in a data file beside it (--shared-data)
    data = {p.name: p for p in oracle_onnx.path.parent.glob("*.data")}
    assert data
    with pytest.raises(InferenceError, match="different exports.*re-export"):
        SplitPipeline(folder("mixed", {"m.stage1.onnx": part_path(tiny, "stage1"), "m.view.onnx": oracle_view, **data}))
    # a link to a part reads the data file beside the part itself
    SplitPipeline(folder("linked", {"m.stage1.onnx": part_path(oracle_onnx.path, "stage1"), "m.view.onnx": oracle_view}), providers=CPU)
    # a part copied without the data file it reads: one line naming the file
    copied = tmp_path / "no_data"
    copied.mkdir()
    for part in ("stage1", "view"):
        shutil.copyfile(part_path(oracle_onnx.path, part), copied / f"m.{part}.onnx")
    with pytest.raises(InferenceError) as err:
        SplitPipeline(copied / "m.onnx", providers=CPU)
    assert "\n" not in str(err.value) and f"its weights file {next(iter(data))} is not beside it" in str(err.value)
    with pytest.raises(InferenceError, match="not the view part.*re-export"):
        SplitPipeline(folder("swapped", {"m.stage1.onnx": part_path(tiny, "stage1"), "m.view.onnx": part_path(tiny, "stage1")}))
    # a part given where a whole model is wanted (`rig model check|render`): one line naming the model
    for part in ("stage1", "view"):
        with pytest.raises(InferenceError, match=rf"the {part} part of a Splat-SAP model, not a whole one; give the model itself \({tiny.name}\)"):
            NovelViewPipeline(part_path(tiny, part), providers=CPU)
    with pytest.raises(InferenceError, match="target_K must be a 3x3 matrix"):
        pipe = SplitPipeline(tiny, providers=CPU)
        feeds = example_inputs(pipe.sizes, False).arrays
        pipe.view({n: np.zeros(1, np.float32) for n in STAGE1}, feeds, np.zeros((2, 2)), feeds["target_pose"])


def large_constants(model: onnx.ModelProto, parameters: set[str]) -> list[str]:
    """Initializers of 1024+ elements whose elements are all equal, but for the model's parameters
    (an untrained model's zero-initialised output layers)."""
    out = []
    for init in model.graph.initializer:
        a = numpy_helper.to_array(init).reshape(-1)
        if a.size >= 1024 and (a == a[0]).all() and init.name not in parameters:
            out.append(init.name)
    return out


@pytest.mark.parametrize("which", ["tiny_onnx", "oracle_onnx"])
def test_the_file_stores_its_weights_not_constant_tensors(which, request):
    from inference.config import ModelConfig
    from inference.model.pipeline import build_model

    exported = request.getfixturevalue(which)
    meta = read_file_metadata(exported.path)
    parameters = dict(build_model(ModelConfig.from_json(meta["splat_sap.config"])).named_parameters())
    weights = 4 * sum(p.numel() for p in parameters.values())
    m = onnx.load(str(exported.path))
    stored = sum(numpy_helper.to_array(i).nbytes for i in m.graph.initializer)
    size = exported.path.stat().st_size
    print(f"\n{exported.backbone}: file {size / 1e6:.2f} MB, float32 weights {weights / 1e6:.2f} MB, initializers {stored / 1e6:.2f} MB")
    # Before slimming: tiny 31.2 MB for 21.2 MB of weights, oracle 8.75 MB for 0.21 MB.
    assert not large_constants(m, set(parameters))
    assert {"ConstantOfShape", "Range"} <= {n.op_type for n in m.graph.node}
    if exported.backbone == "tiny":
        assert size <= 1.5 * weights  # measured 1.06
    else:  # 0.2 MB of weights: the graph's 2000 nodes weigh more than they do
        assert stored <= 1.5 * weights and size <= 1.5e6  # measured 0.88 MB


def test_slim_constants_computes_the_same_values_exactly(tmp_path):
    from inference.export import slim_constants

    rng = np.random.default_rng(0)
    ys, xs = np.meshgrid(np.arange(36, dtype=np.float32), np.arange(64, dtype=np.float32), indexing="ij")
    signed_zeros = np.zeros((40, 40), np.float32)
    signed_zeros[3, 5] = -0.0
    constants = {
        "zeros": np.zeros((1, 36, 64), np.float32),  # replaced: ConstantOfShape
        "eps": np.full((2, 1, 600), 1e-6, np.float32),
        "flags": np.ones((32, 32), bool),
        "pixels": np.stack([xs, ys])[None],  # replaced: Concat of two ramps (x along W, y along H)
        "homogeneous": np.stack([xs, ys, np.ones_like(xs)]),
        "rows": np.broadcast_to((7 - 3 * np.arange(50, dtype=np.float32))[:, None], (50, 30)).copy(),
        "index": np.arange(2000, dtype=np.int64) * 2 + 5,
        "centres": np.broadcast_to(np.arange(64, dtype=np.float32) + 0.5, (36, 64)).copy(),  # kept: not integers
        "signed_zeros": signed_zeros,  # kept: -0.0 is not 0.0 and Range makes +0.0
        "noise": rng.standard_normal((40, 40)).astype(np.float32),  # kept
        "small": np.zeros(100, np.float32),  # kept: too small to matter
        "weight": np.zeros((64, 64), np.float32),  # kept: named a parameter
    }
    inits = [numpy_helper.from_array(a, n) for n, a in constants.items()]
    nodes = [helper.make_node("Identity", [n], [f"out_{n}"]) for n in constants]
    outputs = [helper.make_tensor_value_info(f"out_{n}", helper.np_dtype_to_tensor_dtype(a.dtype), a.shape) for n, a in constants.items()]
    model = helper.make_model(helper.make_graph(nodes, "g", [], outputs, initializer=inits), opset_imports=[helper.make_opsetid("", 18)])
    report = slim_constants(model, keep={"weight"})
    onnx.checker.check_model(model)
    left = {i.name for i in model.graph.initializer if i.name in constants}
    assert left == {"centres", "signed_zeros", "noise", "small", "weight"} and report["replaced"] == 7
    path = tmp_path / "slim.onnx"
    onnx.save(model, path)
    results = ort.InferenceSession(str(path), providers=CPU).run(None, {})
    for (name, a), b in zip(constants.items(), results):
        assert b.dtype == a.dtype and b.shape == a.shape
        assert np.array_equal(a.view(np.uint8), np.ascontiguousarray(b).view(np.uint8)), name  # bit for bit
