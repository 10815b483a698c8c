"""A model and its parts with their weights once, in one data file beside them (`rig model export
--shared-data`, inference.onnx_weights.share_data): what the shipped models are stored as."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from inference.onnx_weights import data_files, share_data

REPO = Path(__file__).resolve().parents[2]
MODELS = REPO / "models"
MODELS_LIMIT = 25_000_000  # bytes: what the repository (and the wheel) carries for the shipped model


def _family(path: Path) -> list[Path]:
    """The fp32 file and its parts (M.onnx, M.stage1.onnx, M.view.onnx, ...), whole file first."""
    return [path] + sorted(p for p in path.parent.glob(f"{path.stem}.*.onnx") if ".fp16" not in p.name)


def _external_locations(path: Path) -> set[str]:
    proto = onnx.load(str(path), load_external_data=False)
    return {e.value for i in proto.graph.initializer if i.data_location == onnx.TensorProto.EXTERNAL
            for e in i.external_data if e.key == "location"}


def _outputs(path: Path, seed: int = 0) -> list[np.ndarray]:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(seed)
    feeds = {}
    for i in session.get_inputs():
        shape = [d if isinstance(d, int) else 1 for d in i.shape]
        feeds[i.name] = rng.random(shape).astype(np.float32)
    return session.run(None, feeds)


def test_sharing_stores_each_weight_once_and_computes_the_same(tiny_onnx, tmp_path):
    src = _family(tiny_onnx.path)
    assert len(src) >= 3 and not any(_external_locations(p) for p in src), "the fixture's files are self-contained"
    work = tmp_path / "m"
    work.mkdir()
    copies = [Path(shutil.copy(p, work / p.name)) for p in src]
    data = share_data(copies)
    assert data_files(copies[0]) == [data]
    for p in copies:
        assert _external_locations(p) == {data.name}
        onnx.checker.check_model(str(p))
    before = sum(p.stat().st_size for p in src)
    after = sum(p.stat().st_size for p in copies) + data.stat().st_size
    assert after < 0.6 * before, (before, after)  # the whole file and both parts held the same weights
    for original, shared in zip(src, copies):
        for a, b in zip(_outputs(original), _outputs(shared)):
            np.testing.assert_array_equal(a, b)
    # shared again (a new export to the same name): one data file is left, the models read it
    again = share_data(copies)
    assert again == data and list(work.glob("*.data")) == [data]


def test_the_oracle_export_with_shared_data_is_one_data_file(oracle_onnx):
    family = _family(oracle_onnx.path)
    files = data_files(oracle_onnx.path)
    assert len(files) == 1 and _external_locations(oracle_onnx.path) == {files[0].name}
    assert all(_external_locations(p) <= {files[0].name} for p in family)  # a part may hold no large weight


def test_the_shipped_models_share_their_weights_and_fit_the_limit():
    if not MODELS.is_dir():
        pytest.skip(f"{MODELS} is absent from this installation")
    total = sum(p.stat().st_size for p in MODELS.rglob("*") if p.is_file())
    assert total <= MODELS_LIMIT, f"models/ holds {total / 1e6:.1f} MB"
    wholes = [p for p in MODELS.glob("*.onnx") if p.stem.count(".") == 0]
    assert wholes
    for whole in wholes:
        data = data_files(whole)
        assert len(data) == 1, f"{whole.name}: {len(data)} data files"
        for p in _family(whole):
            assert _external_locations(p) == {data[0].name}, p.name
    referenced = {d.name for w in wholes for d in data_files(w)}
    assert {p.name for p in MODELS.glob("*.data")} == referenced, "a data file no model reads"
