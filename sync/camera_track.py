"""One camera as the frame grouper follows it: its counters, the frames it is waiting to place, and
for a hardware-triggered camera the line that maps its device clock to the board's:
device_ts_ns ~ dev_ref + offset_ns + slope * (board_us - board_ref), fitted to matched pairs."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

HARDWARE = "hardware"
TIMED = "timed"  # free-run or software-triggered: grouped by host time

# The least-delay clock of a timed camera (LeastDelay): how fast the least delay may grow (the
# camera's clock running slow against the host's: crystals are within 100 ppm, 500 allows for
# more), and how late a frame may seem before its device clock is taken to have jumped.
MAX_DRIFT = 500e-6
RESYNC_NS = 500_000_000
RESYNC_FRAMES = 3


@dataclass
class LeastDelay:
    """How late a timed camera's frame reached the host, beyond the least delay its frames have
    shown: host minus device time is the clocks' offset plus the delivery delay, so its running
    minimum (allowed to grow by MAX_DRIFT as the clocks drift apart) is the offset plus the
    fastest delivery, and a frame above it came that much late: its exposure began that much
    earlier than its arrival says. The passive clock synchronisation of Olson (ICRA 2010), which
    a loaded host needs: a frame delivered two periods late is otherwise taken for a later one.
    A device clock that does not advance says nothing (lateness 0); one that jumps back, or
    RESYNC_FRAMES frames in a row over RESYNC_NS late (a camera restarted), starts it afresh."""

    offset_ns: Optional[float] = None
    last_device_ns: Optional[int] = None
    late_run: int = 0

    def late_ns(self, device_ts_ns: int, host_ns: int) -> float:
        delta = float(host_ns - device_ts_ns)
        if self.offset_ns is None or self.last_device_ns is None or device_ts_ns <= self.last_device_ns:
            self.offset_ns, self.last_device_ns, self.late_run = delta, device_ts_ns, 0
            return 0.0
        allowed = self.offset_ns + (device_ts_ns - self.last_device_ns) * MAX_DRIFT
        self.last_device_ns = device_ts_ns
        if delta - allowed > RESYNC_NS:
            self.late_run += 1
            self.offset_ns = delta if self.late_run >= RESYNC_FRAMES else allowed
            return 0.0  # not believed until it repeats: the frame is placed by its arrival
        self.late_run = 0
        self.offset_ns = min(delta, allowed)
        return delta - self.offset_ns

    def reset(self) -> None:
        self.offset_ns = self.last_device_ns = None
        self.late_run = 0


@dataclass
class CameraCounters:
    frames: int = 0  # received
    grouped: int = 0  # placed in a set
    drops: int = 0  # sets emitted without this camera
    lost_frames: int = 0  # gaps in frame ids: exposures the camera made that never arrived
    missed_triggers: int = 0  # pulses skipped without a gap in frame ids: the camera never exposed
    duplicates: int = 0  # a second frame for a pulse already filled
    unassigned: int = 0  # frames that fit no pulse (before the first, after the last, ambiguous)
    reanchors: int = 0  # the device-time model was rebuilt from host time
    ambiguous_anchors: int = 0  # frame ids and arrival times disagreed on the first pulse; arrival times won

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class CameraTrack:
    name: str
    mode: str  # HARDWARE or TIMED
    counters: CameraCounters = field(default_factory=CameraCounters)
    pending: deque = field(default_factory=deque)  # frames waiting for a timeline
    # hardware: the device-time model
    anchored: bool = False
    board_ref: int = 0
    dev_ref: int = 0
    offset_ns: float = 0.0
    slope: float = 1000.0  # device ns per board us
    pairs: deque = field(default_factory=lambda: deque(maxlen=64))  # (board_us - board_ref, device_ts - dev_ref)
    last_pulse: Optional[int] = None
    last_frame_id: Optional[int] = None  # of the last frame assigned
    last_seen_id: Optional[int] = None  # of the last frame received
    id_gaps: list = field(default_factory=list)  # the first gaps in frame ids: {"after_id", "next_id", "lost", "host_ts_ns"}
    id_base: Optional[int] = 0  # frame id before the first exposure of this train (None: unknown)
    suspicious: int = 0
    # timed: frames not yet claimed by a set, by host exposure-start time
    timed: deque = field(default_factory=deque)
    past_ns: int = -(2**62)  # host exposure-start time of the newest frame
    delivery: LeastDelay = field(default_factory=LeastDelay)  # timed: how late each frame arrived
    alive: bool = True

    def anchor(self, board_ref: int, dev_ref: int) -> None:
        """Start the device-time model afresh: this device time answered the pulse at `board_ref`."""
        self.anchored = True
        self.board_ref = board_ref
        self.dev_ref = dev_ref
        self.offset_ns = 0.0
        self.slope = 1000.0
        self.pairs.clear()
        self.suspicious = 0

    def predicted_board_us(self, device_ts_ns: int) -> float:
        """The board time the model puts a device timestamp at."""
        return self.board_ref + (device_ts_ns - self.dev_ref - self.offset_ns) / self.slope

    def add_pair(self, board_us: float, device_ts_ns: int) -> None:
        """A frame matched to its pulse: refit the line."""
        self.pairs.append((board_us - self.board_ref, float(device_ts_ns - self.dev_ref)))
        if len(self.pairs) < 2:
            x, y = self.pairs[0]
            self.offset_ns, self.slope = y - 1000.0 * x, 1000.0
            return
        xy = np.array(self.pairs, dtype=np.float64)
        x, y = xy[:, 0], xy[:, 1]
        if np.ptp(x) < 0.2e6:  # under 0.2 s: too short to tell the slope from jitter
            self.offset_ns, self.slope = float(np.mean(y - 1000.0 * x)), 1000.0
            return
        xm, ym = x.mean(), y.mean()
        slope = float(np.sum((x - xm) * (y - ym)) / np.sum((x - xm) ** 2))
        self.slope, self.offset_ns = slope, float(ym - slope * xm)

    def new_train(self) -> None:
        """A new pulse train: the model and the waiting frames are forgotten, ids count on from here."""
        self.id_base = self.last_seen_id
        self.anchored = False
        self.pairs.clear()
        self.last_pulse = None
        self.pending.clear()
        self.timed.clear()
        self.past_ns = -(2**62)
