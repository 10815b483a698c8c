"""Bad input to the model-side commands (rig model, rig train): one line on stderr, exit 2, nothing
written. Found by trying them as a user would (trial-model)."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig

LIVE = REPO / "models" / "splat-sap-live.onnx"


def _copy_model(dst: Path) -> Path:
    """The shipped live model and its parts and data file, copied together."""
    for f in LIVE.resolve().parent.glob(LIVE.name.replace(".onnx", ".*")):
        shutil.copy(f, dst / f.name)
    return dst / LIVE.name


def test_model_with_its_data_file_cut_short_is_one_line(tmp_path):
    # ONNX Runtime printed its own multi-line error log before the one line
    model = _copy_model(tmp_path)
    (data,) = tmp_path.glob(LIVE.name + ".*.data")
    with open(data, "r+b") as f:
        f.truncate(data.stat().st_size // 2)
    proc = run_rig("model", "check", model)
    assert_one_line_error(proc, str(model), data.name, "shorter than the model needs")
