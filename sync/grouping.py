"""Frame grouping: each Frame to its trigger pulse, FrameSets out in pulse order.

Hardware-triggered cameras. A camera's device timestamps and the board's pulse times are two clocks
watching the same events, so device_ts = a + b * pulse_board_us (+ trigger-latency jitter) holds
for every frame; b absorbs the drift between the two crystals and a the camera's clock offset plus
its mean trigger latency. The first frame of a camera is anchored by host time (it belongs to the
latest pulse that fired before it arrived, allowing for its exposure); from then on the line is
fitted to the matched pairs and each frame goes to the pulse nearest its predicted board time, so
dropped frames, pulses the camera never saw, late or lost pulse reports and slow delivery all leave
the assignment right. Frame ids tell the two kinds of loss apart: a gap in ids is a frame the camera
took and lost; a pulse skipped with no gap is a trigger the camera never answered.

Cameras that cannot be triggered (free-run, or software triggers) are grouped by host time: the
frame whose exposure start is nearest the pulse's host time, within half a period. A frame's
exposure start is its arrival less its exposure, less how much later than the camera's fastest
frames it came by its device clock (sync.camera_track.LeastDelay): a host that falls behind for a
moment delivers frames late, not from later exposures. With no trigger board at all, a reference
camera's frames define the instants.

A set is emitted once every camera is past its pulse (cameras deliver in order) or its time is up,
never before; a camera with nothing for a pulse leaves None there (a detected drop). Frames of two
pulses never share a set: each set is one pulse, and a second frame for a pulse is set aside as a
duplicate.

The pieces: `sync.pulse_timeline` (the pulses of a train and their times), `sync.camera_track`
(each camera's counters and device-clock line); this module matches frames to pulses and emits sets.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from sync.camera_track import HARDWARE, TIMED, CameraCounters, CameraTrack
from sync.frames import Frame, FrameSet
from sync.pulse_timeline import BoardClock, PulseTimeline

__all__ = ["HARDWARE", "TIMED", "BoardClock", "CameraCounters", "FrameGrouper"]

MAX_GAPS_KEPT = 100  # frame-id gaps described per camera (all are counted)


@dataclass
class _Slot:
    frame: Frame
    offset_ns: float  # timing residual: device-time model residual (hardware) or host-time distance (timed)


@dataclass
class _Pending:
    pulse: int
    frames: dict = field(default_factory=dict)  # camera -> _Slot


class FrameGrouper:
    """Groups frames into sets, one per trigger pulse. Thread-safe.

    cameras: name -> HARDWARE or TIMED, in the order sets list them.
    rate_hz: the trigger rate (with a board) or the reference camera's frame rate (without).
    clock: the board clock model (board us -> host ns); None when there is no trigger board, and
    then `reference` names the camera whose frames define the instants.
    max_wait_s: how long after its pulse a set waits for a camera that is not past it.
    """

    ANCHOR_FRAMES = 3  # frames an anchor normally waits for
    ANCHOR_PATIENCE = 8  # frames it waits for when frame ids and arrival times disagree

    def __init__(self, cameras: dict[str, str], rate_hz: float, clock: Optional[BoardClock] = None,
                 reference: Optional[str] = None, max_wait_s: Optional[float] = None,
                 latency_ns: Optional[dict[str, int]] = None):
        if not cameras:
            raise ValueError("no cameras to group")
        for name, mode in cameras.items():
            if mode not in (HARDWARE, TIMED):
                raise ValueError(f"{name}: grouping mode must be {HARDWARE!r} or {TIMED!r}, got {mode!r}")
        if clock is None and reference is None:
            reference = next(iter(cameras))
        if clock is None and any(m == HARDWARE for m in cameras.values()):
            raise ValueError("hardware-triggered cameras need the trigger board's clock")
        self.clock = clock
        # a timed camera's delay from exposure start to host arrival, where it is known (a GoPro's
        # stream arrives a few hundred ms late); otherwise its exposure time
        self.latency_ns = {n: int(v) for n, v in (latency_ns or {}).items()}
        self.reference = reference if clock is None else None
        self.rate_mhz = int(round(rate_hz * 1000))
        self.period_ns = 1e12 / self.rate_mhz
        self.max_wait_ns = int((max_wait_s if max_wait_s is not None else max(0.5, 4 * self.period_ns / 1e9)) * 1e9)
        self.tracks = {name: CameraTrack(name, mode) for name, mode in cameras.items()}
        self._lock = threading.RLock()
        self.epoch = 0
        self._base = 0  # set index of pulse 0 of this epoch
        self.timeline = PulseTimeline(self.rate_mhz, clock)  # the pulses of the current epoch
        self._next_emit = 0  # next pulse index to emit in this epoch
        self._sets: dict[int, _Pending] = {}
        self.emitted = 0
        self.complete = 0
        self.skews_ns: list[float] = []
        self.mapped_pulses: list[tuple[int, int, int]] = []  # (epoch, pulse, host ns as mapped when reported)
        self._flushed: list[FrameSet] = []  # sets of an ended epoch, handed out by the next poll

    # --- inputs -----------------------------------------------------------------------------------
    def add_pulse(self, index: int, board_us: int) -> None:
        """A pulse the board reported (index counts from 0 in this epoch)."""
        with self._lock:
            if not self.timeline.report(index, board_us):
                return
            if self.clock is not None and self.clock.ready:
                self.mapped_pulses.append((self.epoch, index, self.clock.board_to_host_ns(board_us)))
            self._retry_pending()

    def pulse_position(self, board_us: float) -> Optional[float]:
        """Where board time `board_us` falls on the sets' trigger axis, in pulse periods (set
        `trigger` n is pulse n: 17.25 is a quarter period after it); None before the first pulse."""
        with self._lock:
            if not self.timeline.started:
                return None
            return self._base + (board_us - self.timeline.start_us) * self.rate_mhz / 1e9

    def end_of_train(self, pulses: int) -> None:
        """The board ended the train after `pulses` pulses (DONE)."""
        with self._lock:
            self.timeline.end(pulses)

    def new_epoch(self) -> None:
        """A new pulse train with indices from 0 again (board restarted, or START after STOP)."""
        with self._lock:
            self._retry_pending(force=True)
            self._emit_ready(now_ns=None, flush=True, out=self._flushed)
            self.epoch += 1
            self._base = self._base + max(self._next_emit, self.timeline.max_pulse + 1)
            self.timeline.clear()
            self._next_emit = 0
            self._sets.clear()
            for t in self.tracks.values():
                t.new_train()

    def camera_lost(self, name: str) -> None:
        """The camera is gone: sets stop waiting for it."""
        with self._lock:
            self.tracks[name].alive = False

    def camera_back(self, name: str, ids_continue: bool = False) -> None:
        """The camera delivers again. `ids_continue`: its frame ids go on from before (a daemon's
        camera: the daemon kept counting while the link was down, so a gap is frames lost);
        otherwise a new acquisition whose ids start afresh."""
        with self._lock:
            track = self.tracks[name]
            track.alive = True
            if not ids_continue:
                track.last_seen_id = None
                track.delivery.reset()  # a new acquisition: its clock may start afresh
            track.pending.clear()

    def add_frame(self, frame: Frame) -> None:
        with self._lock:
            track = self.tracks.get(frame.camera)
            if track is None:
                raise ValueError(f"frame from unknown camera {frame.camera!r}")
            track.counters.frames += 1
            if track.last_seen_id is not None and frame.frame_id > track.last_seen_id + 1:
                lost = frame.frame_id - track.last_seen_id - 1
                track.counters.lost_frames += lost
                if len(track.id_gaps) < MAX_GAPS_KEPT:
                    track.id_gaps.append({"after_id": track.last_seen_id, "next_id": frame.frame_id, "lost": lost,
                                          "host_ts_ns": frame.host_ts_ns})
            track.last_seen_id = frame.frame_id
            if self.reference == frame.camera:
                self._add_reference(track, frame)
            elif track.mode == HARDWARE:
                track.pending.append(frame)
                self._retry_pending()
            else:
                self._add_timed(track, frame)

    # --- outputs ----------------------------------------------------------------------------------
    def poll(self, now_ns: int) -> list[FrameSet]:
        """Sets that are ready, in order."""
        out: list[FrameSet] = []
        with self._lock:
            out.extend(self._take_flushed())
            self._retry_pending(now_ns)
            self._emit_ready(now_ns, flush=False, out=out)
        return out

    def settled(self) -> bool:
        """Every pulse known to have fired has been emitted as a set."""
        with self._lock:
            return self._next_emit > self.timeline.max_pulse

    def flush(self) -> list[FrameSet]:
        """Every remaining set of pulses known to have fired (end of run)."""
        out: list[FrameSet] = []
        with self._lock:
            out.extend(self._take_flushed())
            self._retry_pending(force=True)
            self._emit_ready(now_ns=None, flush=True, out=out)
        return out

    def _take_flushed(self) -> list[FrameSet]:
        out, self._flushed = self._flushed, []
        return out

    def stats(self) -> dict:
        with self._lock:
            skews = np.array(self.skews_ns, dtype=np.float64) / 1000.0
            return {
                "sets": self.emitted,
                "complete_sets": self.complete,
                "cameras": {n: {**t.counters.to_dict(), "id_gaps": list(t.id_gaps)} for n, t in self.tracks.items()},
                "skew_us": {
                    "p50": float(np.percentile(skews, 50)) if len(skews) else None,
                    "p99": float(np.percentile(skews, 99)) if len(skews) else None,
                    "max": float(skews.max()) if len(skews) else None,
                },
            }

    # --- hardware-triggered cameras ---------------------------------------------------------------
    def _retry_pending(self, now_ns: Optional[int] = None, force: bool = False) -> None:
        if not self.timeline.started or self.clock is None or not self.clock.ready:
            return
        for track in self.tracks.values():
            if not track.pending:
                continue
            if not track.anchored:
                # anchor on a few frames; a lone frame waits a little for company
                old = now_ns is not None and now_ns - track.pending[0].host_ts_ns > self.max_wait_ns // 2
                # a train that has ended with fewer pulses than ANCHOR_FRAMES sends no more company
                wanted = self.ANCHOR_FRAMES if self.timeline.done is None else max(1, min(self.ANCHOR_FRAMES, self.timeline.done))
                if len(track.pending) < wanted and not (force or old):
                    continue
                self._anchor(track, list(track.pending), decide=force or old)
                if not track.anchored:
                    continue
            while track.pending:
                frame = track.pending.popleft()
                self._assign_hardware(track, frame)
                track.last_frame_id = frame.frame_id

    def _anchor(self, track: CameraTrack, frames: list[Frame], decide: bool = True) -> None:
        """Tie the camera's clock to the pulse timeline: which pulse did its first frame answer?

        Two bounds, with the pulse steps between the frames from their device timestamps. Arrival:
        a frame reaches the host after its pulse fired and its exposure ended, so the latest pulse
        before (arrival - exposure) bounds it from above; the frame delivered fastest decides, and a
        camera that delivers within a period gets it exactly. Frame ids: the n-th exposure of a train
        answered pulse n-1 or a later one (a trigger the camera missed pushes it later), a bound
        from below that no delivery delay can shift. When the two meet, that is the pulse. When they
        do not (a camera slow to deliver, or pulses it missed), more frames may close the gap; after
        ANCHOR_PATIENCE frames the arrival bound is taken and the case counted.
        """
        tolerance_ns = min(2_000_000, int(self.period_ns / 4))
        first = frames[0]
        upper = lower = None
        for frame in frames:
            exposure_ns = int((frame.exposure_us or 0.0) * 1000)
            board_limit = self.clock.host_to_board_us(frame.host_ts_ns - exposure_ns + tolerance_ns)
            steps = int(round((frame.device_ts_ns - first.device_ts_ns) / self.period_ns))
            bound = self.timeline.at_or_before(board_limit) - steps
            upper = bound if upper is None else min(upper, bound)
            if track.id_base is not None:
                low = frame.frame_id - track.id_base - 1 - steps
                lower = low if lower is None else max(lower, low)
        if self.timeline.done is not None:
            upper = min(upper, self.timeline.done - 1)
        if upper < 0:
            track.counters.unassigned += 1  # exposed before the first pulse: not ours
            track.pending.popleft()
            track.last_frame_id = first.frame_id
            if track.pending:
                self._anchor(track, list(track.pending), decide)
            return
        k0 = upper
        if lower is not None and 0 <= lower < upper:
            if not decide and len(frames) < self.ANCHOR_PATIENCE:
                return  # wait for more frames
            track.counters.ambiguous_anchors += 1
        track.anchor(int(self.timeline.board_time(k0)), first.device_ts_ns)

    def _assign_hardware(self, track: CameraTrack, frame: Frame) -> None:
        if not track.anchored:
            self._anchor(track, [frame], decide=True)
            if not track.anchored:
                return
        tolerance_ns = min(2_000_000, int(self.period_ns / 4))
        predicted = track.predicted_board_us(frame.device_ts_ns)
        k = self.timeline.nearest(predicted)
        residual_ns = (predicted - self.timeline.board_time(k)) * track.slope
        arrived_early = self.timeline.host_ns(k) > frame.host_ts_ns + tolerance_ns  # before its pulse fired?
        if abs(residual_ns) > self.period_ns / 4 or arrived_early or k < 0:
            track.counters.unassigned += 1
            track.suspicious += 1
            if track.suspicious >= 3:  # three in a row: the model is wrong (camera restarted?)
                track.anchored = False
                track.counters.reanchors += 1
            return
        track.suspicious = 0
        track.add_pair(self.timeline.board_time(k), frame.device_ts_ns)
        # frame ids against pulses: a gap in ids is a lost frame, a pulse skipped without one a missed trigger
        if track.last_pulse is not None and track.last_frame_id is not None and k > track.last_pulse:
            skipped = k - track.last_pulse - 1
            lost = max(0, frame.frame_id - track.last_frame_id - 1)
            if skipped > lost:
                track.counters.missed_triggers += skipped - lost
        self._place(track, k, frame, residual_ns)

    # --- timed cameras and the reference camera ---------------------------------------------------
    def _exposure_start_host(self, frame: Frame) -> int:
        """Host time of the frame's exposure start: its arrival less its exposure (the least a
        frame takes to arrive) and less how late it came (its device clock against its earlier
        frames': sync.camera_track.LeastDelay), or less the camera's known latency."""
        latency = self.latency_ns.get(frame.camera)
        if latency is not None:
            return frame.host_ts_ns - latency
        late = self.tracks[frame.camera].delivery.late_ns(frame.device_ts_ns, frame.host_ts_ns)
        return frame.host_ts_ns - int((frame.exposure_us or 0.0) * 1000) - int(late)

    def _add_reference(self, track: CameraTrack, frame: Frame) -> None:
        k = self.timeline.add_instant(self._exposure_start_host(frame))
        self._place(track, k, frame, 0.0)

    def _add_timed(self, track: CameraTrack, frame: Frame) -> None:
        t = self._exposure_start_host(frame)
        track.timed.append((t, frame))
        track.past_ns = max(track.past_ns, t)
        while len(track.timed) > 256:  # a camera far ahead of the pulses: forget the oldest
            track.timed.popleft()
            track.counters.unassigned += 1

    def _claim_timed(self, track: CameraTrack, k: int) -> None:
        """Give set k the timed camera's frame nearest the pulse, within half a period."""
        host_k = self.timeline.host_ns(k)
        half = self.period_ns / 2
        best = None
        while track.timed and track.timed[0][0] < host_k - half:
            track.timed.popleft()  # too early for this set and every later one
            track.counters.unassigned += 1
        for i, (t, frame) in enumerate(track.timed):
            if t > host_k + half:
                break
            if best is None or abs(t - host_k) < abs(track.timed[best][0] - host_k):
                best = i
        if best is not None:
            t, frame = track.timed[best]
            for _ in range(best + 1):
                dropped = track.timed.popleft()
                if dropped[1] is not frame:
                    track.counters.unassigned += 1
            self._place(track, k, frame, float(t - host_k))

    def _timed_past(self, track: CameraTrack, k: int) -> bool:
        return track.past_ns > self.timeline.host_ns(k) + self.period_ns / 2

    # --- sets -------------------------------------------------------------------------------------
    def _place(self, track: CameraTrack, k: int, frame: Frame, offset_ns: float) -> None:
        if k < self._next_emit:
            track.counters.duplicates += 1  # its set is gone already: a late second frame
            return
        pending = self._sets.setdefault(k, _Pending(k))
        if track.name in pending.frames:
            track.counters.duplicates += 1
            return
        frame.trigger_index = k
        pending.frames[track.name] = _Slot(frame, offset_ns)
        if track.mode == HARDWARE or track.name == self.reference:
            track.last_pulse = k if track.last_pulse is None else max(track.last_pulse, k)

    def _camera_done_with(self, track: CameraTrack, k: int, pending: Optional[_Pending]) -> bool:
        if pending is not None and track.name in pending.frames:
            return True
        if not track.alive:
            return True
        if track.mode == HARDWARE or track.name == self.reference:
            return track.last_pulse is not None and track.last_pulse > k
        return self._timed_past(track, k)

    def _emit_ready(self, now_ns: Optional[int], flush: bool, out: list) -> None:
        if not self.timeline.started or (self.clock is not None and not self.clock.ready):
            return
        while self.timeline.fired(self._next_emit):
            k = self._next_emit
            pending = self._sets.get(k)
            for track in self.tracks.values():
                if track.mode == TIMED and track.name != self.reference and (pending is None or track.name not in pending.frames):
                    self._claim_timed(track, k)
                    pending = self._sets.get(k)
            waiting = [t for t in self.tracks.values() if not self._camera_done_with(t, k, pending)]
            if waiting and not flush:
                if now_ns is None or now_ns < self.timeline.host_ns(k) + self.max_wait_ns:
                    return
            self._sets.pop(k, None)
            out.append(self._make_set(k, pending))
            self._next_emit = k + 1

    def _make_set(self, k: int, pending: Optional[_Pending]) -> FrameSet:
        frames: dict[str, Optional[Frame]] = {}
        offsets = []
        for name, track in self.tracks.items():
            slot = pending.frames.get(name) if pending else None
            if slot is None:
                frames[name] = None
                track.counters.drops += 1
            else:
                frames[name] = slot.frame
                track.counters.grouped += 1
                offsets.append(slot.offset_ns)
        fs = FrameSet(index=self._base + k, frames=frames, host_ts_ns=self.timeline.host_ns(k),
                      trigger_index=k if self.clock is not None else None, train=self.epoch)
        self.emitted += 1
        if fs.complete:
            self.complete += 1
        if len(offsets) > 1:
            self.skews_ns.append(max(offsets) - min(offsets))
        return fs
