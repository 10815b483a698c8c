"""Model checkpoints (torch) and the record of where a model's weights came from.

A checkpoint is one torch file: {"format": "splat-sap", "version": 1, "config": ModelConfig dict,
"state_dict": ..., "meta": {...}}. An exported ONNX file records its weights' source as JSON in
its metadata ("splat_sap.weights"): {"source": "seed", "seed": 0} for an untrained model (torch
rebuilds the same weights from the seed) or {"source": "checkpoint", "path": ..., "sha256": ...}.
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


def load_checkpoint(path: str | os.PathLike) -> SplatSAP:
    path = Path(path)
    data = read_checkpoint(path)
    cfg = ModelConfig.from_dict(data["config"])
    model = build_model(cfg, seed=None)
    missing, unexpected = model.load_state_dict(data["state_dict"], strict=False)
    if missing or unexpected:
        raise InferenceError(f"{path}: checkpoint does not match its configuration (missing {missing[:3]}, unexpected {unexpected[:3]})")
    return model.eval()


def seed_record(seed: int) -> str:
    return json.dumps({"source": "seed", "seed": int(seed)})


def checkpoint_record(path: str | os.PathLike) -> str:
    path = Path(path).resolve()
    return json.dumps({"source": "checkpoint", "path": str(path), "sha256": file_digest(path)})


def model_from_record(cfg: ModelConfig, record: str, checkpoint: str | os.PathLike | None = None) -> SplatSAP:
    """Rebuild the torch model an ONNX file was exported from (`checkpoint` overrides the recorded path)."""
    try:
        rec = json.loads(record)
    except json.JSONDecodeError:
        raise InferenceError("the model's weights record is not valid JSON; export it again with `rig model export`") from None
    if checkpoint is None and rec.get("source") == "seed":
        return build_model(cfg, seed=int(rec.get("seed", 0)))
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
        raise InferenceError(f"{checkpoint}: its configuration differs from the ONNX model's")
    return model
