"""A running rig: its cameras, its trigger board, and FrameSets out.

    with RigSession(load_config("rig.toml")) as session:     # opens cameras and trigger board
        for frame_set in session.framesets():                 # starts: clock warm-up, pulse train
            ...                                               # sets in pulse order, gaps None
            if enough: break
        print(session.camera_stats(), session.errors())
    # leaving the block stops the train, drains the last frames, closes everything

A camera whose daemon runs on this host (`rig daemon`, `rig up`) is read from the daemon's frame
ring instead of being opened here (rig.daemon.client), and a trigger board whose daemon owns it is
driven through that daemon (rig.daemon.board_client); the FrameSets are the same either way.

`start(pulses=N)` gives a train of a fixed length (the board says DONE: `train_done`); `stop()`
ends a run and flushes the last sets.

One thread per camera pulls frames into the grouper; a pump thread hands ready sets to
`framesets()`/`next_set()`. Hardware-triggered cameras expose on the board's pulses (on a sim rig
the emulated board drives the sim cameras' trigger inputs); software-triggered cameras get a
software trigger per pulse; free-running cameras are grouped by host time. Cameras that record to their own card (a GoPro with
`?record=card`) are opened here too, in this process, but give no frames: they are in
`card_cameras`, not `cameras`, and no set waits for them (`rig record` presses their shutters,
rig.capture.cards). Without a trigger board
the first camera (the `left` one if any) sets the instants, and software-triggered cameras are fired
on each of its frames (or at its frame rate when it is software-triggered itself).

When the trigger board goes away mid-run the session says so (an event in `events`, and
`board_lost`), keeps every set already grouped, and goes on emitting the sets of pulses that had
fired; when the board comes back it starts a new pulse train (`resume=True`), whose sets continue
the numbering.
"""
from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Optional

from rig.cameras import live_cameras, open_camera as _open_in_process, records_to_card
from rig.daemon.board_client import open_board  # the board's daemon when one owns it, else in-process
from rig.daemon.client import open_camera as _open_camera  # a camera's daemon when one serves it, else in-process
from rig.config import RigConfig
from rig.errors import CameraDisconnected, CameraTimeout, DeviceError
from sync.board import BoardEvent, Pulse, TriggerBoard
from sync.errors import TriggerBoardError
from sync.frames import FrameSet, monotonic_ns
from sync.grouping import HARDWARE, TIMED, FrameGrouper

_END = object()
TAKE_NEEDS_LIVE = "a take needs at least one camera with live frames (its sets and pulses are what the videos are aligned to)"
MIN_WARM_ROUND_TRIPS = 100  # usable board time replies the clock model holds before the first pulse


def prerender_note(cameras: dict[str, Any]) -> Optional[str]:
    """What to say before starting `cameras` (name -> open camera) when simulated ones among them
    pre-render their scene loop first (seconds per camera the first time; then it comes from the
    loop cache), else None. A sim camera with a loop has a `sensor` whose `loop_frames` is not 0,
    as SimCamera.prepare tests; other cameras have no such thing."""
    names = [n for n, cam in cameras.items() if getattr(getattr(cam, "sensor", None), "loop_frames", 0)]
    if not names:
        return None
    return f"preparing the simulated scene for {', '.join(names)} (rendered the first time, then loaded from the cache)"


@dataclass
class SessionEvent:
    kind: str  # board_connected, board_disconnected, board_error, link_error, boot, camera_lost, train_done, resumed
    detail: str
    time_ns: int
    values: dict[str, Any] = field(default_factory=dict)


class RigSession:
    """Cameras + trigger board + grouping for one RigConfig. Not reentrant; use once."""

    def __init__(self, config: RigConfig, *, warm_up_s: float = 3.0, max_wait_s: Optional[float] = None,
                 resume: bool = True, open_camera: Callable = _open_camera,
                 on_event: Optional[Callable[[SessionEvent], None]] = None,
                 on_phase: Optional[Callable[[str], None]] = None):
        """`on_phase(text)` hears what a slow start is doing (opened the cameras, pre-rendering the
        simulated scene, warming up the board clock): commands print it as notes (rig/progress.py)."""
        self.config = config
        self._phase = on_phase or (lambda text: None)
        self.warm_up_s = warm_up_s
        self.max_wait_s = max_wait_s
        self.resume = resume
        self._open_camera = open_camera
        self._on_event = on_event
        self.cameras: dict[str, Any] = {}  # the cameras that give frames
        self.card_cameras: dict[str, Any] = {}  # those that record to their own card (no frames)
        self.live_configs = live_cameras(config.cameras, TAKE_NEEDS_LIVE)
        self.board: Optional[TriggerBoard] = None
        self.emulator = None  # the device behind the board, closed after it (the emulated board of sim://trigger)
        self.grouper: Optional[FrameGrouper] = None
        self.events: list[SessionEvent] = []
        self.frames_delivered: dict[str, int] = {c.name: 0 for c in self.live_configs}
        self.board_lost = False
        self.train_pulses: int = 0  # pulses asked for in the current train (0 = until stop)
        self._out: queue.Queue = queue.Queue()
        self.train_done = threading.Event()  # the board ended the current train (DONE)
        self._running = threading.Event()
        self._stopping = False
        self._threads: list[threading.Thread] = []
        self._wake = threading.Event()
        self._soft_triggers: queue.Queue = queue.Queue()
        self._started = False
        self._closed = False
        self._finished = False
        self._trains = 0

    # --- opening ----------------------------------------------------------------------------------
    def open(self) -> "RigSession":
        try:
            if self.config.trigger is not None:
                self._open_board()  # first: its clock model learns while the cameras open and start
            for cam_cfg in self.config.cameras:
                if records_to_card(cam_cfg):  # no daemon serves it: it has no frames to share
                    self.card_cameras[cam_cfg.name] = _open_in_process(cam_cfg)
                else:
                    self.cameras[cam_cfg.name] = self._open_camera(cam_cfg)
            self.grouper = self._make_grouper()
        except BaseException:
            self.close()
            raise
        # said once everything is open, not before: a camera or URI that fails to open is then the
        # command's only line on stderr
        board = f" and the trigger board {self.config.trigger.uri}" if self.board is not None else ""
        cards = f", {len(self.card_cameras)} recording to their cards ({', '.join(self.card_cameras)})" if self.card_cameras else ""
        self._phase(f"opened {len(self.cameras)} cameras ({', '.join(self.cameras)}){cards}{board}")
        return self

    def _open_board(self) -> None:
        # first the board's daemon, when one owns it (rig up): pulses and clock then come from there
        hardware = [c for c in self.live_configs if c.trigger == "hardware"]
        self.board, self.emulator = open_board(self.config, {c.name: self._trigger_input(c.name) for c in hardware})
        self._connect_board()

    def _connect_board(self) -> None:
        trig = self.config.trigger
        self.board.subscribe(on_pulse=self._on_pulse, on_event=self._on_board_event)
        try:
            self.board.connect()
            self.board.set_rate(trig.rate_hz, trig.pulse_width_us)
        except TriggerBoardError as exc:
            raise DeviceError(f"trigger board {trig.uri}: {exc}") from None

    def _trigger_input(self, name: str) -> Callable[[int, int], None]:
        """Camera `name`'s trigger input for the emulated board, opened before the cameras."""
        def fire(pulse_index: int, host_ns: int) -> None:
            cam = self.cameras.get(name)
            if cam is not None:
                cam.hardware_trigger(pulse_index, host_ns)
        return fire

    def _make_grouper(self) -> FrameGrouper:
        modes = {c.name: (HARDWARE if c.trigger == "hardware" else TIMED) for c in self.live_configs}
        latency = {c.name: int(c.latency_ms * 1e6) for c in self.live_configs if c.latency_ms is not None}
        if self.board is not None:
            return FrameGrouper(modes, self.config.trigger.rate_hz, clock=self.board.clock, max_wait_s=self.max_wait_s,
                                latency_ns=latency)
        left = self.config.by_role("left")
        reference = left.name if left is not None and left in self.live_configs else self.live_configs[0].name
        return FrameGrouper(modes, self.config.camera(reference).fps, reference=reference, max_wait_s=self.max_wait_s,
                            latency_ns=latency)

    # --- running ----------------------------------------------------------------------------------
    def start(self, pulses: int = 0) -> None:
        """Start the cameras, warm the clock model up, then the pulse train (pulses = 0: until stop)."""
        if self.grouper is None:
            self.open()
        if self._started:
            raise DeviceError("session already started")
        self._started = True
        note = prerender_note(self.cameras)
        if note:
            self._phase(note)
        for cam in self.cameras.values():
            # slow preparations first (a sim camera pre-renders its loop), so that the cameras then
            # start within moments of each other rather than one long preparation apart
            cam.prepare()
        self._running.set()
        for name, cam in self.cameras.items():
            cam.start()
            self._spawn(self._camera_loop, f"camera-{name}", name, cam)
        self._spawn(self._pump, "grouping")
        if any(c.trigger == "software" for c in self.config.cameras):
            self._spawn(self._software_trigger_loop, "software-trigger")
        if self.board is not None:
            try:
                self._warm_up_clock()
                self._start_train(pulses)
            except TriggerBoardError as exc:
                self.stop()
                raise DeviceError(f"trigger board {self.config.trigger.uri}: {exc}") from None
        elif self.config.camera(self.grouper.reference).trigger == "software":
            self._spawn(self._software_clock, "software-clock")
        # else: software cameras follow the free-running reference camera's frames (_camera_loop)

    def _warm_up_clock(self) -> None:
        """Give the board clock model `warm_up_s` of round trips before the first pulse. It learns
        from the moment the board connects (the driver queries at 100 Hz while the model is young),
        so the time spent since, opening and preparing the cameras, counts: only the rest is waited
        here, for the same span of board time. Should a busy host have spoilt most round trips, it
        waits on for MIN_WARM_ROUND_TRIPS usable ones (at most another warm_up_s)."""
        clock = self.board.clock
        wait = max(0.0, self.warm_up_s - clock.age_s())
        if wait > 0.5 and not self._trains:  # the first start only: a resume is reported by its event
            self._phase(f"warming up the trigger board clock ({wait:.1f} s)")
        self.board.warm_up(wait)
        give_up = time.monotonic() + self.warm_up_s
        while self.board.connected and (clock.fit is None or clock.fit.samples < MIN_WARM_ROUND_TRIPS) and time.monotonic() < give_up:
            self.board.warm_up(0.1)

    def _start_train(self, pulses: int) -> None:
        self.train_pulses = pulses
        self.train_done.clear()
        if self._trains:
            self.grouper.new_epoch()
        self._trains += 1
        self.board.start(pulses)

    def stop(self) -> None:
        """End the train, wait for frames in flight, stop the cameras and flush the last sets."""
        if not self._running.is_set():
            return
        self._stopping = True
        if self.board is not None and self.board.connected:
            try:
                self.board.stop()
                self.board.wait_done(1.0)
            except TriggerBoardError:
                pass
        # frames still on their way: wait until every fired pulse has its set (complete, or given up
        # on by the grouper's own patience), so a busy host does not cut the last sets short
        settle = max(0.2, max((c.exposure_us or 5000.0) for c in self.live_configs) * 1e-6 * 2 + 0.1)
        deadline = time.monotonic() + settle + self.grouper.max_wait_ns / 1e9
        time.sleep(settle / 2)
        while time.monotonic() < deadline and not self.grouper.settled():
            time.sleep(0.02)
        self._running.clear()
        self._wake.set()
        for t in self._threads:
            t.join(timeout=3)
        self._threads.clear()
        for cam in self.cameras.values():
            try:
                cam.stop()
            except Exception:
                pass
        for fs in self.grouper.flush():
            self._out.put(fs)
        self._out.put(_END)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._running.is_set():
            self.stop()
        if self.board is not None:
            self.board.close()
        if self.emulator is not None:
            self.emulator.close()
        for cam in list(self.cameras.values()) + list(self.card_cameras.values()):
            try:
                cam.close()  # a card camera still recording releases its shutter
            except Exception:
                pass

    def __enter__(self) -> "RigSession":
        return self.open() if self.grouper is None else self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- output -----------------------------------------------------------------------------------
    def next_set(self, timeout: Optional[float] = None) -> Optional[FrameSet]:
        """The next set, or None at the end of the session or when `timeout` passes."""
        if self._finished:
            return None
        try:
            item = self._out.get(timeout=timeout)
        except queue.Empty:
            return None
        if item is _END:
            self._finished = True
            return None
        return item

    @property
    def finished(self) -> bool:
        """Every set has been handed out (the session stopped and the queue is empty)."""
        return self._finished

    def framesets(self, seconds: Optional[float] = None, until: Optional[Callable[[], bool]] = None) -> Iterator[FrameSet]:
        """Sets as they are grouped, until the session stops (or `seconds` pass, or `until()` is true:
        then it stops; both are asked also while no set arrives, as when a trigger board is gone).
        Starts the session (a pulse train until stop) if it is not running yet."""
        if not self._started:
            self.start()
        end = None if seconds is None else time.monotonic() + seconds
        while True:
            over = (end is not None and time.monotonic() >= end) or (until is not None and until())
            if over and self._running.is_set():
                self.stop()
            fs = self.next_set(timeout=0.1)
            if fs is not None:
                yield fs
            elif self._finished:
                return

    def camera_stats(self) -> dict[str, dict]:
        """Per camera: delivered (frames from the camera), grouped (placed in sets), dropped (sets
        emitted without it), and how the drops came about."""
        counters = self.grouper.stats()["cameras"] if self.grouper else {}
        out = {}
        for name in self.cameras:
            c = counters.get(name, {})
            out[name] = {
                "delivered": self.frames_delivered.get(name, 0),
                "grouped": c.get("grouped", 0),
                "dropped": c.get("drops", 0),
                "lost_frames": c.get("lost_frames", 0),
                "missed_triggers": c.get("missed_triggers", 0),
                "duplicates": c.get("duplicates", 0),
                "unassigned": c.get("unassigned", 0),
                "id_gaps": c.get("id_gaps", []),
            }
        return out

    def errors(self) -> list[str]:
        """What went wrong during the run, one line each (board or camera lost, board errors)."""
        return [e.detail for e in self.events if e.kind in ("board_disconnected", "camera_lost", "board_error", "boot")]

    def stats(self) -> dict:
        g = self.grouper.stats() if self.grouper else {}
        return {
            "frames": dict(self.frames_delivered),
            "grouping": g,
            "board": self.board.report() if self.board else None,
            "events": [{"kind": e.kind, "detail": e.detail} for e in self.events],
        }

    # --- threads ----------------------------------------------------------------------------------
    def _spawn(self, target: Callable, name: str, *args) -> None:
        t = threading.Thread(target=target, args=args, name=f"rig-{name}", daemon=True)
        t.start()
        self._threads.append(t)

    def _camera_loop(self, name: str, cam) -> None:
        while self._running.is_set():
            try:
                frame = cam.get_frame(timeout=0.2)
            except CameraTimeout:
                continue
            except CameraDisconnected as exc:
                if self._running.is_set():
                    self._event("camera_lost", str(exc), {"camera": name})
                self.grouper.camera_lost(name)
                if not (self.resume and self._await_camera(name, cam)):
                    return
                continue
            self.frames_delivered[name] += 1
            self.grouper.add_frame(frame)
            if self._follow_reference and name == self.grouper.reference:
                self._soft_triggers.put(None)  # software cameras expose right after the reference frame
            self._wake.set()

    def _await_camera(self, name: str, cam) -> bool:
        """Until the session stops, ask a lost camera about once a second whether it is back; True
        when it is (its sets fill again)."""
        while self._running.is_set():
            time.sleep(1.0)
            try:
                back = cam.reconnect()
            except Exception:  # noqa: BLE001 - a backend failing to reopen: still lost, try again
                back = False
            if back and self._running.is_set():
                self.grouper.camera_back(name, ids_continue=getattr(cam, "IDS_CONTINUE", False))
                self._event("camera_back", f"camera {name} is back", {"camera": name})
                return True
        return False

    def _pump(self) -> None:
        while self._running.is_set():
            self._wake.wait(0.01)
            self._wake.clear()
            for fs in self.grouper.poll(monotonic_ns()):
                self._out.put(fs)

    def _software_trigger_loop(self) -> None:
        cams = [self.cameras[c.name] for c in self.config.cameras if c.trigger == "software"]
        while self._running.is_set():
            try:
                self._soft_triggers.get(timeout=0.1)
            except queue.Empty:
                continue
            for cam in cams:
                try:
                    cam.software_trigger()
                except DeviceError:
                    pass  # a lost camera is reported by its frame loop

    @property
    def _follow_reference(self) -> bool:
        """No trigger board and a free-running reference camera: it paces the software triggers."""
        return self.board is None and self.config.camera(self.grouper.reference).trigger == "free"

    def _software_clock(self) -> None:
        """No trigger board, software-triggered reference camera: triggers at its frame rate."""
        period = 1.0 / self.config.camera(self.grouper.reference).fps
        next_t = time.monotonic()
        while self._running.is_set():
            self._soft_triggers.put(None)
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))

    # --- board callbacks (reader and supervisor threads: keep short) ------------------------------
    def flash(self, ms: int) -> Optional[dict[str, Any]]:
        """Flash the trigger board's LED for `ms` ms (cameras that cannot be triggered are aligned
        to the pulses by it afterwards: sync.alignment). Returns where the flash began: board time,
        host time and its position on the trigger axis (in pulse periods); None when the rig's board
        cannot flash or did not say when it did."""
        board = self.board
        if board is None or not hasattr(board, "flash") or self.grouper is None:
            return None
        try:
            event = board.flash(int(ms))
        except TriggerBoardError as exc:
            self._event("board_error", f"LED flash failed: {exc}")
            return None
        if event is None:
            return None
        board_us = int(event.values["board_us"])
        clock = getattr(board, "clock", None)
        flash = {"board_us": board_us, "ms": int(ms), "trigger": self.grouper.pulse_position(board_us),
                 "host_ns": clock.board_to_host_ns(board_us) if clock is not None and clock.ready else None}
        self._event("flash", f"LED flash of {ms} ms", flash)
        return flash

    def _on_pulse(self, pulse: Pulse) -> None:
        if self.grouper is None:  # the session is not grouping yet (a shared board's pulses come early)
            return
        self.grouper.add_pulse(pulse.index, pulse.board_us)
        if not pulse.late:
            self._soft_triggers.put(pulse.index)
        self._wake.set()

    def _on_board_event(self, event: BoardEvent) -> None:
        if event.kind == "done":
            self.grouper.end_of_train(int(event.values["pulses"]))
            self._event("train_done", event.detail, event.values)
            self.train_done.set()
        elif event.kind == "disconnected":
            self.board_lost = True
            self._event("board_disconnected", event.detail)
        elif event.kind == "connected" and event.values.get("reconnect"):
            self._event("board_connected", event.detail, event.values)
            if self.resume and self._running.is_set() and not self._stopping:
                threading.Thread(target=self._resume, name="rig-resume", daemon=True).start()
        elif event.kind == "board_error":
            self._event("link_error", event.detail, event.values)  # a line the board could not read: counted, retried
        elif event.kind == "boot":
            self._event("boot", event.detail, event.values)
        self._wake.set()

    def _resume(self) -> None:
        try:
            self.board.set_rate(self.config.trigger.rate_hz, self.config.trigger.pulse_width_us)
            self._warm_up_clock()
            self._start_train(self.train_pulses)
            self._event("resumed", f"pulse train restarted on {self.config.trigger.uri}")
        except TriggerBoardError as exc:
            self._event("board_error", f"could not restart the pulse train: {exc}")

    def _event(self, kind: str, detail: str, values: Optional[dict] = None) -> None:
        ev = SessionEvent(kind, detail, monotonic_ns(), dict(values or {}))
        self.events.append(ev)
        if self._on_event is not None:
            try:
                self._on_event(ev)
            except Exception:
                pass
