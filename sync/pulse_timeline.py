"""The pulses of one train, as the frame grouper sees them: board times as reported, the board's
schedule for those whose report is late or lost, which pulses are known to have fired, and their
host times through the clock model (or, with no trigger board, a reference camera's exposures)."""
from __future__ import annotations

from typing import Optional, Protocol

import numpy as np

from sync.protocol import pulse_offset_us


class BoardClock(Protocol):
    ready: bool

    def board_to_host_ns(self, board_us: float) -> int: ...

    def host_to_board_us(self, host_ns: int) -> float: ...


class PulseTimeline:
    """Pulse k of the current train: its board time, its host time, whether it has fired.

    With a clock, times come from the board: a reported pulse has its board time, any other pulse
    its scheduled one (start + floor(k * 10^9 / rate_mHz) us, as the firmware schedules it).
    Without one (no trigger board), `add_instant` appends pulses at the reference camera's host times.
    """

    def __init__(self, rate_mhz: int, clock: Optional[BoardClock]):
        self.rate_mhz = rate_mhz
        self.clock = clock
        self.start_us: Optional[int] = None  # board time of pulse 0 (None: no pulse known yet)
        self.max_pulse = -1  # highest index known to have fired (reported, or implied by DONE)
        self.done: Optional[int] = None  # pulses in the train, once the board said DONE
        self._reported: dict[int, int] = {}  # pulse index -> board us
        self._host: dict[int, int] = {}  # pulse index -> host ns (reference camera, no board)

    @property
    def started(self) -> bool:
        return self.start_us is not None

    def clear(self) -> None:
        """A new train: indices count from 0 again."""
        self.start_us = None
        self.max_pulse = -1
        self.done = None
        self._reported.clear()
        self._host.clear()

    def report(self, index: int, board_us: int) -> bool:
        """A pulse the board reported; False when it was reported before."""
        if index in self._reported:
            return False
        self._reported[index] = board_us
        if self.start_us is None:
            self.start_us = board_us - pulse_offset_us(index, self.rate_mhz)
        self.max_pulse = max(self.max_pulse, index)
        return True

    def end(self, pulses: int) -> None:
        """The board ended the train after `pulses` pulses."""
        self.done = pulses
        self.max_pulse = max(self.max_pulse, pulses - 1)

    def add_instant(self, host_ns: int) -> int:
        """No board: the next pulse is at `host_ns` (a reference camera's exposure); returns its index."""
        k = self.max_pulse + 1
        self._host[k] = host_ns
        self.max_pulse = k
        if self.start_us is None:
            self.start_us = 0
        return k

    def fired(self, k: int) -> bool:
        """Whether pulse k is known to have fired."""
        return 0 <= k <= self.max_pulse and (self.done is None or k < self.done)

    def board_time(self, k: int) -> float:
        t = self._reported.get(k)
        if t is not None:
            return float(t)
        return float(self.start_us + pulse_offset_us(k, self.rate_mhz))

    def host_ns(self, k: int) -> int:
        if self.clock is None:
            return self._host[k]
        return self.clock.board_to_host_ns(self.board_time(k))

    def at_or_before(self, board_us: float) -> int:
        """The last pulse at or before `board_us` (-1 and below: before the first)."""
        k = int(np.floor((board_us - self.start_us) * self.rate_mhz / 1e9))
        while self.board_time(k + 1) <= board_us:
            k += 1
        while k >= 0 and self.board_time(k) > board_us:
            k -= 1
        return k

    def nearest(self, board_us: float) -> int:
        k = int(round((board_us - self.start_us) * self.rate_mhz / 1e9))
        return min((k - 1, k, k + 1), key=lambda j: abs(self.board_time(j) - board_us))
