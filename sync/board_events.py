"""What the trigger-board driver reports: the board it found, pulses and other events, the link's
counters, and the bookkeeping that tells lost, late and repeated pulse reports apart."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional


@dataclass(frozen=True)
class BoardInfo:
    protocol: int
    firmware: str
    board_id: str


@dataclass(frozen=True)
class Pulse:
    """One trigger pulse as the board reported it."""

    index: int  # counts from 0 at each START
    board_us: int  # rising edge on the board's clock
    received_ns: int  # host monotonic time the report arrived
    late: bool = False  # arrived after a later pulse's report (a delayed line)


@dataclass(frozen=True)
class BoardEvent:
    """Something other than a pulse: connected, disconnected, done, flash, board_error, boot."""

    kind: str
    detail: str
    time_ns: int
    values: dict[str, Any] = field(default_factory=dict)


@dataclass
class LinkCounters:
    pulses: int = 0
    missing_pulse_reports: int = 0  # gaps in pulse indices (lines lost on the link)
    late_pulses: int = 0  # reports that came after a later one, and filled a gap
    duplicate_pulses: int = 0
    unexpected_replies: int = 0  # replies nobody waits for (late, or not matching the request)
    board_errors: dict[str, int] = field(default_factory=dict)  # ERR 0 CODE: the board could not read our line
    timeouts: int = 0
    retries: int = 0
    disconnects: int = 0
    reconnects: int = 0
    listener_errors: int = 0


class PulseOrder:
    """Pulse reports against the indices the board counts: a gap is a report lost on the link (for
    now), a report that fills a gap is late, one seen before is a duplicate. Counts into `counters`."""

    MAX_MISSING = 100_000  # gaps remembered; a link that loses more is reported by the counter alone

    def __init__(self, counters: LinkCounters):
        self.counters = counters
        self._next = 0
        self._missing: set[int] = set()

    @property
    def missing(self) -> int:
        """Reports still missing (gaps not filled by a late report)."""
        return len(self._missing)

    def reset(self) -> None:
        """A new train (START) or a new board (reconnect): indices count from 0 again."""
        self._next = 0
        self._missing.clear()

    def accept(self, index: int) -> Optional[bool]:
        """Whether the report of pulse `index` is late; None for a duplicate (to be dropped)."""
        late = False
        if index == self._next:
            self._next += 1
        elif index > self._next:
            self.counters.missing_pulse_reports += index - self._next
            if len(self._missing) < self.MAX_MISSING:
                self._missing.update(range(self._next, index))
            self._next = index + 1
        elif index in self._missing:
            self._missing.discard(index)
            self.counters.late_pulses += 1
            late = True
        else:
            self.counters.duplicate_pulses += 1
            return None
        self.counters.pulses += 1
        return late
