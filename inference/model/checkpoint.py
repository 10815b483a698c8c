"""Model checkpoints (torch) and the record of where a model's weights came from.

A checkpoint is one torch file: {"format": "splat-sap", "version": 1, "config": ModelConfig dict,
"state_dict": ..., "meta": {...}}. An exported ONNX file records its weights' source as JSON in
its metadata ("splat_sap.weights"): {"source": "seed", "seed": 0} for an untrained model (torch
rebuilds the same weights from the seed) or {"source": "checkpoint", "path": ..., "sha256": ...}.
An untrained model whose MASt3R backbone was loaded from the user's weights file adds
"backbone_weights": {"path": ..., "sha256": ...} (the file is read again, never copied).
`rig model check` uses that record to rebuild the torch model it compares ONNX Runtime with.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch

from common.files import atomic_path
from inference.config import ModelConfig
from inference.errors import InferenceError, OutputError
from inference.model.mast3r_weights import MASt3RWeights, backbone_net, load_into, read_weights
from inference.model.pipeline import SplatSAP, build_model

FORMAT = "splat-sap"
VERSION = 1


def file_digest(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def save_checkpoint(model: SplatSAP, path: str | os.PathLike, meta: dict | None = None) -> Path:
    """Write atomically (a crash while saving leaves the previous checkpoint, never a torn one)."""
    path = Path(path)
    data = {"format": FORMAT, "version": VERSION, "config": model.cfg.to_dict(), "state_dict": model.state_dict(), "meta": meta or {}}
    try:
        with atomic_path(path, make_parents=True) as tmp:
            torch.save(data, tmp)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write the checkpoint ({exc.strerror or exc})") from None
    return path


def read_checkpoint(path: str | os.PathLike) -> dict:
    """The checkpoint file's contents (tensors on the CPU), checked to be a Splat-SAP checkpoint of this version."""
    path = Path(path)
    if not path.is_file():
        raise InferenceError(f"{path}: no such checkpoint")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for truncated or foreign files
        raise InferenceError(f"{path}: not a readable checkpoint ({type(exc).__name__})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InferenceError(f"{path}: not a Splat-SAP checkpoint")
    if data.get("version") != VERSION:
        raise InferenceError(f"{path}: checkpoint version {data.get('version')!r} is not supported (this program reads {VERSION})")
    return data


def load_weights(model: torch.nn.Module, state_dict, path: str | os.PathLike, strict: bool = True):
    """`model.load_state_dict`, a checkpoint whose tensors do not fit the model (another
    configuration's, or damaged) said in one line. Returns (missing, unexpected) keys."""
    if not isinstance(state_dict, dict) or not all(isinstance(v, torch.Tensor) for v in state_dict.values()):
        raise InferenceError(f"{path}: the checkpoint's weights are not a table of tensors (a damaged file?)")
    try:
        return model.load_state_dict(state_dict, strict=strict)
    except RuntimeError as exc:
        why = next((ln.strip() for ln in str(exc).splitlines() if "size mismatch" in ln or "Missing" in ln or "Unexpected" in ln),
                   str(exc).splitlines()[0])
        raise InferenceError(f"{path}: the checkpoint's weights do not fit its model configuration ({why[:200]})") from None


def load_checkpoint(path: str | os.PathLike) -> SplatSAP:
    path = Path(path)
    data = read_checkpoint(path)
    cfg = ModelConfig.from_dict(data["config"], saved=True)
    model = build_model(cfg, seed=None)
    missing, unexpected = load_weights(model, data.get("state_dict"), path, strict=False)
    if missing or unexpected:
        raise InferenceError(f"{path}: checkpoint does not match its configuration (missing {missing[:3]}, unexpected {unexpected[:3]})")
    return model.eval()


def seed_record(seed: int, backbone_weights: dict | None = None) -> str:
    rec = {"source": "seed", "seed": int(seed)}
    if backbone_weights:
        rec["backbone_weights"] = backbone_weights
    return json.dumps(rec)


def backbone_weights_record(path: str | os.PathLike) -> dict:
    """Where a model's MASt3R weights came from (the user's file: recorded, never copied)."""
    path = Path(path).resolve()
    return {"path": str(path), "sha256": file_digest(path)}


def configure_for_weights(cfg: ModelConfig, weights: MASt3RWeights) -> ModelConfig:
    """A copy of `cfg` with the MASt3R depths the weights' file records."""
    cfg = ModelConfig.from_dict(cfg.to_dict())
    if cfg.backbone.kind != "mast3r":
        raise InferenceError(f"--weights loads MASt3R weights, but the model's backbone is {cfg.backbone.kind}")
    cfg.backbone.mast3r_encoder_blocks = weights.arch.encoder_blocks
    cfg.backbone.mast3r_decoder_blocks = weights.arch.decoder_blocks
    return cfg


def build_with_weights(cfg: ModelConfig, weights_path: str | os.PathLike, seed: int | None = 0) -> tuple[SplatSAP, MASt3RWeights]:
    """An untrained model (seeded) whose MASt3R backbone holds the weights of `weights_path`,
    at the depths that file records. One-line InferenceError for a bad file."""
    weights = read_weights(weights_path)
    model = build_model(configure_for_weights(cfg, weights), seed=seed)
    load_into(backbone_net(model), weights)
    return model, weights


def load_backbone_weights(model: SplatSAP, weights_path: str | os.PathLike) -> MASt3RWeights:
    """Replace the MASt3R backbone's weights of `model` by those of the file (same depths)."""
    weights = read_weights(weights_path)
    load_into(backbone_net(model), weights)
    return weights


def checkpoint_record(path: str | os.PathLike) -> str:
    path = Path(path).resolve()
    return json.dumps({"source": "checkpoint", "path": str(path), "sha256": file_digest(path)})


def model_from_record(cfg: ModelConfig, record: str, checkpoint: str | os.PathLike | None = None,
                      weights: str | os.PathLike | None = None) -> SplatSAP:
    """Rebuild the torch model an ONNX file was exported from (`checkpoint` overrides the recorded
    path; `weights` the recorded MASt3R weights file)."""
    try:
        rec = json.loads(record)
    except json.JSONDecodeError:
        raise InferenceError("the model's weights record is not valid JSON; export it again with `rig model export`") from None
    if checkpoint is None and rec.get("source") == "seed":
        model = build_model(cfg, seed=int(rec.get("seed", 0)))
        backbone = rec.get("backbone_weights") or {}
        if backbone or weights is not None:
            path = weights if weights is not None else backbone.get("path")
            if not path or not Path(path).is_file():
                raise InferenceError(f"the model was exported with the MASt3R weights {path}, which are not here: pass --weights")
            if backbone.get("sha256") and file_digest(path) != backbone["sha256"]:
                raise InferenceError(f"{path}: not the MASt3R weights the model was exported with (sha256 differs)")
            load_backbone_weights(model, path)
        return model
    if weights is not None:
        raise InferenceError("--weights: the model was exported from a checkpoint, which holds its backbone's weights")
    if checkpoint is None and rec.get("source") == "checkpoint":
        checkpoint = rec.get("path")
        if (not checkpoint or not Path(checkpoint).is_file()) and rec.get("sha256"):
            # Exported on another machine: the shipped checkpoint, if it is the one (same digest).
            from inference.runtime.shipped import MODELS, NAME

            shipped = MODELS / f"{NAME}.pt"
            if shipped.is_file() and file_digest(shipped) == rec["sha256"]:
                checkpoint = str(shipped)
        if not checkpoint or not Path(checkpoint).is_file():
            raise InferenceError(f"the model was exported from checkpoint {checkpoint}, which is not here: pass --checkpoint")
    if checkpoint is None:
        raise InferenceError(f"unknown weights source {rec.get('source')!r}: pass --checkpoint")
    if rec.get("sha256") and file_digest(checkpoint) != rec["sha256"]:
        raise InferenceError(f"{checkpoint}: not the checkpoint the model was exported from (sha256 differs)")
    model = load_checkpoint(checkpoint)
    if model.cfg.to_dict() != cfg.to_dict():
        if {**model.cfg.to_dict(), "sizes": None} != {**cfg.to_dict(), "sizes": None}:
            raise InferenceError(f"{checkpoint}: its configuration differs from the ONNX model's")
        # Exported at other sizes (`rig model export --checkpoint C --size S`, the CPU live model):
        # the same weights built at the export's sizes, none of them depends on the sizes.
        resized = build_model(cfg, seed=None)
        load_weights(resized, model.state_dict(), checkpoint, strict=True)
        model = resized.eval()
    return model
