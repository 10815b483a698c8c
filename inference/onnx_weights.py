"""Initializers kept out of the ONNX protos during an export, and written either back into each
model file or, above EXTERNAL_DATA_LIMIT, into one data file beside them (ONNX external data).

A protobuf message cannot exceed 2 GiB: a model with the MASt3R backbone (about 2.6 GB of float32
weights) cannot be one file, nor can onnx serialise it for shape inference or the checker. So the
export detaches every initializer of at least DETACH_MIN_BYTES right after tracing (`detach`): the
graph work (splitting, fp16 conversion) runs on light protos whose large initializers are external
references to a placeholder, and their values live once, in a `WeightStore`.

`write_models` then writes a set of models (the whole file and its parts, of one precision):
- at most EXTERNAL_DATA_LIMIT bytes of weights: each file self-contained, as before;
- above it: one data file `<M.onnx>.<digest>.data` beside `M.onnx` holding every tensor the set
  references once (4 KiB-aligned, so ONNX Runtime can map it), written atomically before the
  models, which reference it by that relative name (ONNX Runtime resolves it from the model's
  folder). The digest of its content in its name means a new export never overwrites the data an
  earlier model file still reads: an interrupted export leaves the earlier model whole. Once the
  set is written, data files of earlier exports to the same name are removed.
"""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np
import onnx
from google.protobuf.message import DecodeError
from onnx import TensorProto, numpy_helper

from common.files import atomic_path
from inference.errors import OutputError

EXTERNAL_DATA_LIMIT = 2_000_000_000  # bytes of weights above which a model keeps them in a data file
DETACH_MIN_BYTES = 1024
ALIGN = 4096
PLACEHOLDER = "__rig_detached__"
_DATA_NAME = re.compile(r"^(?P<model>.+\.onnx)\.[0-9a-f]{16}\.data$")


class WeightStore:
    """Detached initializer values by (name, ONNX element type)."""

    def __init__(self) -> None:
        self.arrays: dict[tuple[str, int], np.ndarray] = {}

    def value(self, init: TensorProto) -> np.ndarray:
        return self.arrays[(init.name, init.data_type)]

    def nbytes(self, model: onnx.ModelProto) -> int:
        return sum(self.value(i).nbytes for i in model.graph.initializer if is_detached(i))

    def to_float16(self, init: TensorProto) -> None:
        """Make the detached float32 initializer `init` float16 (the value converted once, kept beside the float32 one)."""
        key = (init.name, TensorProto.FLOAT16)
        if key not in self.arrays:
            self.arrays[key] = self.value(init).astype(np.float16)
        init.data_type = TensorProto.FLOAT16
        _set_external(init, PLACEHOLDER, 0, self.arrays[key].nbytes)


def is_detached(init: TensorProto) -> bool:
    return init.data_location == TensorProto.EXTERNAL and any(e.key == "location" and e.value == PLACEHOLDER for e in init.external_data)


def has_detached(model: onnx.ModelProto) -> bool:
    return any(is_detached(i) for i in model.graph.initializer)


def _set_external(init: TensorProto, location: str, offset: int, length: int) -> None:
    del init.external_data[:]
    for key, value in (("location", location), ("offset", str(offset)), ("length", str(length))):
        entry = init.external_data.add()
        entry.key = key
        entry.value = value
    init.data_location = TensorProto.EXTERNAL


def _clear_data(init: TensorProto) -> None:
    for name in ("raw_data", "float_data", "int32_data", "int64_data", "double_data", "uint64_data", "string_data"):
        init.ClearField(name)


def detach(model: onnx.ModelProto, store: WeightStore | None = None, min_bytes: int = DETACH_MIN_BYTES) -> WeightStore:
    """Move the values of initializers of at least `min_bytes` into `store` (in place)."""
    store = store or WeightStore()
    for init in model.graph.initializer:
        if init.data_location == TensorProto.EXTERNAL:
            continue
        arr = numpy_helper.to_array(init)
        if arr.nbytes < min_bytes:
            continue
        store.arrays[(init.name, init.data_type)] = arr
        _clear_data(init)
        _set_external(init, PLACEHOLDER, 0, arr.nbytes)
    return store


def attached(model: onnx.ModelProto, store: WeightStore) -> onnx.ModelProto:
    """A copy of `model` with every detached initializer's value back inside it."""
    out = onnx.ModelProto()
    out.CopyFrom(model)
    for init in out.graph.initializer:
        if is_detached(init):
            arr = store.value(init)
            del init.external_data[:]
            init.data_location = TensorProto.DEFAULT
            init.raw_data = np.ascontiguousarray(arr).astype(arr.dtype.newbyteorder("<"), copy=False).tobytes()
    return out


def data_files(path: Path) -> list[Path]:
    """The external-data files written for the model at `path` (this or earlier exports)."""
    return sorted(p for p in path.parent.glob(f"{path.name}.*.data") if _DATA_NAME.match(p.name))


def write_models(models: list[tuple[onnx.ModelProto, Path]], store: WeightStore, save, limit: int = EXTERNAL_DATA_LIMIT) -> Path | None:
    """Write each (model, path) of one set (the first is the whole file) with `save(proto, path)`.
    Returns the data file written, or None when every file is self-contained."""
    whole_path = models[0][1]
    if store.nbytes(models[0][0]) <= limit:
        for proto, target in models:
            save(attached(proto, store), target)
        _remove_stale(whole_path, keep=None)
        return None
    keys: list[tuple[str, int]] = []
    for proto, _ in models:
        for init in proto.graph.initializer:
            if is_detached(init) and (init.name, init.data_type) not in keys:
                keys.append((init.name, init.data_type))
    digest = hashlib.sha256()
    for key in keys:
        digest.update(f"{key[0]}\0{key[1]}\0".encode())
        digest.update(np.ascontiguousarray(store.arrays[key]).data)
    data_path = whole_path.with_name(f"{whole_path.name}.{digest.hexdigest()[:16]}.data")
    offsets: dict[tuple[str, int], tuple[int, int]] = {}
    try:
        with atomic_path(data_path) as tmp, open(tmp, "wb") as f:
            pos = 0
            for key in keys:
                pad = (-pos) % ALIGN
                f.write(b"\0" * pad)
                pos += pad
                buf = np.ascontiguousarray(store.arrays[key]).astype(store.arrays[key].dtype.newbyteorder("<"), copy=False).data
                f.write(buf)
                offsets[key] = (pos, buf.nbytes)
                pos += buf.nbytes
    except OSError as exc:
        raise OutputError(f"{data_path}: cannot write ({exc.strerror or exc})") from None
    for proto, target in models:
        out = onnx.ModelProto()
        out.CopyFrom(proto)
        for init in out.graph.initializer:
            if is_detached(init):
                offset, length = offsets[(init.name, init.data_type)]
                _set_external(init, data_path.name, offset, length)
        save(out, target)
        onnx.checker.check_model(str(target))  # by path: the references to the data file are checked too
    _remove_stale(whole_path, keep=data_path)
    return data_path


def _remove_stale(path: Path, keep: Path | None) -> None:
    for p in data_files(path):
        if keep is None or p.name != keep.name:
            try:
                p.unlink()
            except OSError:
                pass


def share_data(paths: list[Path], min_bytes: int = DETACH_MIN_BYTES) -> Path:
    """Rewrite the model files `paths` (a model and its parts, written by one export) so that their
    weights live once, in one data file beside the first: `<first.onnx>.<digest>.data`.

    The whole file and its parts hold the same weights, and the part without the scale search is a
    separate trace whose initializers have other names: tensors are matched by content (element
    type and bytes), not by name, so each value is stored once whatever the file and the name.
    The data file is written (atomically, its digest in its name) before any model is rewritten,
    and each model is replaced atomically: an interrupted run leaves every file readable. Earlier
    data files of these models are removed once all are rewritten. Returns the data file."""
    paths = [Path(p) for p in paths]
    protos = []
    for p in paths:
        try:
            protos.append(onnx.load(str(p)))  # external data of an earlier export is read in too
        except (OSError, DecodeError, ValueError) as exc:
            raise OutputError(f"{p}: cannot read the model ({exc})") from None
    values: dict[str, np.ndarray] = {}  # content key -> value, in first-seen order
    keys_of: list[list[tuple[TensorProto, str]]] = []
    for proto in protos:
        refs = []
        for init in proto.graph.initializer:
            arr = numpy_helper.to_array(init)
            if arr.nbytes < min_bytes:
                continue
            buf = np.ascontiguousarray(arr).astype(arr.dtype.newbyteorder("<"), copy=False)
            key = hashlib.sha256(f"{init.data_type}\0".encode() + buf.tobytes()).hexdigest()
            values.setdefault(key, buf)
            refs.append((init, key))
        keys_of.append(refs)
    digest = hashlib.sha256("".join(values).encode()).hexdigest()[:16]
    data_path = paths[0].with_name(f"{paths[0].name}.{digest}.data")
    offsets: dict[str, tuple[int, int]] = {}
    try:
        with atomic_path(data_path) as tmp, open(tmp, "wb") as f:
            pos = 0
            for key, buf in values.items():
                # a large tensor starts on a page, so ONNX Runtime can map it; a small one only
                # on 64 bytes, which spares most of the padding of a model of many small tensors
                align = ALIGN if buf.nbytes >= ALIGN else 64
                pad = (-pos) % align
                f.write(b"\0" * pad)
                pos += pad
                f.write(buf.data)
                offsets[key] = (pos, buf.nbytes)
                pos += buf.nbytes
    except OSError as exc:
        raise OutputError(f"{data_path}: cannot write ({exc.strerror or exc})") from None
    for proto, refs, target in zip(protos, keys_of, paths):
        for init, key in refs:
            _clear_data(init)
            _set_external(init, data_path.name, *offsets[key])
        try:
            with atomic_path(target) as tmp:
                onnx.save_model(proto, str(tmp), save_as_external_data=False)
        except OSError as exc:
            raise OutputError(f"{target}: cannot write ({exc.strerror or exc})") from None
        onnx.checker.check_model(str(target))
    for target in paths:
        _remove_stale(target, keep=data_path)
    return data_path
