"""Models and checkpoints are written atomically, through common.files: the finished file or the
previous one, never a torn one, and nothing left beside it."""
from __future__ import annotations

import onnx
import pytest
import torch
from onnx.external_data_helper import uses_external_data

from inference.config import ModelConfig, Sizes
from inference.errors import InferenceError
from inference.export import _save
from inference.model.checkpoint import load_checkpoint, save_checkpoint
from inference.model.pipeline import build_model


def test_export_writes_self_contained_models_and_nothing_else(tiny_onnx):
    folder = tiny_onnx.path.parent
    assert sorted(p.name for p in folder.iterdir()) == ["tiny.fp16.onnx", "tiny.fp16.stage1.onnx", "tiny.fp16.view.onnx",
                                                       "tiny.onnx", "tiny.stage1.onnx", "tiny.view.onnx"]  # no temporaries, no .data files
    for path in folder.iterdir():
        model = onnx.load(str(path), load_external_data=False)
        assert not any(uses_external_data(t) for t in model.graph.initializer)


def identity_model() -> onnx.ModelProto:
    g = onnx.helper.make_graph([onnx.helper.make_node("Identity", ["x"], ["y"])], "g",
                               [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
                               [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])])
    return onnx.helper.make_model(g, ir_version=8, opset_imports=[onnx.helper.make_opsetid("", 18)])


def test_a_failed_model_write_is_one_line_and_leaves_nothing(tmp_path):
    (tmp_path / "m.onnx").mkdir()  # the rename onto a folder fails after the data is written
    with pytest.raises(InferenceError, match=r"m\.onnx: cannot write \(Is a directory\)$") as failed:
        _save(identity_model(), tmp_path / "m.onnx")
    assert failed.value.exit_code == 1  # a failure during the work, not bad input
    assert [p.name for p in tmp_path.iterdir()] == ["m.onnx"] and (tmp_path / "m.onnx").is_dir()
    _save(identity_model(), tmp_path / "ok.onnx")
    assert onnx.load(str(tmp_path / "ok.onnx")).graph.node[0].op_type == "Identity"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx", "ok.onnx"]


def test_checkpoint_round_trip_is_atomic(tmp_path):
    cfg = ModelConfig(sizes=Sizes.preset("test"))
    model = build_model(cfg, seed=3)
    path = save_checkpoint(model, tmp_path / "runs" / "step1.pt", {"step": 1})
    assert sorted(p.name for p in path.parent.iterdir()) == ["step1.pt"]
    loaded = load_checkpoint(path)
    assert loaded.cfg.to_dict() == cfg.to_dict()
    for (name, a), (_, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert torch.equal(a, b), name
    # Saving again replaces the file; a failed write is one line and leaves the folder as it was.
    save_checkpoint(model, path, {"step": 2})
    assert torch.load(path, weights_only=True)["meta"] == {"step": 2}
    (tmp_path / "runs" / "dir.pt").mkdir()
    with pytest.raises(InferenceError, match=r"dir\.pt: cannot write the checkpoint") as failed:
        save_checkpoint(model, tmp_path / "runs" / "dir.pt")
    assert failed.value.exit_code == 1
    assert sorted(p.name for p in path.parent.iterdir()) == ["dir.pt", "step1.pt"]


def test_a_checkpoint_saved_before_a_renderer_setting_existed_computes_what_it_did(tmp_path):
    """Configurations record every key; one a checkpoint lacks was added later, and the model gets
    the value it was trained with (config.SAVED_BEFORE), not the new default."""
    cfg = ModelConfig.for_backbone("tiny", Sizes((64, 32), (128, 64), (160, 80)))
    model = build_model(cfg, seed=3)
    save_checkpoint(model, tmp_path / "new.pt")
    assert load_checkpoint(tmp_path / "new.pt").cfg.depth_init.zbuffer == "occlusion"
    data = torch.load(tmp_path / "new.pt", weights_only=True)
    del data["config"]["depth_init"]["zbuffer"]
    del data["config"]["stage2"]["visibility_ramp"]
    torch.save(data, tmp_path / "old.pt")
    old = load_checkpoint(tmp_path / "old.pt")
    assert (old.cfg.depth_init.zbuffer, old.cfg.stage2.visibility_ramp) == ("reference", 1.0)
    # a configuration a user writes gets today's defaults
    assert ModelConfig.from_dict({"depth_init": {"radius": 1}}).depth_init.zbuffer == "occlusion"


def test_a_checkpoint_whose_tensors_do_not_fit_its_configuration_is_one_line(tmp_path, capsys):
    from rig.cli import main

    model = build_model(ModelConfig(sizes=Sizes.preset("test")), seed=3)
    path = save_checkpoint(model, tmp_path / "damaged.pt")
    data = torch.load(path, weights_only=True)
    name = next(iter(data["state_dict"]))
    data["state_dict"][name] = torch.zeros(2, 2)  # another configuration's tensor, or a damaged one
    torch.save(data, path)
    with pytest.raises(InferenceError, match=r"damaged\.pt: the checkpoint's weights do not fit its model configuration \(size mismatch") as err:
        load_checkpoint(path)
    assert err.value.exit_code == 2 and "\n" not in str(err.value)
    assert main(["model", "export", "--checkpoint", str(path), "-o", str(tmp_path / "m.onnx")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "do not fit" in lines[0] and not (tmp_path / "m.onnx").exists()
