"""The line protocol in Python (host driver and emulator side) against the shared test vectors."""
from __future__ import annotations

import subprocess
import sys

import pytest

from sync.protocol import (
    BOARD,
    HOST,
    LineReader,
    ProtocolError,
    crc16,
    encode,
    format_line,
    parse_line,
    pulse_offset_us,
)


def test_crc_matches_the_standard_check_value(vectors):
    assert f"{crc16(vectors['crc_check']['input'].encode()):04X}" == vectors["crc_check"]["crc16"]


def test_valid_vectors_parse_and_format(vectors):
    for v in vectors["valid"]:
        msg = parse_line(v["line"].encode("latin-1"), v["dir"])
        assert (msg.kind, list(msg.args)) == (v["kind"], v["args"]), v
        if v["canonical"]:
            assert format_line(v["kind"], *v["args"], direction=v["dir"]) == v["line"], v


def test_invalid_vectors_are_rejected_for_the_right_reason(vectors):
    for v in vectors["invalid"]:
        with pytest.raises(ProtocolError) as err:
            parse_line(v["line"].encode("latin-1"), v["dir"])
        assert err.value.reason == v["error"], (v, str(err.value))


def test_formatter_refuses_invalid_messages(vectors):
    for v in vectors["format_invalid"]:
        with pytest.raises(ValueError):
            format_line(v["kind"], *v["args"], direction=v["dir"])


def test_messages_read_by_name():
    msg = parse_line(format_line("STATUS", 4, 1, 30000, 100, 17, 0, direction=BOARD), BOARD)
    assert msg["rate_mhz"] == 30000 and msg["pulses"] == 17 and msg.get("nope") is None


def test_reader_splits_a_stream_and_counts_what_it_rejects():
    reader = LineReader(BOARD)
    good = encode("PULSE", 7, 233333, direction=BOARD)
    stream = b"\r\n" + good[:5] + b"" + good[5:] + b"garbage*0000\r\n" + encode("OK", 1, direction=BOARD).replace(b"\n", b"\r\n")
    messages = reader.feed(stream[:9]) + reader.feed(stream[9:])
    assert [m.kind for m in messages] == ["PULSE", "OK"]
    assert messages[0]["index"] == 7
    assert reader.counters.lines == 3 and reader.counters.good == 2 and reader.counters.corrupt == 1


def test_reader_drops_an_overlong_line_without_growing():
    reader = LineReader(HOST)
    assert reader.feed(b"A" * 5000) == []
    assert reader.partial is False
    msgs = reader.feed(b"B" * 10 + b"\n" + encode("TIME", 3, direction=HOST))
    assert [m.kind for m in msgs] == ["TIME"]
    assert reader.counters.rejected["length"] == 1


def test_pulse_schedule_has_no_accumulated_rounding():
    # 30 Hz: 33333.33 us periods; pulse 3 is at exactly 100000 us, pulse 30 at one second
    assert [pulse_offset_us(k, 30000) for k in (0, 1, 2, 3, 30)] == [0, 33333, 66666, 100000, 1000000]


def test_command_line_prints_a_line_to_type():
    out = subprocess.run([sys.executable, "-m", "sync.protocol", "TIME", "7"], capture_output=True, text=True)
    assert out.returncode == 0
    assert parse_line(out.stdout.strip(), HOST).kind == "TIME"
    bad = subprocess.run([sys.executable, "-m", "sync.protocol", "JUMP"], capture_output=True, text=True)
    assert bad.returncode == 2 and "unknown message" in bad.stderr
