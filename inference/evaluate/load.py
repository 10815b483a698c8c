"""The model `rig model eval` measures: a checkpoint, the checkpoint an ONNX export records, or the
untrained pipeline on pretrained MASt3R weights."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from inference.errors import InferenceError


def model_to_evaluate(model_path: Optional[Path], *, weights: Optional[str] = None, size: str = "paper"):
    """The torch model of `model_path` (.pt, or an .onnx export whose recorded checkpoint is used,
    with `weights` for an export made with MASt3R weights), or with `model_path` None the untrained
    pipeline on the MASt3R backbone of `weights` at the `size` preset. An oracle model is refused: it
    reads ground-truth depth."""
    from inference.model.checkpoint import build_with_weights, load_checkpoint, model_from_record

    if model_path is None:
        from inference.config import ModelConfig, Sizes

        model, _ = build_with_weights(ModelConfig.for_backbone("mast3r", Sizes.preset(size)), weights)
        model_path = Path(weights)
    elif model_path.suffix == ".onnx":
        from inference.config import ModelConfig
        from inference.runtime.metadata import read_file_metadata

        meta = read_file_metadata(model_path)
        model = model_from_record(ModelConfig.from_json(meta["splat_sap.config"], saved=True), meta["splat_sap.weights"], weights=weights)
    else:
        if weights is not None:
            raise InferenceError("--weights: a checkpoint holds its backbone's weights already; give one of them")
        model = load_checkpoint(model_path)
    if model.needs_depth:
        raise InferenceError(f"{model_path}: an oracle model reads ground-truth depth; evaluate a trained model")
    return model
