"""Where the live engine's frame sets come from: the running rig, or a recorded take replayed at its
recorded rate (rehearsal without cameras). Both hand out `LiveSet`s and say how the devices are."""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from calibration.camera import CameraModel
from rig.errors import ConfigError


@dataclass
class LiveSet:
    index: int  # increasing; gaps are sets the source dropped or that lacked a source frame
    capture_ns: int  # exposure time, host monotonic clock
    images: dict[str, np.ndarray]  # per source camera, as the camera delivered it (rig.cameras.pixels.rgb8 makes it RGB)


@dataclass
class Health:
    ok: bool = True
    messages: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"ok": self.ok, "messages": list(self.messages)}


class SessionSource:
    """Frame sets of a running rig (rig.capture.session.RigSession), left and right frames only.

    Only the two sources are opened and grouped: the model renders from them alone, and capturing
    the supervision cameras too would take CPU from the model (on a 2-core box, a sixth of it for a
    simulated six-camera rig) for frames nobody looks at. The cameras keep the whole rig
    (CameraConfig.rig), so a simulated one still shows the rig's scene from its own place."""

    def __init__(self, config, left: str, right: str, on_phase=None):
        from dataclasses import replace

        from rig.capture.session import RigSession

        self.left, self.right = left, right
        sources = [c for c in config.cameras if c.name in (left, right)]
        self.session = RigSession(replace(config, cameras=sources), on_phase=on_phase)
        self.incomplete = 0
        self._lost: dict[str, str] = {}  # what is down now, by device
        self._seen_events = 0
        self._last_set = time.monotonic()

    def start(self) -> None:
        self.session.open()
        self.session.start()
        self._last_set = time.monotonic()

    def next(self, timeout: float) -> Optional[LiveSet]:
        fs = self.session.next_set(timeout=timeout)
        if fs is None:
            return None
        self._last_set = time.monotonic()
        left, right = fs.frames.get(self.left), fs.frames.get(self.right)
        if left is None or right is None:
            self.incomplete += 1
            return None
        capture = fs.host_ts_ns if fs.host_ts_ns is not None else min(left.host_ts_ns, right.host_ts_ns)
        return LiveSet(fs.index, int(capture), {self.left: left.image, self.right: right.image})

    @property
    def finished(self) -> bool:
        return self.session.finished

    def health(self) -> Health:
        events = self.session.events
        for e in events[self._seen_events:]:
            if e.kind == "camera_lost":
                self._lost[f"camera:{e.values.get('camera', e.detail)}"] = e.detail
            elif e.kind == "board_disconnected":
                self._lost["board"] = e.detail
            elif e.kind in ("resumed", "board_connected"):
                self._lost.pop("board", None)
            elif e.kind == "camera_back":
                self._lost.pop(f"camera:{e.values.get('camera', e.detail)}", None)
        self._seen_events = len(events)
        messages = list(self._lost.values())
        quiet = time.monotonic() - self._last_set
        if quiet > 2.0:
            messages.append(f"no frame set for {quiet:.0f} s")
        return Health(not messages, messages)

    def stop(self) -> None:
        try:
            self.session.stop()
        finally:
            self.session.close()


class ReplaySource:
    """A recorded take's left and right frames at the take's own rate, looped (rehearsal)."""

    def __init__(self, sequence: str | Path, left: str, right: str, loop: bool = True):
        from rig.storage.dataset import Sequence
        from rig.storage.layout import SequenceError

        if Path(sequence).exists() and not Path(sequence).is_dir():
            raise ConfigError(f"--replay: {sequence}: is a file, not a sequence folder")
        try:
            self.sequence = Sequence(sequence)
        except SequenceError as exc:
            raise ConfigError(f"--replay: {exc}") from None
        names = self.sequence.camera_names
        for n in (left, right):
            if n not in names:
                raise ConfigError(f"--replay: {sequence} has no camera '{n}' (it has: {', '.join(names)})")
        self.left, self.right = left, right
        self.positions = self.sequence.complete_sets([left, right])
        if not self.positions:
            raise ConfigError(f"--replay: {sequence} has no set with both '{left}' and '{right}'")
        self.loop = loop
        self.incomplete = len(self.sequence) - len(self.positions)
        self._k = 0
        self._lap = 0
        self._t0 = 0.0
        self._stop = threading.Event()
        self._finished = False
        times = [self.sequence.rows[p]["frames"][left]["host_ts_ns"] for p in self.positions]
        self._offsets = [(t - times[0]) / 1e9 for t in times]
        period = float(np.median(np.diff(self._offsets))) if len(times) > 1 else 1.0 / 30
        self._lap_s = self._offsets[-1] + period

    def cameras(self) -> dict[str, CameraModel]:
        from rig.storage.layout import SequenceError

        try:
            return {n: self.sequence.camera_model(n) for n in (self.left, self.right)}
        except SequenceError as exc:
            raise ConfigError(f"--replay: {exc}") from None

    def start(self) -> None:
        self._t0 = time.monotonic()

    def next(self, timeout: float) -> Optional[LiveSet]:
        if self._finished:
            return None
        if self._k >= len(self.positions):
            if not self.loop:
                self._finished = True
                return None
            self._k, self._lap = 0, self._lap + 1
        due = self._t0 + self._lap * self._lap_s + self._offsets[self._k]
        wait = due - time.monotonic()
        if wait > timeout:
            self._stop.wait(timeout)
            return None
        if wait > 0:
            self._stop.wait(wait)
        if self._stop.is_set():
            return None
        pos = self.positions[self._k]
        index = self._lap * len(self.sequence) + pos
        self._k += 1
        sample = self.sequence.sample(pos, [self.left, self.right])
        return LiveSet(index, int(due * 1e9), {n: sample.images[n] for n in (self.left, self.right)})

    @property
    def finished(self) -> bool:
        return self._finished

    def health(self) -> Health:
        return Health()

    def stop(self) -> None:
        self._stop.set()
