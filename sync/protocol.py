"""The trigger-board line protocol: message table, checksum, formatter and a parser that never raises.

Every line is `BODY*CCCC` followed by a newline, where BODY is a message keyword and its arguments
separated by single spaces and CCCC is the CRC-16/CCITT-FALSE of BODY in hex. The full description
is `sync/PROTOCOL.md`; the firmware (`sync/firmware/`) and the emulator implement the same table, and
`sync/protocol_vectors.json` holds the test vectors all three must pass.

Run `python -m sync.protocol TIME 7` to print a line with its checksum (for a serial terminal).
"""
from __future__ import annotations

import re
import sys
from dataclasses import dataclass, field
from typing import Callable, Optional, Union

PROTOCOL_VERSION = 1
MAX_LINE = 100  # characters, checksum included, newline excluded (the firmware's buffer size)
MAX_WORD = 24
U64_MAX = 2**64 - 1

HOST = "host"  # lines the host sends to the board
BOARD = "board"  # lines the board sends to the host

# kind -> argument names; a name ending in ':w' is a word ([A-Za-z0-9._-]), any other an unsigned integer.
MESSAGES: dict[str, dict[str, tuple[str, ...]]] = {
    HOST: {
        "HELLO": ("n",),
        "RATE": ("n", "rate_mhz", "width_us"),
        "START": ("n", "count"),
        "STOP": ("n",),
        "TIME": ("n",),
        "FLASH": ("n", "ms"),
        "STATUS": ("n",),
    },
    BOARD: {
        "ID": ("n", "proto", "fw:w", "board:w"),
        "OK": ("n",),
        "ERR": ("n", "code:w"),
        "TIME": ("n", "board_us"),
        "PULSE": ("index", "board_us"),
        "FLASH": ("board_us", "ms"),
        "STATUS": ("n", "running", "rate_mhz", "width_us", "pulses", "errors"),
        "DONE": ("pulses",),
        "BOOT": ("proto", "fw:w", "board:w"),
    },
}

# Error codes the board puts in `ERR n CODE` (n = 0 when the line it refers to could not be read).
ERROR_CODES = ("CHECKSUM", "SYNTAX", "UNKNOWN", "ARGS", "LENGTH", "RANGE", "BUSY", "OVERRUN")

# Why a line was rejected; the parser's counters are keyed by these.
REJECTIONS = ("length", "checksum", "syntax", "unknown", "args")

_WORD = re.compile(r"[A-Za-z0-9._-]{1,%d}" % MAX_WORD)
_KIND = re.compile(r"[A-Z]{1,16}")
_HEX_DIGITS = frozenset(b"0123456789ABCDEF")  # upper case only: a flipped bit 5 must not pass
_UINT = re.compile(r"0|[1-9][0-9]{0,19}")

Arg = Union[int, str]


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        table.append(crc)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor); '123456789' -> 0x29B1."""
    crc = 0xFFFF
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ byte]
    return crc


@dataclass(frozen=True)
class Message:
    """One parsed line: `kind` and its arguments by name (integers, or strings for words)."""

    kind: str
    args: tuple[Arg, ...]
    direction: str

    def __getitem__(self, name: str) -> Arg:
        names = [a.split(":")[0] for a in MESSAGES[self.direction][self.kind]]
        return self.args[names.index(name)]

    def get(self, name: str, default=None):
        try:
            return self[name]
        except ValueError:
            return default


class ProtocolError(ValueError):
    """A line that is not a valid message; `reason` is one of REJECTIONS."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


def format_line(kind: str, *args: Arg, direction: str) -> str:
    """The wire form of a message (without the newline). Raises ValueError for an invalid message."""
    spec = MESSAGES[direction].get(kind)
    if spec is None:
        raise ValueError(f"{kind}: not a {direction} message (known: {', '.join(MESSAGES[direction])})")
    if len(args) != len(spec):
        raise ValueError(f"{kind}: takes {len(spec)} arguments ({' '.join(spec)}), got {len(args)}")
    parts = [kind]
    for name, value in zip(spec, args):
        if name.endswith(":w"):
            if not isinstance(value, str) or not _WORD.fullmatch(value):
                raise ValueError(f"{kind}.{name[:-2]}: must be a word of 1-{MAX_WORD} of [A-Za-z0-9._-], got {value!r}")
            parts.append(value)
        else:
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= U64_MAX:
                raise ValueError(f"{kind}.{name}: must be an integer in 0..2^64-1, got {value!r}")
            parts.append(str(value))
    body = " ".join(parts)
    line = f"{body}*{crc16(body.encode('ascii')):04X}"
    if len(line) > MAX_LINE:
        raise ValueError(f"{kind}: line of {len(line)} characters is longer than {MAX_LINE}")
    return line


def encode(kind: str, *args: Arg, direction: str) -> bytes:
    """The line as bytes, newline included."""
    return (format_line(kind, *args, direction=direction) + "\n").encode("ascii")


def parse_line(line: Union[str, bytes], direction: str) -> Message:
    """Parse one line (newline and a trailing CR already removed). Raises ProtocolError.

    Checks run in a fixed order, which the firmware follows too: length, checksum present, checksum
    value, characters and spacing, keyword, argument count, argument values.
    """
    if isinstance(line, str):
        try:
            line = line.encode("latin-1")
        except UnicodeEncodeError:
            raise ProtocolError("syntax", "character outside 8 bits") from None
    if len(line) > MAX_LINE:
        raise ProtocolError("length", f"{len(line)} characters (at most {MAX_LINE})")
    star = line.rfind(b"*")
    if star < 0 or len(line) - star != 5 or not all(c in _HEX_DIGITS for c in line[star + 1:]):
        raise ProtocolError("checksum", "no '*CCCC' checksum at the end")
    body = line[:star]
    if crc16(body) != int(line[star + 1:], 16):
        raise ProtocolError("checksum", f"checksum {line[star + 1:].decode()} does not match the line")
    if any(not 0x20 <= c <= 0x7E for c in body) or b"*" in body:
        raise ProtocolError("syntax", "character that is not printable ASCII, or a second '*'")
    tokens = body.decode("ascii").split(" ")
    if any(t == "" for t in tokens):
        raise ProtocolError("syntax", "empty line, or spaces not single")
    kind = tokens[0]
    if not _KIND.fullmatch(kind):
        raise ProtocolError("syntax", f"{kind[:20]!r} is not a message keyword")
    spec = MESSAGES[direction].get(kind)
    if spec is None:
        raise ProtocolError("unknown", f"{kind} is not a {direction} message")
    values = tokens[1:]
    if len(values) != len(spec):
        raise ProtocolError("args", f"{kind} takes {len(spec)} arguments, got {len(values)}")
    args: list[Arg] = []
    for name, text in zip(spec, values):
        if name.endswith(":w"):
            if not _WORD.fullmatch(text):
                raise ProtocolError("args", f"{kind}.{name[:-2]}: {text[:30]!r} is not a word")
            args.append(text)
        else:
            if not _UINT.fullmatch(text):
                raise ProtocolError("args", f"{kind}.{name}: {text[:30]!r} is not an unsigned decimal integer")
            value = int(text)
            if value > U64_MAX:
                raise ProtocolError("args", f"{kind}.{name}: {text} does not fit in 64 bits")
            args.append(value)
    return Message(kind, tuple(args), direction)


@dataclass
class LineCounters:
    """What a receiver saw: good lines, and rejected ones by reason."""

    lines: int = 0
    good: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: {r: 0 for r in REJECTIONS})
    overlong: int = 0  # bytes discarded because no newline came within a line's length
    # lines the parser failed on with something other than ProtocolError: a bug in parse_line, not
    # noise on the link. Kept apart from the rejections so a test can demand it stays 0.
    parser_errors: int = 0
    last_error: Optional[str] = None

    @property
    def corrupt(self) -> int:
        return self.rejected["length"] + self.rejected["checksum"] + self.rejected["syntax"] + self.rejected["args"]

    @property
    def unknown(self) -> int:
        return self.rejected["unknown"]

    def to_dict(self) -> dict:
        return {"lines": self.lines, "good": self.good, "corrupt": self.corrupt, "unknown": self.unknown,
                "rejected": dict(self.rejected), "overlong": self.overlong, "parser_errors": self.parser_errors}


class LineReader:
    """Split a byte stream into lines and parse them; bad input is counted, never raised.

    Every line read is counted once: good, rejected (by ProtocolError reason), or a parser error
    (parse_line raised something else: a bug, counted apart and kept off the live link).

    `feed(data)` returns the messages completed by `data`. A line longer than MAX_LINE without a
    newline is discarded up to the next newline (a stuck or noisy line cannot grow the buffer).
    """

    def __init__(self, direction: str, on_reject: Optional[Callable[[str, str], None]] = None):
        self.direction = direction
        self.on_reject = on_reject  # called with (reason, detail) for every rejected line
        self.counters = LineCounters()
        self._buf = bytearray()
        self._discarding = False

    def feed(self, data: bytes) -> list[Message]:
        out: list[Message] = []
        self._buf.extend(data)
        while True:
            nl = self._buf.find(b"\n")
            if nl < 0:
                if len(self._buf) > MAX_LINE + 1:
                    if not self._discarding:
                        self._reject("length", "line without newline is too long")
                        self._discarding = True
                    self.counters.overlong += len(self._buf)
                    self._buf.clear()
                return out
            raw = bytes(self._buf[:nl])
            del self._buf[: nl + 1]
            if self._discarding:  # the tail of an overlong line
                self._discarding = False
                self.counters.overlong += len(raw)
                continue
            if raw.endswith(b"\r"):
                raw = raw[:-1]
            if not raw.strip(b" \r\x00"):
                continue  # blank lines (a terminal's Enter) are not messages
            msg = self.parse(raw)
            if msg is not None:
                out.append(msg)

    def parse(self, raw: Union[bytes, str]) -> Optional[Message]:
        self.counters.lines += 1
        try:
            msg = parse_line(raw, self.direction)
        except ProtocolError as exc:
            self._reject(exc.reason, str(exc))
            return None
        except Exception as exc:  # a parser bug must not take the link down; counted apart from noise
            self.counters.parser_errors += 1
            detail = f"parser error on {repr(raw)[:60]}: {exc!r}"  # repr first: the net must not trip itself
            self.counters.last_error = detail
            if self.on_reject is not None:  # the other end still gets its answer: this line was not read
                self.on_reject("syntax", detail)
            return None
        self.counters.good += 1
        return msg

    @property
    def partial(self) -> bool:
        """Whether bytes of an unfinished line are waiting for their newline."""
        return bool(self._buf) and not self._discarding

    def clear(self) -> None:
        """Forget a partial line (the port was reopened); counters stay."""
        self._buf.clear()
        self._discarding = False

    def _reject(self, reason: str, detail: str) -> None:
        self.counters.rejected[reason] += 1
        self.counters.last_error = detail
        if self.on_reject is not None:
            self.on_reject(reason, detail)


def pulse_offset_us(index: int, rate_mhz: int) -> int:
    """Board time of pulse `index` after the first: floor(index * 10^9 / rate_mHz) us (no accumulated rounding)."""
    return (index * 1_000_000_000) // rate_mhz


def rate_to_mhz(rate_hz: float) -> int:
    return int(round(rate_hz * 1000.0))


def main(argv: Optional[list[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv:
        print("usage: python -m sync.protocol KIND [ARG...]   (prints the line to type, checksum included)", file=sys.stderr)
        return 2
    kind, *rest = argv
    args = [int(a) if a.isdigit() else a for a in rest]
    for direction in (HOST, BOARD):
        if kind in MESSAGES[direction]:
            try:
                print(format_line(kind, *args, direction=direction))
                return 0
            except ValueError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
    print(f"error: unknown message {kind!r}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
