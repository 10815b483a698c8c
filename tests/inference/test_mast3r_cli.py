"""`--backbone mast3r --weights W` on the command line: export (external data, fp16) that the
runtime loads and `rig model check` passes, the one-line refusals, and training with the backbone
frozen. Random weights in the official layout at reduced depth (1 encoder + 2 decoder blocks)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from mast3r_support import official_layout, random_state, write_checkpoint

import inference.onnx_weights as onnx_weights
from rig.cli import main as rig_main

pytestmark = pytest.mark.slow

ENC, DEC = 1, 2


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> tuple[Path, dict]:
    state = random_state(official_layout(ENC, DEC), seed=5)
    return write_checkpoint(tmp_path_factory.mktemp("mast3r") / "mast3r_random.pth", state, ENC, DEC), state


def rig(capsys, *argv) -> tuple[int, str, str]:
    code = rig_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line(code: int, err: str, *fragments: str) -> str:
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, err)
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def test_export_with_external_data_loads_in_the_runtime_and_checks(weights, tmp_path, capsys, monkeypatch):
    w, _ = weights
    # The reduced model's 0.4 GB of weights stand for the full model's 2.6 GB: the same path.
    monkeypatch.setattr(onnx_weights, "EXTERNAL_DATA_LIMIT", 100_000_000)
    out = tmp_path / "m.onnx"
    code, stdout, err = rig(capsys, "model", "export", "--backbone", "mast3r", "--weights", w, "--size", "test", "--fp16", "-o", out, "--json")
    assert code == 0, err
    info = json.loads(stdout)
    assert "CC BY-NC-SA 4.0" in err and "CC BY-NC-SA 4.0" in info["licence"]
    data = [Path(p) for p in info["data_files"]]
    assert [p.name.split(".")[:2] for p in data] == [["m", "onnx"], ["m", "fp16"]] and all(p.stat().st_size > 100_000_000 for p in data)
    for f in info["files"] + info["parts"]:
        assert Path(f).stat().st_size < 20_000_000  # the weights are beside, not inside
    proto = onnx.load(str(out), load_external_data=False)
    meta = {p.key: p.value for p in proto.metadata_props}
    cfg = json.loads(meta["splat_sap.config"])
    assert cfg["backbone"]["kind"] == "mast3r" and (cfg["backbone"]["mast3r_encoder_blocks"], cfg["backbone"]["mast3r_decoder_blocks"]) == (ENC, DEC)
    assert json.loads(meta["splat_sap.weights"])["backbone_weights"]["path"] == str(w.resolve())
    # ONNX Runtime's limits: no matrix inverse, grid_sample on 4-D tensors only.
    assert "Inverse" not in {n.op_type for n in proto.graph.node}
    inferred = onnx.shape_inference.infer_shapes(proto)
    ranks = {v.name: len(v.type.tensor_type.shape.dim) for v in list(inferred.graph.value_info) + list(inferred.graph.input)}
    grids = [n for n in inferred.graph.node if n.op_type == "GridSample"]
    assert grids and all(ranks.get(n.input[0]) == 4 for n in grids)

    # The runtime (onnxruntime + numpy) opens the files with their data beside them, in another folder too:
    # `rig model check` runs the whole file against torch (the weights read again from the recorded file).
    moved = tmp_path / "moved"
    moved.mkdir()
    for f in [out, *map(Path, info["parts"][:2]), data[0]]:
        f.rename(moved / f.name)
    code, stdout, err = rig(capsys, "model", "check", moved / "m.onnx", "--json")
    assert code == 0, err
    check = json.loads(stdout)
    assert check["ok"] and check["max_abs_diff_image"] <= 1e-3
    print("rig model check (mast3r 2+2, test size):", check["max_abs_diff_image"], check["max_abs_diff_depth"])
    # benchmarking the exported model runs the MASt3R weights too: the licence is said (it was not)
    code, stdout, err = rig(capsys, "model", "bench", "--model", moved / "m.onnx", "--repeat", 1, "--json")
    assert code == 0, err
    bench = json.loads(stdout.strip().splitlines()[-1])  # (the check's figures printed above come first)
    assert bench["backbone"] == "mast3r" and "CC BY-NC-SA 4.0" in err, err
    # The live path's two parts share the one data file.
    from inference.runtime import SplitPipeline
    from inference.runtime.synthetic import example_inputs

    split = SplitPipeline(moved / "m.onnx", providers=["CPUExecutionProvider"])
    feeds = {n: a for n, a in example_inputs(split.stage1_info.config.sizes, False).arrays.items()}
    image, depth = split.view(split.stage1(feeds), feeds, feeds["target_K"], feeds["target_pose"])
    assert image.shape == (1, 3, 180, 320) and float((depth > 0).mean()) > 0.01  # the points (2 m ahead) render

    from fp16_support import float16_op_types  # the fp16 files: their float16 learned layers run here when ORT has the kernels
    half = onnx.load(str(info["files"][1]), load_external_data=False)
    assert {"MatMul", "Conv"} <= float16_op_types(half)


def test_bad_weights_are_refused_in_one_line(weights, tmp_path, capsys):
    w, state = weights
    out = tmp_path / "m.onnx"
    one_line(*rig(capsys, "model", "export", "--backbone", "mast3r", "-o", out)[::2], "--backbone mast3r needs --weights PATH")
    one_line(*rig(capsys, "model", "export", "--backbone", "mast3r", "--weights", tmp_path / "none.pth", "-o", out)[::2],
             "none.pth: no such MASt3R weights file")
    one_line(*rig(capsys, "model", "export", "--backbone", "tiny", "--weights", w, "-o", out)[::2], "use it with --backbone mast3r")
    # Another architecture: the official layout with one key renamed, or one shape changed (meta
    # tensors: the check reads names and shapes only, before any data).
    meta = {k: torch.empty(v.shape, device="meta") for k, v in state.items()}
    renamed = {("enc_blocks.0.attn.proj.weights" if k == "enc_blocks.0.attn.proj.weight" else k): v for k, v in meta.items()}
    write_checkpoint(tmp_path / "renamed.pth", renamed, ENC, DEC)
    one_line(*rig(capsys, "model", "export", "--backbone", "mast3r", "--weights", tmp_path / "renamed.pth", "--size", "test", "-o", out)[::2],
             "not the MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric layout", "unexpected key enc_blocks.0.attn.proj.weights (1024, 1024)",
             "missing enc_blocks.0.attn.proj.weight (1024, 1024)")
    reshaped = dict(meta, **{"downstream_head1.dpt.head.4.weight": torch.empty(3, 128, 1, 1, device="meta")})
    write_checkpoint(tmp_path / "reshaped.pth", reshaped, ENC, DEC)
    # (export, not eval: eval reads its take first, a check that costs nothing against reading the weights)
    one_line(*rig(capsys, "model", "export", "--backbone", "mast3r", "--weights", tmp_path / "reshaped.pth", "--size", "test", "-o", out)[::2],
             "downstream_head1.dpt.head.4.weight has shape (3, 128, 1, 1), expected (4, 128, 1, 1)")
    data = w.read_bytes()[:5_000_000]
    (tmp_path / "cut.pth").write_bytes(data)
    one_line(*rig(capsys, "model", "export", "--backbone", "mast3r", "--weights", tmp_path / "cut.pth", "--size", "test", "-o", out)[::2],
             "cut.pth: not a readable torch checkpoint (truncated or corrupt?")
    assert not out.exists()


def test_training_keeps_the_backbone_frozen_and_trains_stage_1(weights, tmp_path, capsys):
    from simulator.takes import write_take

    w, state = weights
    take = Path(write_take(tmp_path / "take", seed=7, seconds=0.2, fps=10, size=(320, 180))["out"])
    light = tmp_path / "light.json"
    light.write_text(json.dumps({"supervision_per_step": 1, "eval_sets": 1, "render_scales": [1],
                                 "stage1": {"steps": 2, "batch": 1, "warmup": 1, "lr": 1e-3}, "stage2": {"steps": 0}}))
    run = tmp_path / "run"
    one_line(*rig(capsys, "train", take, "-o", run, "--config", light, "--size", "test", "--backbone", "mast3r")[::2], "needs --weights PATH")
    code, stdout, err = rig(capsys, "train", take, "-o", run, "--config", light, "--size", "test", "--backbone", "mast3r", "--weights", w,
                            "--threads", "1", "--eval-every", "100", "--json")
    assert code == 0, err
    assert "CC BY-NC-SA 4.0" in err
    record = json.loads((run / "train.json").read_text())
    assert record["backbone_weights"]["path"] == str(w.resolve()) and record["config"]["train_backbone"] is False
    trained = torch.load(run / "model.pt", weights_only=True)["state_dict"]
    # The backbone is the file's weights, untouched (under our names: the DPT aliases and mask_token are not kept).
    backbone = {k[len("point_init.net."):]: v for k, v in trained.items() if k.startswith("point_init.net.")}
    assert len(backbone) == len(state) - 1 - 8 and all(torch.equal(v, state[k]) for k, v in backbone.items())
    # Stage 1's affine transform moved from its initial weights.
    from inference.config import ModelConfig
    from inference.model.pipeline import build_model

    cfg = ModelConfig.from_dict(record["config"]["model"])
    initial = {k: v for k, v in build_model(cfg, seed=0).state_dict().items() if k.startswith("affine_transform.")}
    changed = [k for k, v in initial.items() if not torch.equal(v, trained[k])]
    assert len(changed) > len(initial) // 2, changed

    # rig model eval on the untrained pipeline over MASt3R (S = 1, T = 0: MASt3R's own geometry).
    code, stdout, err = rig(capsys, "model", "eval", "--backbone", "mast3r", "--weights", w, "--size", "test", "--sequence", take,
                            "--max-sets", "1", "--no-references", "--json")
    assert code == 0, err
    result = json.loads(stdout)
    assert result["sets"] == 1 and result["overall"]["psnr"] > 0 and "CC BY-NC-SA 4.0" in err


def test_external_data_replaces_an_earlier_export_only_once_the_models_are_written(tmp_path):
    from onnx import TensorProto, helper, numpy_helper

    from inference.export import _save
    from inference.onnx_weights import data_files, detach, write_models

    def model(value: float) -> onnx.ModelProto:
        w = numpy_helper.from_array(np.full((64, 64), value, np.float32), "w")
        g = helper.make_graph([helper.make_node("MatMul", ["x", "w"], ["y"])], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 64])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 64])], [w])
        return helper.make_model(g, opset_imports=[helper.make_opsetid("", 18)])

    import onnxruntime as ort

    path = tmp_path / "m.onnx"
    run = lambda: ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"x": np.ones((1, 64), np.float32)})[0]  # noqa: E731
    for value in (1.0, 2.0):
        proto = model(value)
        store = detach(proto)
        first = write_models([(proto, path)], store, _save, limit=1000)
        assert data_files(path) == [first]  # the earlier export's data file is gone, the new one named by its content
        assert float(run()[0, 0]) == 64 * value
    # Under the limit the file is self-contained again, and the data file goes.
    proto = model(3.0)
    assert write_models([(proto, path)], detach(proto), _save) is None
    assert data_files(path) == [] and float(run()[0, 0]) == 192.0
