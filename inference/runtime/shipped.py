"""Where the trained model that ships with the product lives (models/ at the top of the source tree).

`models/splat-sap-preview.pt` is the checkpoint `rig train` wrote, `models/splat-sap-preview.onnx`
its export; `models/MODEL_CARD.md` says how it was trained and what it scores. The runtime, `rig
model export` and the demo use them when no model is named. `models/splat-sap-live.onnx` is the
same checkpoint exported at the `test` sizes (128x64 / 256x144 -> 320x180), what `rig live` runs on
a CPU by default (docs/live.md). Standard library only (the live path).
"""
from __future__ import annotations

from pathlib import Path

from inference.errors import InferenceError

MODELS = Path(__file__).resolve().parents[2] / "models"
NAME = "splat-sap-preview"
LIVE_NAME = "splat-sap-live"  # `rig model export --checkpoint models/splat-sap-preview.pt --size test -o models/splat-sap-live.onnx`


def shipped_checkpoint() -> Path:
    return _existing(MODELS / f"{NAME}.pt")


def shipped_onnx() -> Path:
    return _existing(MODELS / f"{NAME}.onnx")


def shipped_live_onnx() -> Path:
    """The shipped model at the CPU live size (the preview model where an installation lacks it)."""
    live = MODELS / f"{LIVE_NAME}.onnx"
    return live if live.is_file() else shipped_onnx()


def _existing(path: Path) -> Path:
    if not path.is_file():
        raise InferenceError(f"{path}: the shipped model is missing from this installation; name a model "
                             f"(`rig model export --checkpoint CKPT -o model.onnx`, from `rig train`)")
    return path
