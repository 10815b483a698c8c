"""Fuzzing the line protocol: random bytes, mutated valid lines, and mutated lines with their
checksum made right again (so the parser's later checks get the garbage, not only the CRC).

parse_line may only ever raise ProtocolError. The LineReader keeps a safety net for the live link
(any other exception is caught and counted as a parser error, apart from corrupt lines), so the
reader tests demand that counter stays 0: a parser bug fails them instead of hiding in the net."""
from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from sync.protocol import (
    BOARD,
    HOST,
    MESSAGES,
    REJECTIONS,
    LineReader,
    Message,
    ProtocolError,
    crc16,
    format_line,
    parse_line,
)

U64 = st.integers(min_value=0, max_value=2**64 - 1)
WORD = st.text(alphabet="ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._-", min_size=1, max_size=24)
DIRECTION = st.sampled_from([HOST, BOARD])


@st.composite
def valid_lines(draw, direction: str = BOARD) -> str:
    kind = draw(st.sampled_from(sorted(MESSAGES[direction])))
    spec = MESSAGES[direction][kind]
    args = [draw(WORD) if name.endswith(":w") else draw(U64) for name in spec]
    try:
        return format_line(kind, *args, direction=direction)
    except ValueError:  # longer than a line may be: use the shortest values
        return format_line(kind, *[("x" if name.endswith(":w") else 0) for name in spec], direction=direction)


board_lines = valid_lines


def mutate(draw, data: bytearray, noise: st.SearchStrategy) -> bytearray:
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "delete", "insert", "replace", "duplicate", "truncate"]))
        i = draw(st.integers(0, max(0, len(data) - 1)))
        if not data:
            data.append(draw(noise))
        elif op == "flip":
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "delete":
            del data[i]
        elif op == "insert":
            data.insert(i, draw(noise))
        elif op == "replace":
            data[i] = draw(noise)
        elif op == "duplicate":
            data[i:i] = data[i:i + draw(st.integers(1, 8))]
        else:
            del data[i:]
    return data


@st.composite
def mutated(draw) -> tuple[bytes, bytes]:
    line = draw(board_lines()).encode()
    return line, bytes(mutate(draw, bytearray(line), st.integers(0, 255)))


# Bytes a garbled body is made of: mostly what a line holds (so the keyword, the spacing and the
# argument checks are reached), some of anything.
BODY_NOISE = st.one_of(st.sampled_from(list(b" 0123456789AZaz._-*:+")), st.integers(0, 255))


# Tokens a garbled argument list is made of: numbers at and past the 64-bit edge, leading zeros,
# signs, words at and past their length limit, characters no argument may hold.
TOKEN = st.one_of(
    U64.map(str),
    st.integers(2**64, 10**21).map(str),
    st.from_regex(r"0[0-9]{1,4}", fullmatch=True),
    st.from_regex(r"[+-][0-9]{1,3}", fullmatch=True),
    WORD,
    st.text(alphabet="abcXYZ019._-", min_size=25, max_size=30),
    st.text(alphabet=" */:#\x7f\xe9\t", min_size=1, max_size=3),
)


@st.composite
def token_body(draw, direction: str) -> bytes:
    """A keyword (real, lower-case or made up) and tokens, mostly as many as it takes, sometimes
    with doubled spaces."""
    kind = draw(st.one_of(st.sampled_from(sorted(MESSAGES[direction])), st.sampled_from(["ping", "PING", "TIME1", ""])))
    wanted = len(MESSAGES[direction].get(kind, "ab"))
    count = draw(st.one_of(st.just(wanted), st.just(wanted), st.integers(0, 7)))
    tokens = [kind] + draw(st.lists(TOKEN, min_size=count, max_size=count))
    sep = draw(st.sampled_from([" ", " ", " ", "  "]))
    return sep.join(tokens).encode("latin-1", "replace")


@st.composite
def checksummed(draw) -> tuple[str, bytes]:
    """A garbled body given its correct checksum, so the checks after the CRC get the garbage: a valid
    line's body mutated byte by byte, or a body assembled from keyword and argument tokens."""
    direction = draw(DIRECTION)
    if draw(st.booleans()):
        line = draw(valid_lines(direction)).encode()
        body = bytes(mutate(draw, bytearray(line[:line.rindex(b"*")]), BODY_NOISE))
    else:
        body = draw(token_body(direction))
    return direction, body + f"*{crc16(body):04X}".encode()


def parse_or_reason(line, direction: str):
    """The message, or the ProtocolError's reason; any other exception propagates and fails the test."""
    try:
        msg = parse_line(line, direction)
    except ProtocolError as exc:
        assert exc.reason in REJECTIONS, exc.reason
        return exc.reason
    assert isinstance(msg, Message) and msg.kind in MESSAGES[direction]
    return msg


def assert_every_line_counted(reader: LineReader, messages: list) -> None:
    c = reader.counters
    assert c.parser_errors == 0, c.last_error  # parse_line raised something other than ProtocolError
    assert c.good == len(messages)
    assert c.lines == c.good + sum(c.rejected.values())


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=600))
def test_random_bytes_never_escape(data):
    reader = LineReader(BOARD)
    assert_every_line_counted(reader, reader.feed(data))


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=130), DIRECTION)
def test_parse_line_raises_only_protocol_errors_on_random_bytes(data, direction):
    parse_or_reason(data, direction)


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=130), DIRECTION)
def test_parse_line_raises_only_protocol_errors_on_any_text(text, direction):
    parse_or_reason(text, direction)


@settings(max_examples=1000, deadline=None)
@given(checksummed())
def test_garbled_lines_with_a_good_checksum_are_judged_never_crash(case):
    direction, line = case
    reader = LineReader(direction)  # first through the reader: its safety net must not hide a crash
    messages = reader.feed(line + b"\n")
    assert_every_line_counted(reader, messages)
    result = parse_or_reason(line, direction)
    if b"\n" in line:
        return  # the reader sees two lines here (both counted above), not this one
    if isinstance(result, Message):
        assert messages == [result]
        # what was accepted is a well-formed message: it formats back to the very same line
        assert format_line(result.kind, *result.args, direction=direction).encode() == line
    else:
        assert messages == [] and reader.counters.rejected[result] == 1


@settings(max_examples=600, deadline=None)
@given(mutated())
def test_mutated_lines_are_counted_never_raised(pair):
    original, data = pair
    reader = LineReader(BOARD)
    pieces = [p for p in data.split(b"\n") if p.strip(b" \r\x00")]
    messages = reader.feed(data + b"\n")
    assert_every_line_counted(reader, messages)
    c = reader.counters
    # every line that came through is a real message (its checksum matched), nothing else was accepted
    for m in messages:
        assert parse_line(format_line(m.kind, *m.args, direction=BOARD), BOARD) == m
    if data.rstrip(b"\r") != original and len(pieces) == 1 and len(pieces[0]) <= 100:
        accepted = isinstance(parse_or_reason(pieces[0].rstrip(b"\r"), BOARD), Message)
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
    assert reader.counters.parser_errors == 0


@settings(max_examples=300, deadline=None)
@given(board_lines())
def test_round_trip(line):
    msg = parse_line(line, BOARD)
    assert format_line(msg.kind, *msg.args, direction=BOARD) == line


def test_a_parser_bug_is_counted_apart_and_still_answered():
    """The reader's safety net: an exception from the parser is counted as a parser error (not as
    line noise), the line is rejected, and the other end is told (the emulator answers ERR 0)."""
    rejected = []
    reader = LineReader(HOST, on_reject=lambda reason, detail: rejected.append((reason, detail)))
    # a str the parser cannot encode raises ProtocolError; an int is not a line at all: TypeError
    assert reader.parse(12345) is None
    c = reader.counters
    assert (c.lines, c.good, c.parser_errors, c.corrupt) == (1, 0, 1, 0)
    assert rejected and rejected[0][0] == "syntax" and "TypeError" in rejected[0][1]
    assert "TypeError" in c.last_error
