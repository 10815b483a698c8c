"""Where the trained model that ships with the product lives: the package data `inference/runtime/models`,
which in the source tree is a link to models/ at its top and in an installed wheel a copy of it
(pyproject.toml's package-data), so an installation that is not editable serves it too.

`models/splat-sap-preview.pt` is the checkpoint `rig train` wrote, `models/splat-sap-preview.onnx`
its export; `models/MODEL_CARD.md` says how it was trained and what it scores. The runtime, `rig
model export` and the demo use them when no model is named. `models/splat-sap-live.onnx` is the
same checkpoint exported at the `test` sizes (128x64 / 256x144 -> 320x180), what `rig live` runs on
a CPU by default (docs/live.md). Standard library only (the live path).
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

from inference.errors import InferenceError

# a folder on disk (ONNX Runtime opens a model, and the external weights beside it, by path); in the
# source tree the link resolves to models/ itself
MODELS = Path(str(resources.files("inference.runtime").joinpath("models"))).resolve()
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
