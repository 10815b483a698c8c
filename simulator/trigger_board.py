"""An emulated trigger board: the protocol of sync/PROTOCOL.md on a pty pair or a loopback socket.

    board = TriggerBoardEmulator({"drift_ppm": 100, "reply_jitter_us": 200})
    board.add_pulse_output(camera.hardware_trigger)    # the trigger wire: (pulse_index, host_ns)
    board.open()                                        # board.url is what pyserial opens
    ...
    board.unplug(); board.replug()                      # the USB cable, pulled and pushed back
    board.close()

The board has its own clock: it counts microseconds from power-up, starting at `clock_offset_us`,
with a crystal `drift_ppm` off; `clock.host_ns(board_us)` is the truth the host's clock model is
measured against. Pulse k of a train rises at start + floor(k * 10^9 / rate_mHz) board microseconds,
as the firmware schedules it; the pulse outputs get the host time of that edge. Faults on demand:
pulses not delivered to the cameras, replies delayed at random, lines corrupted (both directions),
lines held back and overtaken.

The command handling mirrors the firmware's (sync/firmware/trigger_board/tb_board.c), so the host
driver sees the same board either way. The port and the line queue (delays, order) are
`simulator.serial_link`; this module decides what the board says, when, and which faults hit it.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from simulator.errors import SimulatorError
from simulator.options import validate_options
from simulator.serial_link import BoardSerial, PtyTransport, SocketTransport, transmission_error
from sync.protocol import (
    BOARD,
    HOST,
    MAX_LINE,
    PROTOCOL_VERSION,
    LineReader,
    Message,
    encode,
    pulse_offset_us,
)

FIRMWARE_VERSION = "1.0.0-sim"
START_LEAD_US = 2000  # as the firmware: the first pulse follows START by this much
MIN_RATE_MHZ, MAX_RATE_MHZ, MAX_FLASH_MS = 1, 10_000_000, 60_000


@dataclass(frozen=True)
class BoardClock:
    """The board's microsecond counter against host monotonic time."""

    boot_ns: int
    offset_us: int
    drift_ppm: float

    def board_us(self, host_ns: int) -> int:
        return self.offset_us + math.floor((host_ns - self.boot_ns) * (1.0 + self.drift_ppm * 1e-6) / 1000.0)

    def host_ns(self, board_us: float) -> int:
        """Host time at which the counter reaches `board_us` (the truth the host's model estimates)."""
        return self.boot_ns + math.ceil((board_us - self.offset_us) * 1000.0 / (1.0 + self.drift_ppm * 1e-6))


@dataclass(frozen=True)
class PulseTruth:
    train: int
    index: int
    board_us: int
    host_ns: int
    delivered: bool  # False: dropped on purpose, the cameras never saw it


@dataclass(frozen=True)
class FlashTruth:
    board_us: int
    host_start_ns: int
    host_end_ns: int


# ---- the board -------------------------------------------------------------------------------------

class TriggerBoardEmulator:
    """A trigger board in software. Thread-safe; pulse outputs are called from the board's pulse thread."""

    def __init__(self, options: Optional[dict] = None, *, board_id: str = "SIM-TB-0001",
                 link: Optional[Path] = None, port: int = 0):
        try:
            self.options = validate_options(dict(options or {}), "trigger")
        except ValueError as exc:
            raise SimulatorError(f"trigger.sim.{exc}") from None
        self.board_id = board_id
        self.rng = np.random.default_rng(self.options["seed"])  # used under self._lock only
        self._rng_in = np.random.default_rng(self.options["seed"] + 1)  # the io thread's (incoming faults)
        transport = SocketTransport(port=port) if self.options["transport"] == "socket" else PtyTransport(link)
        self.serial = BoardSerial(transport)
        self.clock = BoardClock(time.monotonic_ns(), int(self.options["clock_offset_us"]), float(self.options["drift_ppm"]))
        self.boots = 0
        # the truth, for tests and `rig sync check`
        self.pulses: list[PulseTruth] = []
        self.flashes: list[FlashTruth] = []
        self.lines_corrupted = 0
        self.lines_delayed = 0
        self.lines_received = 0

        self._pulse_outputs: list[Callable[[int, int], None]] = []
        self._led_outputs: list[Callable[[bool, int], None]] = []
        self._lock = threading.RLock()
        self._cv = threading.Condition(self._lock)
        self._reader = LineReader(HOST, on_reject=self._rejected)
        self.train = 0  # counts STARTs over the emulator's life, for the truth log
        self._plugged = False
        self._closed = False
        self._threads: list[threading.Thread] = []
        self._reset_state()

    # --- wiring -----------------------------------------------------------------------------------
    def add_pulse_output(self, fn: Callable[[int, int], None]) -> None:
        """Connect a trigger input: fn(pulse_index, host_ns_of_rising_edge)."""
        self._pulse_outputs.append(fn)

    def add_led_output(self, fn: Callable[[bool, int], None]) -> None:
        """Connect something that sees the LED: fn(on, host_ns), the LED's state from host_ns on. A
        flash tells its start and its end at once, as the firmware sets its timer then: a camera
        drawing a frame right after the flash ended must not see it lit because a thread woke late."""
        self._led_outputs.append(fn)

    @property
    def url(self) -> str:
        """What the host's pyserial opens."""
        return self.serial.url

    @property
    def transport(self):
        """The port's transport (PtyTransport or SocketTransport)."""
        return self.serial.transport

    @property
    def lines_sent(self) -> int:
        return self.serial.sent

    @property
    def lines_lost(self) -> int:
        """Lines written while no host was listening."""
        return self.serial.lost

    # --- power and cable --------------------------------------------------------------------------
    def open(self) -> "TriggerBoardEmulator":
        if self._threads:
            return self
        self.serial.start()
        self._plug()
        for target, name in ((self._io_loop, "io"), (self._pulse_loop, "pulses")):
            t = threading.Thread(target=target, name=f"emulated-trigger-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def unplug(self) -> None:
        """Pull the cable: the port vanishes, the board loses power (its train stops)."""
        with self._cv:
            self._plugged = False
            self._reset_state()
            self.serial.unplug()
            self._cv.notify_all()

    def replug(self) -> None:
        """Push the cable back: the board boots again (clock restarts) and the port reappears."""
        with self._cv:
            if self._plugged:
                return
            self._plug()
            self._cv.notify_all()

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._plugged = False
            self._cv.notify_all()
        for t in self._threads:
            t.join(timeout=2)
        self._threads.clear()
        self.serial.close()

    def __enter__(self) -> "TriggerBoardEmulator":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def _plug(self) -> None:
        self.boots += 1
        self.clock = BoardClock(time.monotonic_ns(), int(self.options["clock_offset_us"]), float(self.options["drift_ppm"]))
        self._reset_state()
        self._reader = LineReader(HOST, on_reject=self._rejected)
        self.serial.plug()
        self._plugged = True
        self._send("BOOT", PROTOCOL_VERSION, FIRMWARE_VERSION, self.board_id)

    def _reset_state(self) -> None:
        self.rate_mhz = 30_000
        self.width_us = 100
        self.running = False
        self.train_active = False
        self.start_us = 0
        self.count = 0
        self.next_index = 0
        self.reported = 0
        self.bad_lines = 0
        self.last_n = 0
        self.last_kind = ""
        self.last_reply: Optional[bytes] = None
        self.led_off_ns: Optional[int] = None

    # --- truth ------------------------------------------------------------------------------------
    def truth_host_ns(self, board_us: float) -> int:
        """Host time of a board time under the current boot (what the host's clock model estimates)."""
        return self.clock.host_ns(board_us)

    def dropped_pulses(self, train: Optional[int] = None) -> list[int]:
        with self._lock:
            return [p.index for p in self.pulses if not p.delivered and (train is None or p.train == train)]

    # --- link -------------------------------------------------------------------------------------
    def _send(self, kind: str, *args, remember: bool = False) -> None:
        line = encode(kind, *args, direction=BOARD)
        if remember:
            self.last_reply = line
        self._queue(line)

    def _queue(self, line: bytes) -> None:
        """Put a line on the wire after the link's delay; faults are applied here."""
        now = time.monotonic_ns()
        opts = self.options
        with self._cv:  # self.rng is drawn under the lock
            if opts["corrupt_rate"] > 0 and self.rng.random() < opts["corrupt_rate"]:
                line = transmission_error(line, self.rng)
                self.lines_corrupted += 1
            jitter = int(self.rng.exponential(opts["reply_jitter_us"] * 1000.0)) if opts["reply_jitter_us"] > 0 else 0
            if opts["delay_rate"] > 0 and self.rng.random() < opts["delay_rate"]:
                self.lines_delayed += 1
                self.serial.send(line, now + int(opts["delay_ms"] * 1e6), hold_back=True)
            else:
                self.serial.send(line, now + jitter)

    def _io_loop(self) -> None:
        while not self._closed:
            data = self.serial.read(0.05)
            if not data:
                continue
            arrival_ns = time.monotonic_ns()
            if self.options["corrupt_rate"] > 0:
                data = self._corrupt_incoming(data)
            with self._cv:
                for msg in self._reader.feed(data):  # rejected lines answer ERR 0 via _rejected
                    self.lines_received += 1
                    self._handle(msg, self.clock.board_us(arrival_ns), arrival_ns)

    def _rejected(self, reason: str, detail: str) -> None:
        with self._cv:
            self.bad_lines += 1
            self._send("ERR", 0, _ERROR_CODES.get(reason, "SYNTAX"))

    def _corrupt_incoming(self, data: bytes) -> bytes:
        out = bytearray()
        for part in data.split(b"\n"):
            if part and self._rng_in.random() < self.options["corrupt_rate"]:
                part = transmission_error(part + b"\n", self._rng_in)[:-1]
                self.lines_corrupted += 1
            out += part + b"\n"
        return bytes(out[:-1])

    # --- commands (mirrors tb_board.c) ------------------------------------------------------------
    def _handle(self, msg: Message, now_us: int, now_ns: int) -> None:
        kind = msg.kind
        n = int(msg["n"])
        if n != 0 and n == self.last_n and kind == self.last_kind and self.last_reply is not None and kind not in ("TIME", "HELLO"):
            self._queue(self.last_reply)  # a retry: same answer, not run twice
            return
        if kind != "TIME":
            self.last_n, self.last_kind = n, kind
        if kind == "HELLO":
            self._send("ID", n, PROTOCOL_VERSION, FIRMWARE_VERSION, self.board_id, remember=True)
        elif kind == "RATE":
            rate, width = int(msg["rate_mhz"]), int(msg["width_us"])
            if self.train_active:
                self._send("ERR", n, "BUSY", remember=True)
            elif not (MIN_RATE_MHZ <= rate <= MAX_RATE_MHZ) or width < 1 or width >= 1_000_000_000 // rate:
                self._send("ERR", n, "RANGE", remember=True)
            else:
                self.rate_mhz, self.width_us = rate, width
                self._send("OK", n, remember=True)
        elif kind == "START":
            if self.train_active:
                self._send("ERR", n, "BUSY", remember=True)
            else:
                self.train += 1
                self.count = int(msg["count"])
                self.next_index = 0
                self.start_us = now_us + START_LEAD_US
                self.train_active = True
                self.running = True
                self._send("OK", n, remember=True)
                self._cv.notify_all()
        elif kind == "STOP":
            self.running = False
            self._send("OK", n, remember=True)
            self._finish_train_if_over()
            self._cv.notify_all()
        elif kind == "TIME":
            # Read the clock as the answer is made, as a microcontroller that answers at once does:
            # the emulator's own parsing time then falls before the reading instead of lengthening
            # the way back (the truth stays exact either way; only the link's symmetry changes).
            self._send("TIME", n, self.clock.board_us(time.monotonic_ns()))
        elif kind == "FLASH":
            ms = int(msg["ms"])
            if not 1 <= ms <= MAX_FLASH_MS:
                self._send("ERR", n, "RANGE", remember=True)
                return
            # The LED lights when the command is run, not when its line arrived (the handler may
            # have waited for the lock), and whatever sees it is told before the replies are
            # written: a thread held up between the two on a loaded host would otherwise let a
            # camera draw frames past the flash's start without it.
            now_us = self.clock.board_us(time.monotonic_ns())
            end_ns = self.clock.host_ns(now_us + ms * 1000)
            start_ns = self.clock.host_ns(now_us)
            lit_until = self.led_off_ns if self.led_off_ns is not None and start_ns < self.led_off_ns < end_ns else None
            for fn in list(self._led_outputs):
                fn(True, start_ns)
                if lit_until is not None:  # a flash still lit is extended: the end told for it does not come
                    fn(True, lit_until)
                fn(False, end_ns)
            self.flashes.append(FlashTruth(now_us, start_ns, end_ns))
            self.led_off_ns = end_ns
            self._send("OK", n, remember=True)
            self._send("FLASH", now_us, ms)
        elif kind == "STATUS":
            self._send("STATUS", n, int(self.train_active), self.rate_mhz, self.width_us, self.next_index, self.bad_lines, remember=True)

    def _finish_train_if_over(self) -> None:
        # DONE follows the report of every fired pulse, as on the firmware
        if self.train_active and not self.running and self.reported >= self.next_index:
            self.train_active = False
            self._send("DONE", self.next_index)

    # --- the pulse timer --------------------------------------------------------------------------
    def _pulse_loop(self) -> None:
        while True:
            with self._cv:
                while not self._closed and not (self._plugged and self.running):
                    self._cv.wait(0.1)
                if self._closed:
                    return
                train, index = self.train, self.next_index
                board_us = self.start_us + pulse_offset_us(index, self.rate_mhz)
                due_ns = self.clock.host_ns(board_us)
                while not self._closed and self.running and self.train == train and time.monotonic_ns() < due_ns:
                    self._cv.wait(min(0.1, (due_ns - time.monotonic_ns()) / 1e9))
                if self._closed or not self.running or self.train != train or not self._plugged:
                    continue  # stopped (or unplugged) before this edge
                delivered = not (self.options["drop_pulse_rate"] > 0 and self.rng.random() < self.options["drop_pulse_rate"])
                self.pulses.append(PulseTruth(train, index, board_us, due_ns, delivered))
                self.next_index = index + 1
                if self.count and self.next_index >= self.count:
                    self.running = False
            if delivered:
                for fn in list(self._pulse_outputs):
                    fn(index, due_ns)
            with self._cv:
                if self.train == train and self._plugged:
                    self._send("PULSE", index, board_us)
                    self.reported = index + 1
                    self._finish_train_if_over()


_ERROR_CODES = {"length": "LENGTH", "checksum": "CHECKSUM", "syntax": "SYNTAX", "unknown": "UNKNOWN", "args": "ARGS"}


__all__ = ["BoardClock", "FlashTruth", "PtyTransport", "PulseTruth", "SocketTransport", "TriggerBoardEmulator", "MAX_LINE"]
