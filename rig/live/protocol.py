"""The live server's wire format (WebSocket `/ws`).

Server -> browser, binary: one rendered frame = a fixed little-endian header, then the JPEG bytes.

    offset size  field
    0      4     magic        b"RLVF"
    4      2     version      uint16, 1
    6      2     header_len   uint16, bytes before the JPEG (32 in version 1)
    8      8     set_index    uint64, the frame set the view was rendered from
    16     4     viewpoint_id uint32, the viewpoint it shows (as `Viewer.set_viewpoint` returned)
    20     4     flags        uint32, 0 (reserved)
    24     8     capture_ns   int64, when the frames were exposed (host monotonic clock, time.monotonic_ns())
    32     ...   JPEG

A reader finds the JPEG at `header_len`, so later versions may append fields to the header without
breaking older readers; `version` changes only for an incompatible layout, which readers reject.

Server -> browser, text: JSON objects with a "type":
    {"type": "hello", "viewer": id, "presets": [...], "protocol": 1}       once, at connect
    {"type": "status", ...engine.status(), "viewer": id}                  about twice a second
    {"type": "viewpoint", "viewpoint": id, "seq": n}                     a viewpoint message applied
    {"type": "error", "message": "...", "seq": n}                        a message was refused

Browser -> server, text only (a binary message is refused), at most MAX_MESSAGE_BYTES:
    {"type": "viewpoint", ...}          passed whole to `Viewer.set_viewpoint`, which checks the fields
    {"type": "ack", "set": int, "viewpoint": int}   the frame (set, viewpoint) was drawn
Either may carry "seq": an integer the reply to it echoes (so a page knows which of its viewpoint
messages a reply answers); the server takes it off before the engine sees the message.

`parse_client_message` checks the envelope (a JSON object of a known type, numbers finite and
within range, no NaN/Infinity, size) and raises ProtocolError with a one-line reason.
"""
from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from typing import Any, Optional

from rig.live.api import LiveFrame

MAGIC = b"RLVF"
VERSION = 1
HEADER = struct.Struct("<4sHHQIIq")
HEADER_LEN = HEADER.size  # 32
MAX_MESSAGE_BYTES = 4096
MAX_INT = 2 ** 53  # numbers a browser's JSON (IEEE doubles) keeps exactly
MAX_DEPTH = 8  # nesting of a viewpoint message
MESSAGE_TYPES = ("viewpoint", "ack")


class ProtocolError(ValueError):
    """A malformed message; the text is the one-line reason sent back to the client (with the
    message's "seq" when it had a valid one)."""

    def __init__(self, reason: str, seq: Optional[int] = None):
        super().__init__(reason)
        self.seq = seq


# --- frames (server -> browser) ----------------------------------------------------------------------
def pack_frame(frame: LiveFrame) -> bytes:
    """Header + JPEG of one frame, as sent in one binary WebSocket message."""
    if not 0 <= frame.set_index < 2 ** 64:
        raise ValueError(f"set index out of range: {frame.set_index}")
    if not 0 <= frame.viewpoint_id < 2 ** 32:
        raise ValueError(f"viewpoint id out of range: {frame.viewpoint_id}")
    if not -(2 ** 63) <= frame.capture_ns < 2 ** 63:
        raise ValueError(f"capture time out of range: {frame.capture_ns}")
    head = HEADER.pack(MAGIC, VERSION, HEADER_LEN, frame.set_index, frame.viewpoint_id, 0, frame.capture_ns)
    return head + bytes(frame.jpeg)


def unpack_frame(data: bytes) -> LiveFrame:
    """The frame in one binary message (the inverse of pack_frame); ProtocolError if it is not one."""
    if len(data) < HEADER_LEN:
        raise ProtocolError(f"frame message too short: {len(data)} bytes, the header alone is {HEADER_LEN}")
    magic, version, header_len, set_index, viewpoint_id, _flags, capture_ns = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(f"not a frame message (magic {magic!r}, expected {MAGIC!r})")
    if version != VERSION:
        raise ProtocolError(f"frame message version {version} is not supported (this reader knows {VERSION})")
    if not HEADER_LEN <= header_len <= len(data):
        raise ProtocolError(f"bad header length {header_len} in a {len(data)}-byte frame message")
    return LiveFrame(set_index=set_index, viewpoint_id=viewpoint_id, capture_ns=capture_ns, jpeg=bytes(data[header_len:]))


# --- JSON (both ways) ----------------------------------------------------------------------------------
def jsonable(value: Any) -> Any:
    """`value` with what JSON cannot carry made safe: NaN and infinities become None (a browser's
    JSON.parse rejects them), numpy scalars and arrays become Python numbers and lists, tuples lists."""
    if value is None or isinstance(value, (bool, str, int)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if hasattr(value, "tolist"):  # numpy arrays and scalars, without importing numpy here
        return jsonable(value.tolist())
    if hasattr(value, "item"):
        return jsonable(value.item())
    return str(value)


def encode(message: dict) -> str:
    return json.dumps(jsonable(message), allow_nan=False, separators=(",", ":"))


def hello_message(viewer_id: int, presets: list) -> str:
    return encode({"type": "hello", "viewer": viewer_id, "presets": presets, "protocol": VERSION})


def status_message(status: dict, viewer_id: Optional[int] = None) -> str:
    msg = {**status, "type": "status"}
    if viewer_id is not None:
        msg["viewer"] = viewer_id
    return encode(msg)


def viewpoint_reply(viewpoint_id: int, seq: Optional[int] = None) -> str:
    msg = {"type": "viewpoint", "viewpoint": viewpoint_id}
    if seq is not None:
        msg["seq"] = seq
    return encode(msg)


def error_message(text: str, seq: Optional[int] = None) -> str:
    msg = {"type": "error", "message": str(text)[:300]}
    if seq is not None:
        msg["seq"] = seq
    return encode(msg)


# --- browser -> server -----------------------------------------------------------------------------
@dataclass(frozen=True)
class Viewpoint:
    message: dict  # the message for Viewer.set_viewpoint ("seq" taken off)
    seq: Optional[int] = None


@dataclass(frozen=True)
class Ack:
    set_index: int
    viewpoint_id: int
    seq: Optional[int] = None


def _reject_constant(name: str):
    raise ProtocolError(f"{name} is not a number JSON allows")


def _check_values(value: Any, where: str, depth: int = 0) -> None:
    if depth > MAX_DEPTH:
        raise ProtocolError(f"message nested deeper than {MAX_DEPTH} levels")
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return
    if isinstance(value, int):
        if not -MAX_INT <= value <= MAX_INT:
            raise ProtocolError(f"{where}: number out of range")
        return
    if isinstance(value, float):
        if not math.isfinite(value):  # 1e999 parses as inf
            raise ProtocolError(f"{where}: number out of range")
        return
    if isinstance(value, list):
        for i, v in enumerate(value):
            _check_values(v, f"{where}[{i}]", depth + 1)
        return
    if isinstance(value, dict):
        for k, v in value.items():
            _check_values(v, f"{where}.{k}" if where else k, depth + 1)
        return
    raise ProtocolError(f"{where}: unexpected value")  # json.loads makes nothing else


def _index(msg: dict, key: str, limit: int, seq: Optional[int] = None) -> int:
    kind = msg.get("type")
    if key not in msg:
        raise ProtocolError(f"{kind}: '{key}' is missing", seq)
    v = msg[key]
    if isinstance(v, float) and v.is_integer():
        v = int(v)  # 3.0 from a browser is 3
    if isinstance(v, bool) or not isinstance(v, int):
        raise ProtocolError(f"{kind}: '{key}' must be an integer", seq)
    if not 0 <= v < limit:
        raise ProtocolError(f"{kind}: '{key}' out of range", seq)
    return v


def parse_client_message(data: str | bytes | None) -> Viewpoint | Ack:
    """A browser's message, envelope checked; ProtocolError (one line) if it is malformed."""
    if not isinstance(data, str):
        raise ProtocolError("binary messages are not accepted (send JSON text)")
    if len(data) > MAX_MESSAGE_BYTES or len(data.encode("utf-8", "surrogatepass")) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message too long (at most {MAX_MESSAGE_BYTES} bytes)")
    try:
        msg = json.loads(data, parse_constant=_reject_constant)
    except ProtocolError:
        raise
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, int too long, nesting
        raise ProtocolError(f"not JSON: {str(exc).splitlines()[0][:120]}") from None
    if not isinstance(msg, dict):
        raise ProtocolError("a message must be a JSON object")
    seq = msg.get("seq")
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq <= MAX_INT:
        seq = None  # (a bad one is refused below, without an echo)
    kind = msg.get("type")
    if not isinstance(kind, str) or kind not in MESSAGE_TYPES:
        shown = kind[:40] if isinstance(kind, str) else kind if isinstance(kind, (int, float, bool, type(None))) else type(kind).__name__
        raise ProtocolError(f"unknown message type {shown!r} (known: {', '.join(MESSAGE_TYPES)})", seq)
    try:
        _check_values(msg, "")
    except ProtocolError as exc:
        raise ProtocolError(str(exc), seq) from None
    if "seq" in msg:
        _index(msg, "seq", MAX_INT + 1)
        msg = {k: v for k, v in msg.items() if k != "seq"}
    if kind == "ack":
        extra = sorted(set(msg) - {"type", "set", "viewpoint"})
        if extra:
            raise ProtocolError(f"ack: unknown field {extra[0][:40]!r}", seq)
        return Ack(_index(msg, "set", 2 ** 64, seq), _index(msg, "viewpoint", 2 ** 32, seq), seq)
    return Viewpoint(msg, seq)
