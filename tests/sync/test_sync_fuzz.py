"""Fuzzing the host's line reader: random bytes and mutated valid lines. Nothing may escape, and
every line that is not a valid message is counted."""
from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from sync.protocol import BOARD, MESSAGES, LineReader, ProtocolError, format_line, parse_line

U64 = st.integers(min_value=0, max_value=2**64 - 1)
WORD = st.text(alphabet="ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._-", min_size=1, max_size=24)


@st.composite
def board_lines(draw) -> str:
    kind = draw(st.sampled_from(sorted(MESSAGES[BOARD])))
    args = [draw(WORD) if name.endswith(":w") else draw(U64) for name in MESSAGES[BOARD][kind]]
    try:
        return format_line(kind, *args, direction=BOARD)
    except ValueError:  # longer than a line may be: use the shortest values
        return format_line(kind, *[("x" if name.endswith(":w") else 0) for name in MESSAGES[BOARD][kind]], direction=BOARD)


@st.composite
def mutated(draw) -> tuple[bytes, bytes]:
    line = draw(board_lines()).encode()
    data = bytearray(line)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "delete", "insert", "replace", "duplicate", "truncate"]))
        i = draw(st.integers(0, max(0, len(data) - 1)))
        if not data:
            data.append(draw(st.integers(0, 255)))
        elif op == "flip":
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "delete":
            del data[i]
        elif op == "insert":
            data.insert(i, draw(st.integers(0, 255)))
        elif op == "replace":
            data[i] = draw(st.integers(0, 255))
        elif op == "duplicate":
            data[i:i] = data[i:i + draw(st.integers(1, 8))]
        else:
            del data[i:]
    return line, bytes(data)


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=600))
def test_random_bytes_never_escape(data):
    reader = LineReader(BOARD)
    messages = reader.feed(data)
    c = reader.counters
    assert c.good == len(messages)
    assert c.lines == c.good + sum(c.rejected.values())


@settings(max_examples=600, deadline=None)
@given(mutated())
def test_mutated_lines_are_counted_never_raised(pair):
    original, data = pair
    reader = LineReader(BOARD)
    pieces = [p for p in data.split(b"\n") if p.strip(b" \r\x00")]
    messages = reader.feed(data + b"\n")
    c = reader.counters
    assert c.lines == c.good + sum(c.rejected.values())
    assert c.good == len(messages)
    # every line that came through is a real message (its checksum matched), nothing else was accepted
    for m in messages:
        assert parse_line(format_line(m.kind, *m.args, direction=BOARD), BOARD) == m
    if data.rstrip(b"\r") != original and len(pieces) == 1 and len(pieces[0]) <= 100:
        try:
            parse_line(pieces[0].rstrip(b"\r"), BOARD)
            accepted = True
        except ProtocolError:
            accepted = False
        assert c.good == int(accepted) and sum(c.rejected.values()) == int(not accepted)


@settings(max_examples=300, deadline=None)
@given(board_lines(), st.integers(0, 99), st.integers(0, 7))
def test_any_single_bit_error_is_detected(line, pos, bit):
    data = bytearray(line.encode())
    pos %= len(data)
    data[pos] ^= 1 << bit
    if data[pos] == ord("\n"):
        return  # a bit error that makes a newline splits the line: two bad lines, also counted
    reader = LineReader(BOARD)
    assert reader.feed(bytes(data) + b"\n") == []
    assert reader.counters.corrupt + reader.counters.unknown == 1


@settings(max_examples=300, deadline=None)
@given(board_lines())
def test_round_trip(line):
    msg = parse_line(line, BOARD)
    assert format_line(msg.kind, *msg.args, direction=BOARD) == line
