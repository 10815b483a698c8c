"""An ONNX file's metadata (`metadata_props`), read without the onnx package and without a session.

The runtime must choose its execution providers' options (TensorRT's float16 switch) from the
model's metadata before it opens the session, and the live path has neither torch nor onnx. A
session opened just to read the metadata would cost a second model load and fails outright on an
ONNX Runtime without float16 CPU kernels, so this reads the one field straight from the protobuf
wire format: ModelProto field 14, `repeated StringStringEntryProto metadata_props`, whose entries
are {1: key, 2: value}. Every other field (the graph with its weights) is skipped by its length,
and the file is memory-mapped, so the weights are never read.
"""
from __future__ import annotations

import mmap
import os
from pathlib import Path

from inference.errors import InferenceError

_METADATA_PROPS = 14  # ModelProto.metadata_props
_KEY, _VALUE = 1, 2  # StringStringEntryProto.key, .value
_VARINT, _FIXED64, _LENGTH, _FIXED32 = 0, 1, 2, 5


class _Malformed(ValueError):
    pass


def _varint(buf, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if pos >= len(buf) or shift > 63:
            raise _Malformed("truncated varint")
        byte = buf[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7


def _fields(buf, start: int, end: int):
    """(field number, wire type, payload start, payload end) of each field in buf[start:end]."""
    pos = start
    while pos < end:
        tag, pos = _varint(buf, pos)
        number, wire = tag >> 3, tag & 7
        if wire == _VARINT:
            _, nxt = _varint(buf, pos)
        elif wire == _FIXED64:
            nxt = pos + 8
        elif wire == _FIXED32:
            nxt = pos + 4
        elif wire == _LENGTH:
            size, pos = _varint(buf, pos)
            nxt = pos + size
        else:  # groups (3, 4) are not used by ONNX; anything else is not protobuf
            raise _Malformed(f"wire type {wire}")
        if nxt > end:
            raise _Malformed("field runs past the end")
        yield number, wire, pos, nxt
        pos = nxt


def read_file_metadata(path: str | os.PathLike) -> dict[str, str]:
    """The model's metadata_props as a dict; {} when it has none. Raises InferenceError."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                raise InferenceError(f"{path}: empty file, not an ONNX model")
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
                return _metadata_props(buf)
    except OSError as exc:
        raise InferenceError(f"{path}: cannot read it ({exc.strerror})") from None
    except (_Malformed, UnicodeDecodeError) as exc:
        raise InferenceError(f"{path}: not an ONNX model ({exc})") from None


def _metadata_props(buf) -> dict[str, str]:
    out = {}
    for number, wire, start, end in _fields(buf, 0, len(buf)):
        if number != _METADATA_PROPS or wire != _LENGTH:
            continue
        key = value = ""
        for sub, sub_wire, s, e in _fields(buf, start, end):
            if sub_wire == _LENGTH and sub in (_KEY, _VALUE):
                text = bytes(buf[s:e]).decode("utf-8")
                key, value = (text, value) if sub == _KEY else (key, text)
        out[key] = value
    return out
