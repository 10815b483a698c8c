"""`rig daemon CAMERA -c RIG.toml`: one camera as a process of its own.

The daemon opens the camera through its backend and acquires from start to end; every frame is
copied once into the camera's frame ring (rig.daemon.ring), which any process on the host maps to
read it: the recorder, the live server, the calibrator, through `RigSession` (rig.daemon.client). A
camera that vanishes is asked about once a second whether it is back, as in-process capture does;
the daemon itself stays up. Beside the ring:

- a control API (HTTP JSON, rig.daemon.api) on loopback, or on another address with a token;
- a trigger input: a UDP socket on loopback that takes a software trigger (b"S") or an emulated
  hardware edge (b"H" + pulse index + host time, little-endian int64s) in one datagram, so that a
  session's (emulated) trigger board reaches a camera in another process within a millisecond; the
  same socket takes readers' doorbell subscriptions (b"W", renewed every second, lapsing after 5 s):
  as it begins to copy each frame into the ring, the daemon sends each subscriber one byte, so a
  reader blocked on its socket wakes while the frame is copied instead of polling the ring;
  a daemon whose API listens beyond loopback (with a token) has a second trigger input on that address
  (`network_trigger_port`), which takes only triggers tagged with the token (rig.cameras.daemon.signed):
  the emulated wire from a trigger board on another host;
- its info file (rig.daemon.paths), written once all of that serves, removed at a clean exit;
- an mDNS advertisement (`_rigcam._tcp.local.`, rig.cameras.discovery), unless disabled;
- sd_notify READY once the camera acquires and WATCHDOG from the acquisition loop (rig.daemon.notify),
  so systemd restarts a daemon whose loop hangs.

The ring's heartbeat is renewed by the same loop: a supervisor (`rig up`) that sees it stop restarts
the daemon even when its process is still there. Work that blocks the loop for longer on purpose
(opening the camera again with new settings, asking a lost camera whether it is back) keeps the
heartbeat going from a thread of its own for at most BUSY_LIMIT_S: longer than that is a hang too.
"""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import json
import os
import socket
import threading
import time
from typing import Any, Optional

import numpy as np

from common.files import atomic_write_json
from rig.cameras import open_camera
from rig.cameras.daemon import TRIGGER, verify
from rig.config import RigConfig
from rig.daemon import paths
from rig.daemon.ring import FrameRing, RingError
from rig.errors import CameraDisconnected, CameraTimeout, ConfigError, DeviceError
from sync.frames import monotonic_ns

LOOPBACK = ("127.0.0.1", "localhost", "::1")

WATCH_S = 5.0  # a doorbell subscription lapses unless renewed
# A reader may fall behind (a busy host: a session's threads wait for the GIL, its disk for writes): the
# ring keeps about a second of frames, within 64 MB, and at least 8.
RING_SECONDS = 1.0
RING_MAX_BYTES = 64 << 20
MIN_SLOTS = 8
HEARTBEAT_S = 0.2  # the heartbeat's period while slow work blocks the loop
BUSY_LIMIT_S = 60.0  # slow work that takes longer than this is treated as a hang (the heartbeat stops)


def default_slots(cfg) -> int:
    shape, dtype = ring_geometry(cfg)
    frame_bytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    return max(MIN_SLOTS, min(int(np.ceil(cfg.fps * RING_SECONDS)), RING_MAX_BYTES // max(frame_bytes, 1)))
RECONNECT_EVERY_S = 1.0
# what the API may change while the daemon runs, and the range each takes
SETTINGS = {"exposure_us": (1.0, 10_000_000.0), "gain": (0.0, 48.0), "fps": (0.1, 1000.0)}
TRIGGER_MODES = ("free", "software", "hardware")


def ring_geometry(cfg) -> tuple[tuple[int, ...], str]:
    """The frame shape and dtype a camera's configuration gives (backends convert Bayer to RGB)."""
    if cfg.pixel_format == "Mono8":
        return (cfg.height, cfg.width), "uint8"
    if cfg.pixel_format == "Mono16":
        return (cfg.height, cfg.width), "uint16"
    return (cfg.height, cfg.width, 3), "uint8"


class CameraDaemon:
    def __init__(self, config: RigConfig, camera: str, *, host: str = "127.0.0.1", port: int = 0, token: Optional[str] = None,
                 advertise: bool = True, interfaces: Optional[list[str]] = None, slots: Optional[int] = None):
        self.config = config
        self.cfg = config.camera(camera)
        self.host, self.port, self.token = host, port, token
        self.advertise, self.interfaces = advertise, interfaces
        self.slots = slots or default_slots(self.cfg)
        self.camera = None
        self.ring: Optional[FrameRing] = None
        self.state = "starting"  # starting | running | stopped (acquisition paused) | lost | closing
        self.acquiring = threading.Event()
        self.stop_event = threading.Event()
        self._lock = threading.RLock()  # the camera object: replaced by a settings change
        self.counters = collections.Counter()
        self.events: collections.deque = collections.deque(maxlen=50)
        self.started_ns = monotonic_ns()
        self.last_frame_ns = 0
        self._recent: collections.deque = collections.deque(maxlen=64)  # host times of the last frames: fps
        self._trigger_sock: Optional[socket.socket] = None
        self._net_trigger_sock: Optional[socket.socket] = None
        self._watchers: dict[tuple, float] = {}  # doorbell subscribers -> lapse time (monotonic s)
        self.api = None
        self._advert = None

    # --- what the API reads and does ---------------------------------------------------------------
    def event(self, kind: str, detail: str) -> None:
        self.events.append({"kind": kind, "detail": detail, "time_ns": monotonic_ns()})

    def status(self) -> dict[str, Any]:
        now = monotonic_ns()
        recent = list(self._recent)
        fps = (len(recent) - 1) / ((recent[-1] - recent[0]) / 1e9) if len(recent) > 1 and recent[-1] > recent[0] else 0.0
        cam = self.camera
        return {
            "rig": self.config.name, "camera": self.cfg.name, "role": self.cfg.role, "uri": self.cfg.uri, "pid": os.getpid(),
            "state": self.state, "frames": self.ring.latest() if self.ring else 0, "fps": round(fps, 2),
            "last_frame_age_s": None if not self.last_frame_ns else round((now - self.last_frame_ns) / 1e9, 3),
            "uptime_s": round((now - self.started_ns) / 1e9, 3), "ring": str(self.ring.path) if self.ring else None,
            "slots": self.slots, "trigger": self.cfg.trigger, "trigger_port": self.trigger_port,
            "network_trigger_port": self.network_trigger_port,
            "camera_stats": cam.stats.to_dict() if cam is not None else {}, "counters": dict(self.counters),
            "events": list(self.events)[-10:],
        }

    def settings(self) -> dict[str, Any]:
        c = self.cfg
        return {"width": c.width, "height": c.height, "pixel_format": c.pixel_format, "fps": c.fps, "trigger": c.trigger,
                "exposure_us": c.exposure_us, "gain": c.gain}

    def change_settings(self, changes: dict[str, Any]) -> dict[str, Any]:
        """Apply new exposure / gain / frame rate / trigger mode: the camera is opened again with them
        (every backend takes its settings at open). Bad values raise ConfigError, nothing changed."""
        new = {}
        for key, value in changes.items():
            if key == "trigger":
                if value not in TRIGGER_MODES:
                    raise ConfigError(f"trigger must be one of {', '.join(TRIGGER_MODES)}, got {value!r}")
                new[key] = value
                continue
            if key not in SETTINGS:
                fixed = " (the frame size and format need a new config and a restart)" if key in ("width", "height", "pixel_format") else ""
                raise ConfigError(f"unknown setting {key!r}{fixed}; settable: {', '.join([*SETTINGS, 'trigger'])}")
            lo, hi = SETTINGS[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (lo <= float(value) <= hi):
                raise ConfigError(f"{key} must be a number from {lo:g} to {hi:g}, got {value!r}")
            new[key] = float(value)
        if not new:
            return self.settings()
        cfg = dataclasses.replace(self.cfg, **new)
        cfg.rig = self.cfg.rig
        with self._busy(), self._lock:
            was = self.acquiring.is_set()
            self._close_camera()
            self.cfg = cfg
            self._open_camera(start=was)
        self.event("settings", f"settings changed: {json.dumps(new)}")
        return self.settings()

    def start_acquisition(self) -> None:
        with self._busy(), self._lock:
            if not self.acquiring.is_set():
                self.camera.start()
                self.acquiring.set()
                self.state = "running"
                self.event("started", "acquisition started")

    def stop_acquisition(self) -> None:
        with self._busy(), self._lock:
            if self.acquiring.is_set():
                self.acquiring.clear()
                self.camera.stop()
                self.state = "stopped"
                self.event("stopped", "acquisition stopped")

    def software_trigger(self) -> None:
        if self.cfg.trigger != "software":
            raise ConfigError(f"camera {self.cfg.name} is in '{self.cfg.trigger}' trigger mode, not software")
        cam = self.camera
        if cam is None or not self.acquiring.is_set():
            raise DeviceError(f"camera {self.cfg.name} is not acquiring")
        cam.software_trigger()

    @property
    def trigger_port(self) -> Optional[int]:
        return self._trigger_sock.getsockname()[1] if self._trigger_sock else None

    @property
    def network_trigger_port(self) -> Optional[int]:
        return self._net_trigger_sock.getsockname()[1] if self._net_trigger_sock else None

    # --- lifecycle ---------------------------------------------------------------------------------
    @contextlib.contextmanager
    def _busy(self):
        """Keeps the ring's heartbeat fresh while slow work blocks the acquisition loop (at most
        BUSY_LIMIT_S), so a supervisor watching it tells slow work from a hang."""
        done = threading.Event()

        def beat() -> None:
            end = time.monotonic() + BUSY_LIMIT_S
            while not done.wait(HEARTBEAT_S) and time.monotonic() < end:
                if self.ring is not None:
                    self.ring.heartbeat()

        beater = threading.Thread(target=beat, name="rig-daemon-busy", daemon=True)
        beater.start()
        try:
            yield
        finally:
            done.set()
            beater.join()

    def _open_camera(self, start: bool = True) -> None:
        self.camera = open_camera(self.cfg)
        self.camera.prepare()
        if start:
            self.camera.start()
            self.acquiring.set()
            self.state = "running"

    def _close_camera(self) -> None:
        cam, self.camera = self.camera, None
        self.acquiring.clear()
        if cam is not None:
            try:
                cam.stop()
            finally:
                cam.close()

    def open(self) -> "CameraDaemon":
        """Camera, ring, trigger input, API, info file, advertisement; then READY."""
        from rig.daemon import api, notify

        shape, dtype = ring_geometry(self.cfg)
        self.ring = FrameRing.create(paths.ring_path(self.config.name, self.cfg.name), slots=self.slots, height=shape[0],
                                     width=shape[1], channels=shape[2] if len(shape) == 3 else 1, dtype=dtype,
                                     pixel_format=self.cfg.pixel_format, camera=self.cfg.name)
        self._open_camera(start=True)
        self._trigger_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._trigger_sock.bind(("127.0.0.1", 0))
        self._trigger_sock.settimeout(0.2)
        threading.Thread(target=self._trigger_loop, args=(self._trigger_sock, False), name="rig-daemon-trigger", daemon=True).start()
        if self.token and self.host not in LOOPBACK:
            self._net_trigger_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._net_trigger_sock.bind((self.host, 0))
            self._net_trigger_sock.settimeout(0.2)
            threading.Thread(target=self._trigger_loop, args=(self._net_trigger_sock, True), name="rig-daemon-net-trigger", daemon=True).start()
        self.api = api.serve(self, self.host, self.port, self.token)
        self.ring.heartbeat()  # opening the camera took a while: the loop renews it from here on
        self._publish()
        if self.advertise:
            self._advertise()
        notify.ready(f"camera {self.cfg.name} acquiring into {self.ring.path}")
        self.event("ready", f"acquiring into {self.ring.path}, API {self.api.url}")
        return self

    def _publish(self) -> None:
        """The info file: how to reach this daemon, and whether its camera is there (`state`)."""
        atomic_write_json(paths.info_path(self.config.name, self.cfg.name), {
            "rig": self.config.name, "camera": self.cfg.name, "pid": os.getpid(), "uri": self.cfg.uri, "role": self.cfg.role,
            "api": self.api.url, "trigger_port": self.trigger_port, "ring": str(self.ring.path), "state": self.state,
            "token_required": self.token is not None, "started_ns": self.started_ns,
        })

    def _advertise(self) -> None:
        try:
            from rig.cameras.discovery import DaemonInfo, advertise

            device = getattr(self.camera, "device_info", None)
            info = DaemonInfo(rig=self.config.name, camera=self.cfg.name, role=self.cfg.role, uri=self.cfg.uri,
                              model=str(getattr(device, "model", "") or ""), serial=str(getattr(device, "serial", "") or ""),
                              shm=str(self.ring.path), host=self.host, port=self.api.port, pid=os.getpid(),
                              token_required=self.token is not None)
            self._advert = advertise(info, interfaces=self.interfaces, wait=False)
        except Exception as exc:  # noqa: BLE001 - no multicast here: the daemon still serves
            self.event("advertise_failed", f"not advertised on mDNS: {exc}")

    def run(self) -> None:
        """The acquisition loop, until stop_event (SIGTERM / SIGINT from the command)."""
        from rig.daemon import notify

        watchdog = notify.Watchdog()
        next_reconnect = 0.0
        while not self.stop_event.is_set():
            self.ring.heartbeat()
            watchdog.tick()
            if not self.acquiring.is_set():
                time.sleep(0.05)
                continue
            with self._lock:
                cam = self.camera
                if cam is None:
                    continue
                if self.state == "lost":
                    if time.monotonic() >= next_reconnect:
                        next_reconnect = time.monotonic() + RECONNECT_EVERY_S
                        with self._busy():
                            back = self._reconnect(cam)
                        if back:
                            self.state = "running"
                            self.event("camera_back", f"camera {self.cfg.name} is back")
                            self._publish()
                    else:
                        time.sleep(0.05)
                    continue
                try:
                    frame = cam.get_frame(timeout=0.2)
                except CameraTimeout:
                    continue
                except CameraDisconnected as exc:
                    self.state = "lost"
                    self.counters["lost"] += 1
                    self.event("camera_lost", str(exc))
                    self._publish()
                    continue
            try:
                # the doorbells ring once the slot is marked, before the copy: a reader's wake-up
                # overlaps the write (rig.daemon.client)
                self.ring.write(frame, started=self._ring_doorbells)
            except RingError as exc:
                self.counters["ring_errors"] += 1
                if self.counters["ring_errors"] == 1:
                    self.event("ring_error", str(exc))
                continue
            self.last_frame_ns = monotonic_ns()
            self._recent.append(self.last_frame_ns)

    def _ring_doorbells(self) -> None:
        if not self._watchers:
            return
        now = time.monotonic()
        for address, until in list(self._watchers.items()):
            if until < now:
                self._watchers.pop(address, None)
                continue
            try:
                self._trigger_sock.sendto(b"F", address)
            except OSError:
                self._watchers.pop(address, None)

    @staticmethod
    def _reconnect(cam) -> bool:
        try:
            return bool(cam.reconnect())
        except Exception:  # noqa: BLE001 - a backend failing to reopen: still lost, try again later
            return False

    def _trigger_loop(self, sock: socket.socket, tagged: bool) -> None:
        while not self.stop_event.is_set() and sock is not None:
            try:
                data, address = sock.recvfrom(128)
            except socket.timeout:
                continue
            except OSError:
                return
            if tagged:  # from another host: only what carries the token's tag
                data = verify(self.token, data)
                if data is None:
                    self.counters["unauthorised_trigger_datagrams"] += 1
                    continue
            elif data == b"W":  # a reader's doorbell subscription
                self._watchers[address] = time.monotonic() + WATCH_S
                continue
            if len(data) != TRIGGER.size:
                self.counters["bad_trigger_datagrams"] += 1
                continue
            kind, pulse, host_ns = TRIGGER.unpack(data)
            cam = self.camera
            if cam is None or not self.acquiring.is_set():
                continue
            try:
                if kind == b"H":
                    cam.hardware_trigger(pulse, host_ns)
                elif kind == b"S" and self.cfg.trigger == "software":
                    cam.software_trigger()
                else:
                    self.counters["bad_trigger_datagrams"] += 1
            except (DeviceError, NotImplementedError):
                self.counters["trigger_errors"] += 1

    def close(self) -> None:
        from rig.daemon import notify

        self.state = "closing"
        notify.stopping()
        self.stop_event.set()
        for step in (lambda: self._advert and self._advert.close(), lambda: self.api and self.api.stop(),
                     lambda: paths.info_path(self.config.name, self.cfg.name).unlink(missing_ok=True),
                     self._close_camera, lambda: self._trigger_sock and self._trigger_sock.close(),
                     lambda: self._net_trigger_sock and self._net_trigger_sock.close(),
                     lambda: self.ring and self.ring.close()):
            try:
                step()
            except Exception:  # noqa: BLE001 - closing: every step is tried
                pass
