"""sync.peer_clock: another host's monotonic clock from NTP-style exchanges."""
from __future__ import annotations

from sync.frames import monotonic_ns
from sync.peer_clock import PeerClock


def test_the_shortest_round_trip_gives_the_offset_and_a_peer_clock_ahead_is_moved_back():
    clock = PeerClock(lambda: 0)
    clock.sample(1_000, 5_000_000_900, 3_000)  # round trip 2000 ns: offset 5e9 - 100
    clock.sample(10_000, 5_000_020_000, 30_000)  # slower, and 10 us off: not taken
    assert clock.rtt_ns == 2_000 and clock.offset_ns == 5_000_000_900 - 2_000
    assert clock.to_local(5_000_100_000) == 100_000 + 2_000 - 900 and clock.to_peer(clock.to_local(123)) == 123


def test_an_offset_within_half_the_round_trip_is_no_offset():
    clock = PeerClock(lambda: 0)
    clock.sample(0, 1_400, 4_000)  # 1400 - 2000 = -600, under half of 4000
    assert clock.offset_ns == 0 and clock.to_local(777) == 777


def test_a_peer_that_stops_answering_keeps_the_last_estimate():
    answers = iter([monotonic_ns() + 10**12] * 5)
    clock = PeerClock(lambda: next(answers) + 0)
    assert clock.refresh() and abs(clock.offset_ns - 10**12) < 10**9
    before = clock.offset_ns
    assert not clock.refresh() and clock.offset_ns == before
