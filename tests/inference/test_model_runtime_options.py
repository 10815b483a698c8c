"""What the runtime hands ONNX Runtime: the model's metadata read from the file without a session,
and TensorRT's float16 switch set from the precision the model was exported in. No GPU is needed:
the provider options are plain values, checked before any provider sees them."""
from __future__ import annotations

import onnx
import onnxruntime as ort
import pytest

from inference.errors import InferenceError
from inference.runtime.metadata import read_file_metadata
from inference.runtime.pipeline import PREFERRED_PROVIDERS, model_precision, provider_options


def fp16_path(exported):
    return exported.path.with_name(exported.path.stem + ".fp16.onnx")


def small_model(path, metadata: dict[str, str]) -> None:
    g = onnx.helper.make_graph([onnx.helper.make_node("Identity", ["x"], ["y"])], "g",
                               [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
                               [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])])
    model = onnx.helper.make_model(g, ir_version=8, opset_imports=[onnx.helper.make_opsetid("", 18)])
    onnx.helper.set_model_props(model, metadata)
    onnx.save(model, path)


def test_file_metadata_is_what_onnx_and_onnx_runtime_read(tiny_onnx):
    for path in (tiny_onnx.path, fp16_path(tiny_onnx)):
        meta = read_file_metadata(path)
        assert meta == {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
        assert meta == ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
        assert meta["splat_sap.format"] == "1" and len(meta) == 6


def test_file_metadata_of_foreign_and_broken_files(tmp_path):
    small_model(tmp_path / "foreign.onnx", {})
    assert read_file_metadata(tmp_path / "foreign.onnx") == {}
    small_model(tmp_path / "tagged.onnx", {"a": "1", "ünïcode": "é"})
    assert read_file_metadata(tmp_path / "tagged.onnx") == {"a": "1", "ünïcode": "é"}
    (tmp_path / "torn.onnx").write_bytes(b"\x08\x07garbage")
    with pytest.raises(InferenceError, match="torn.onnx: not an ONNX model"):
        read_file_metadata(tmp_path / "torn.onnx")
    whole = (tmp_path / "tagged.onnx").read_bytes()
    (tmp_path / "cut.onnx").write_bytes(whole[:-3])  # the metadata entry runs past the end
    with pytest.raises(InferenceError, match="cut.onnx: not an ONNX model"):
        read_file_metadata(tmp_path / "cut.onnx")
    (tmp_path / "empty.onnx").write_bytes(b"")
    with pytest.raises(InferenceError, match="empty file"):
        read_file_metadata(tmp_path / "empty.onnx")
    with pytest.raises(InferenceError, match="missing.onnx: cannot read it"):
        read_file_metadata(tmp_path / "missing.onnx")


def test_tensorrt_runs_float16_only_for_a_model_exported_as_fp16(tiny_onnx):
    """An fp32 model's projections and z-buffer must stay float32 under TensorRT."""
    for path, precision, half in ((tiny_onnx.path, "fp32", "False"), (fp16_path(tiny_onnx), "fp16", "True")):
        assert model_precision(path) == precision
        trt, cuda, cpu = provider_options(list(PREFERRED_PROVIDERS), path, model_precision(path))
        name, options = trt
        assert name == "TensorrtExecutionProvider"
        assert options["trt_fp16_enable"] == half and options["trt_layer_norm_fp32_fallback"] == half
        assert options["trt_engine_cache_path"] == str(path) + ".trt-cache"  # one engine cache per file, so per precision
        assert (cuda, cpu) == ("CUDAExecutionProvider", "CPUExecutionProvider")
    assert provider_options(["CPUExecutionProvider"], tiny_onnx.path, "fp32") == ["CPUExecutionProvider"]


def test_precision_of_models_without_or_with_unknown_metadata(tmp_path):
    small_model(tmp_path / "foreign.onnx", {})
    assert model_precision(tmp_path / "foreign.onnx") == "fp32"  # never reduced precision by default
    small_model(tmp_path / "int8.onnx", {"splat_sap.precision": "int8"})
    with pytest.raises(InferenceError, match="unknown precision 'int8'"):
        model_precision(tmp_path / "int8.onnx")
    with pytest.raises(InferenceError, match="unknown model precision 'bf16'"):
        provider_options(["TensorrtExecutionProvider"], tmp_path / "int8.onnx", "bf16")
