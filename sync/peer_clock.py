"""Another host's monotonic clock, as seen from this one.

A daemon stamps its frames (and a board's owner its pulses and its clock model) with its own host's
monotonic clock. Two machines' monotonic clocks count from their own boots: PTP or chrony align
their wall clocks, never that origin, so a session reading a daemon on another host must move the
daemon's times onto its own clock before it compares them with anything. (Network namespaces of one
machine share one clock; a time namespace does not.)

The offset is measured as NTP does, over the daemon's API: local time t0, the peer's clock c, local
time t1; offset = c - (t0 + t1) / 2, within half the round trip. Of the recent samples, the one with
the shortest round trip wins. An offset smaller than half that round trip cannot be told from none
and counts as none: the same clock read across a link stays exactly the same clock.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable, Optional

from sync.frames import monotonic_ns

WINDOW = 16  # samples kept: the best of them is the estimate (clocks drift by ppm: minutes of samples are fine)


class PeerClock:
    def __init__(self, read_peer_ns: Callable[[], int], samples: int = 5):
        self._read = read_peer_ns
        self._per_refresh = samples
        self._samples: deque = deque(maxlen=WINDOW)  # (rtt_ns, offset_ns)
        self._lock = threading.Lock()
        self.offset_ns = 0
        self.rtt_ns: Optional[int] = None
        self.refreshed_at = 0.0  # when an estimate was last made or tried (monotonic s)

    def sample(self, t0: int, peer_ns: int, t1: int) -> None:
        """One exchange measured elsewhere (a status request that carries the peer's clock)."""
        with self._lock:
            self._samples.append((t1 - t0, peer_ns - (t0 + t1) // 2))
            rtt, offset = min(self._samples)
            self.rtt_ns = rtt
            self.offset_ns = 0 if abs(offset) <= rtt // 2 else offset
            self.refreshed_at = time.monotonic()

    def refresh(self) -> bool:
        """A few exchanges now; False when the peer did not answer (the last estimate stands)."""
        self.refreshed_at = time.monotonic()
        for _ in range(self._per_refresh):
            t0 = monotonic_ns()
            try:
                peer = int(self._read())
            except Exception:  # noqa: BLE001 - the peer is away: asked again at the next refresh
                return False
            self.sample(t0, peer, monotonic_ns())
        return True

    def to_local(self, peer_ns: int) -> int:
        return int(peer_ns) - self.offset_ns

    def to_peer(self, local_ns: int) -> int:
        return int(local_ns) + self.offset_ns
