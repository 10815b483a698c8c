"""`rig up -c RIG.toml`: a daemon per camera, kept running; `rig down` ends them.

The supervisor starts `rig daemon NAME -c RIG.toml` for every camera of the config (child processes
sharing one simulated scene clock, $RIG_SIM_EPOCH_NS), then watches them ten times a second:

- a daemon that exited (crashed, was killed) is started again;
- a daemon whose ring heartbeat is older than `stale_s` (1 s by default; its acquisition loop hangs, or it never came
  up within `start_timeout_s`) is killed (SIGKILL) and started again;
- restarts back off (0.2 s, doubled per quick failure, at most 5 s; a daemon up for 30 s is healthy
  again), are counted per camera and reported as events (printed, and kept in the state file).

Its state (its pid, per camera: pid, state, restarts, last event) is rewritten every second to
<root>/<rig>/supervisor.json (rig.daemon.paths); `rig down` signals the pid found there and waits.

A rig with a trigger board gets its owner too (`rig daemon --board`, listed as `@board`): sessions
drive the board through it, and for a `sim://` board its emulator fires the camera daemons.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from common.files import atomic_write_json
from rig.config import RigConfig
from rig.daemon import paths
from rig.daemon.ring import RingError, RingReader
from sync.frames import monotonic_ns

BOARD = "@board"  # the trigger board daemon's entry among the children
BACKOFF_START_S = 0.2
BACKOFF_MAX_S = 5.0
HEALTHY_AFTER_S = 30.0
# A camera daemon renews its heartbeat at least every 0.2 s (rig.daemon.camera_daemon): 1 s without one
# is a hang, so a hung daemon runs again within 2 s. The board daemon beats every 0.5 s (its clock
# datagrams' period, rig.daemon.board_daemon.CLOCK_EVERY_S) by rewriting its info file: 2 s for it.
STALE_S = 1.0
BOARD_STALE_S = 2.0


@dataclass
class Child:
    camera: str
    proc: Optional[subprocess.Popen] = None
    started: float = 0.0
    restarts: int = 0
    backoff: float = BACKOFF_START_S
    next_start: float = 0.0
    state: str = "starting"  # starting | running | restarting | stopped
    last_event: str = ""
    reader: Optional[RingReader] = field(default=None, repr=False)


class Supervisor:
    def __init__(self, config: RigConfig, config_path: Path, *, stale_s: float = STALE_S, start_timeout_s: float = 60.0,
                 daemon_args: tuple[str, ...] = (), say: Callable[[str], None] = print, only: Optional[set[str]] = None):
        self.config = config
        self.config_path = Path(config_path).absolute()
        self.stale_s = stale_s
        self.start_timeout_s = start_timeout_s
        self.daemon_args = tuple(daemon_args)
        self.say = say
        from rig.cameras import records_to_card

        # a camera recording to its card has no frames to serve: each take opens it (rig record)
        self.children = {c.name: Child(c.name) for c in config.cameras if not records_to_card(c)}
        if config.trigger is not None:  # the board's owner, under a name no camera file can have
            self.children[BOARD] = Child(BOARD)
        if only is not None:  # this host's part of a rig spread over several (rig up --cameras)
            self.children = {n: c for n, c in self.children.items() if n in only}
        self.events: list[dict] = []
        self.stop_event = threading.Event()
        self._changed = False
        self.env = dict(os.environ, RIG_SIM_EPOCH_NS=os.environ.get("RIG_SIM_EPOCH_NS") or str(monotonic_ns()))

    def event(self, camera: str, kind: str, detail: str) -> None:
        self.events.append({"camera": camera, "kind": kind, "detail": detail, "time_ns": monotonic_ns()})
        del self.events[:-200]
        self.children[camera].last_event = detail
        self._changed = True
        self.say(f"{camera}: {detail}")

    def _spawn(self, child: Child) -> None:
        who = ["--board"] if child.camera == BOARD else [child.camera]
        cmd = [sys.executable, "-m", "rig", "daemon", *who, "-c", str(self.config_path), *self.daemon_args]
        child.proc = subprocess.Popen(cmd, env=self.env, stdin=subprocess.DEVNULL, start_new_session=True)
        child.started = time.monotonic()
        child.state = "starting"
        self._changed = True  # the state file says so at once
        if child.reader is not None:
            child.reader.close()
            child.reader = None

    def _heartbeat_age(self, child: Child) -> Optional[float]:
        """Seconds since the child's heartbeat (a camera's in its ring, the board's in its info file),
        None while it has not come up yet."""
        board = child.camera == BOARD
        info = paths.read_json(paths.board_info_path(self.config.name) if board else paths.info_path(self.config.name, child.camera))
        if info is None or child.proc is None or info.get("pid") != child.proc.pid:
            return None
        if board:
            return (monotonic_ns() - int(info.get("heartbeat_ns", 0))) / 1e9
        if child.reader is None:
            try:
                child.reader = RingReader.attach(info["ring"])
            except RingError:
                return None
        return (monotonic_ns() - child.reader.heartbeat_ns) / 1e9

    def _check(self, child: Child) -> None:
        now = time.monotonic()
        if child.proc is None:
            if now >= child.next_start:
                self._spawn(child)
            return
        code = child.proc.poll()
        if code is None:
            age = self._heartbeat_age(child)
            if age is None:
                if now - child.started > self.start_timeout_s:
                    self._restart(child, f"did not come up within {self.start_timeout_s:g} s")
                return
            if age > (max(self.stale_s, BOARD_STALE_S) if child.camera == BOARD else self.stale_s):
                self._restart(child, f"heartbeat stopped ({age:.1f} s old): killed")
                return
            if child.state != "running":
                child.state = "running"
                self.event(child.camera, "up", f"daemon up (pid {child.proc.pid})")
            if now - child.started > HEALTHY_AFTER_S:
                child.backoff = BACKOFF_START_S
            return
        self._restart(child, f"daemon exited ({_exit_text(code)})")

    def _restart(self, child: Child, why: str) -> None:
        if child.proc is not None and child.proc.poll() is None:
            child.proc.kill()
            child.proc.wait(5)
        child.proc = None
        child.restarts += 1
        child.state = "restarting"
        child.next_start = time.monotonic() + child.backoff
        self.event(child.camera, "restart", f"{why}; restarting in {child.backoff:.1f} s (restart {child.restarts})")
        child.backoff = min(BACKOFF_MAX_S, child.backoff * 2)

    def write_state(self) -> None:
        atomic_write_json(paths.supervisor_path(self.config.name), {
            "pid": os.getpid(), "rig": self.config.name, "config": str(self.config_path), "time_ns": monotonic_ns(),
            "sim_epoch_ns": int(self.env["RIG_SIM_EPOCH_NS"]),
            "cameras": {c.camera: {"pid": c.proc.pid if c.proc else None, "state": c.state, "restarts": c.restarts,
                                   "last_event": c.last_event} for c in self.children.values()},
            "events": self.events[-50:],
        }, make_parents=True)

    def run(self) -> None:
        for child in self.children.values():
            self._spawn(child)
        last_state = 0.0
        try:
            while not self.stop_event.is_set():
                for child in self.children.values():
                    self._check(child)
                if self._changed or time.monotonic() - last_state > 1.0:
                    self.write_state()
                    self._changed = False
                    last_state = time.monotonic()
                self.stop_event.wait(0.1)
        finally:
            self.shutdown()

    def shutdown(self, timeout: float = 10.0) -> None:
        for child in self.children.values():
            if child.proc is not None and child.proc.poll() is None:
                child.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for child in self.children.values():
            if child.proc is None:
                continue
            try:
                child.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.proc.kill()
                child.proc.wait(5)
            child.state = "stopped"
            if child.reader is not None:
                child.reader.close()
        paths.supervisor_path(self.config.name).unlink(missing_ok=True)


def _exit_text(code: int) -> str:
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"


def stop_supervisor(rig: str, timeout: float = 15.0) -> Optional[int]:
    """SIGTERM the rig's running supervisor and wait for it to finish; its pid, or None when none runs."""
    state = paths.read_json(paths.supervisor_path(rig))
    if state is None or not paths.pid_alive(state.get("pid")):
        return None
    pid = int(state["pid"])
    os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while paths.pid_alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    return pid
