"""`sim://NAME`: a virtual camera with the full camera contract, drawing images from the simulator.

Timing model (all on the host monotonic clock, which is also the simulator's clock while live):
an exposure request arrives (free-run tick at `fps`, a software trigger, or a hardware trigger edge
at `time_ns`); exposure starts after the trigger latency plus Gaussian jitter; the frame is read out
when the exposure ends and is delivered then. Every exposure increments the device frame id, so a
dropped frame (sensor option `drop_rate`) leaves a gap in the ids as it does on real cameras. The
device timestamp comes from the camera's own clock (offset `clock_offset_ns`, drift `drift_ppm`).

For sync tests the camera records which trigger pulse each exposure answered:
`truth_pulse[frame_id] = pulse_index` (hardware trigger) — the simulator's ground truth.
"""
from __future__ import annotations

import heapq
import itertools
import queue
import threading
import time
import zlib
from typing import TYPE_CHECKING, Callable, Optional

import numpy as np

from rig.cameras.base import Camera, DeviceInfo
from rig.cameras.pixels import demosaic, from_rgb, is_bayer
from rig.errors import CameraDisconnected, CameraTimeout, ConfigError
from rig.progress import ProgressBar
from rig.sim.clock import SIM_EPOCH_NS
from simulator.options import with_defaults
from sync.frames import Frame, monotonic_ns

if TYPE_CHECKING:  # annotations only: rig.config imports the camera backends to check a camera's settings
    from rig.config import CameraConfig

SCHEME = "sim"
DEFAULT_NAMES = ("left", "sup1", "sup2", "sup3", "sup4", "right")

ImageSource = Callable[[float, float, np.random.Generator], np.ndarray]


def discover() -> list[DeviceInfo]:
    """The virtual cameras of the default simulated rig (always present)."""
    return [
        DeviceInfo(uri=f"sim://{n}", backend=SCHEME, model="virtual camera", serial=f"SIM-{n.upper()}", vendor="rig simulator")
        for n in DEFAULT_NAMES
    ]


def open(uri: str, settings: CameraConfig, source: Optional[ImageSource] = None) -> "SimCamera":  # noqa: A001
    return SimCamera(uri, settings, source=source)


def synthetic_source(width: int, height: int, seed: int) -> ImageSource:
    """A cheap moving test pattern (used where no scene renderer is wanted)."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    base = np.random.default_rng(seed).integers(0, 64, size=(height, width), dtype=np.uint8).astype(np.float32)

    def render(t: float, exposure_s: float, rng: np.random.Generator) -> np.ndarray:
        phase = (xx + 60.0 * t * 30.0) % 64.0
        bars = np.where(phase < 32.0, 160.0, 60.0)
        img = np.clip(bars + base + 20.0 * np.sin(yy / 23.0 + t), 0, 255).astype(np.uint8)
        return np.repeat(img[:, :, None], 3, axis=2)

    return render


class SimCamera(Camera):
    """A virtual camera; thread-safe between one consumer (get_frame) and trigger producers."""

    QUEUE_FRAMES = 64  # host-side buffer pool; overflow loses frames as a real driver would

    def __init__(self, uri: str, settings: CameraConfig, source: Optional[ImageSource] = None):
        super().__init__(uri, settings)
        self.device_name = uri.split("://", 1)[1].strip("/")
        if not self.device_name:
            raise ConfigError(f"{uri}: a sim URI names the virtual camera, e.g. sim://left")
        self.opts = with_defaults(settings.sim, "camera")
        seed = (int(self.opts["seed"]) * 1_000_003 + zlib.crc32(self.device_name.encode())) & 0x7FFFFFFF
        self.rng = np.random.default_rng(seed)
        self.sensor = None
        if source is None:
            source = self._scene_source(settings, seed)
        self.source = source
        self.exposure_s = (settings.exposure_us or 5000.0) * 1e-6
        # What the image source renders at (a replayed loop is rendered once, at the opening exposure
        # and gain); a control changed while acquiring scales the rendered signal, as a linear sensor does.
        self._rendered_exposure_s = self.exposure_s
        self.gain_db = float(settings.gain or 0.0)
        self._rendered_gain_db = self.gain_db
        self.truth_pulse: dict[int, int] = {}
        self._requests: list[tuple[int, int, Optional[int]]] = []  # heap of (expose_ns, seq, pulse)
        self._seq = itertools.count()
        self._cv = threading.Condition()
        self._out: queue.Queue = queue.Queue(maxsize=self.QUEUE_FRAMES)
        self._running = False
        self._closed = False
        self._unplugged = False
        self._back_at: Optional[float] = None
        self._vanished_once = False
        self._thread: Optional[threading.Thread] = None
        self._frame_counter = 0
        self._opened_slowly = False
        self._start_ns = 0
        self._last_exposure_end_ns = 0
        self._session = getattr(settings, "calibration_session", None)

    def _scene_source(self, settings: CameraConfig, seed: int) -> ImageSource:
        """The simulated scene seen by this camera of its rig, or a plain test pattern for a lone camera."""
        session = getattr(settings, "calibration_session", None)
        if session is not None:  # see calibration_session(): the board at its stations, no people
            self.sensor = session.sensor(settings.name)
            return self.sensor.image_source()
        rig = getattr(settings, "rig", None)
        if rig is None:
            return synthetic_source(settings.width, settings.height, seed)
        from simulator.sensor import sim_rig

        self.sensor = sim_rig(rig).sensor(settings.name)
        return self.sensor.image_source()

    # --- exposure and gain while acquiring -------------------------------------------------------------
    GAIN_DB = (0.0, 24.0)

    def exposure_range_us(self) -> tuple[float, float]:
        """From 20 us to the frame period (a sensor cannot expose longer than one frame at its rate)."""
        return (20.0, 1e6 / self.settings.fps if self.settings.fps else 1e6)

    def controls(self) -> dict:
        return {"exposure_us": round(self.exposure_s * 1e6, 3), "gain": self.gain_db,
                "ranges": {"exposure_us": list(self.exposure_range_us()), "gain": list(self.GAIN_DB)}, "live": True}

    def set_controls(self, exposure_us=None, gain=None) -> dict:
        from rig.cameras.base import check_control

        new_exposure = None if exposure_us is None else check_control(self.name, "exposure_us", exposure_us, self.exposure_range_us())
        new_gain = None if gain is None else check_control(self.name, "gain", gain, self.GAIN_DB)
        with self._cv:  # both or neither
            if new_exposure is not None:
                self.exposure_s = new_exposure * 1e-6
            if new_gain is not None:
                self.gain_db = new_gain
        return self.controls()

    def scene_time(self, t: float) -> float:
        """The scene time an exposure starting at simulated time t shows (the loop replays frames)."""
        if self.sensor is None:
            return t + self.exposure_s / 2
        looped = bool(getattr(self.sensor, "loop_frames", 0))
        return self.sensor.scene_time(t, self._rendered_exposure_s if looped else self.exposure_s)

    # --- clocks ------------------------------------------------------------------------------------
    def device_time_ns(self, host_ns: int) -> int:
        """This camera's clock reading at host monotonic time `host_ns`."""
        rel = host_ns - SIM_EPOCH_NS
        return int(rel * (1.0 + self.opts["drift_ppm"] * 1e-6)) + int(self.opts["clock_offset_ns"])

    # --- lifecycle -------------------------------------------------------------------------------
    def prepare(self) -> None:
        """Make the pre-rendered loop, if the scene is replayed from one: replay is real-time,
        rendering is not. The loop cache makes a repeated start quick; a first one shows a progress
        bar on a terminal. `start` does it too; a rig prepares all its cameras first, so that they
        then start together."""
        if self.opts["open_s"] > 0 and not self._opened_slowly:
            self._opened_slowly = True  # an emulated device that takes its time to open, once per open
            time.sleep(self.opts["open_s"])
        if self.sensor is not None and getattr(self.sensor, "loop_frames", 0):
            with ProgressBar(f"{self.name}: pre-rendering the simulated scene") as bar:
                self.sensor.prerender(self.exposure_s, progress=bar.update)

    def start(self) -> None:
        self._check_alive()
        if self._running:
            return
        self.prepare()
        self._running = True
        self._start_ns = monotonic_ns()
        self._thread = threading.Thread(target=self._run, name=f"sim-camera-{self.name}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        with self._cv:
            self._running = False
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def close(self) -> None:
        self.stop()
        self._closed = True

    def unplug(self) -> None:
        """Make the camera vanish as if its cable were pulled: frames stop, get_frame reports it."""
        back = self.opts["reconnect_after_s"]
        self._back_at = time.monotonic() + back if back > 0 else None
        self._unplugged = True
        with self._cv:
            self._cv.notify_all()

    def reconnect(self) -> bool:
        """A vanished camera is back once `reconnect_after_s` has passed: acquisition restarts with
        the same settings (frames queued before it vanished are gone, as with a real device)."""
        if not self._unplugged:
            return True
        if self._closed or self._back_at is None or time.monotonic() < self._back_at:
            return False
        self.stop()
        while not self._out.empty():
            self._out.get_nowait()
        with self._cv:
            self._requests.clear()
            self._unplugged = False
        self._vanished_once = True  # it does not vanish again on its own
        self._opened_slowly = False  # opening it again takes open_s again
        self.start()
        return True

    # --- triggers --------------------------------------------------------------------------------
    def software_trigger(self) -> None:
        self._check_alive()
        if self.settings.trigger != "software":
            raise ConfigError(f"{self.name}: software trigger fired but the camera is in '{self.settings.trigger}' mode")
        self._request(monotonic_ns(), None)

    def hardware_trigger(self, pulse_index: int, time_ns: int) -> None:
        if self.settings.trigger != "hardware" or self._unplugged:
            return  # a camera not in hardware-trigger mode ignores its input line
        self._request(time_ns, pulse_index)

    def _request(self, trigger_ns: int, pulse: Optional[int]) -> None:
        latency_ns = self.opts["latency_us"] * 1e3
        if self.opts["jitter_us"] > 0:
            latency_ns += abs(self.rng.normal(0.0, self.opts["jitter_us"] * 1e3))
        with self._cv:
            heapq.heappush(self._requests, (int(trigger_ns + latency_ns), next(self._seq), pulse))
            self._cv.notify_all()

    # --- frames ----------------------------------------------------------------------------------
    def _read_frame(self, timeout: float) -> Frame:
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self._out.get(timeout=min(0.05, max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                if self._unplugged:
                    raise CameraDisconnected(f"{self.name} ({self.uri}): camera disconnected") from None
                if self._closed:
                    raise CameraDisconnected(f"{self.name} ({self.uri}): camera is closed") from None
                if time.monotonic() >= deadline:
                    self.stats.timeouts += 1
                    raise CameraTimeout(f"{self.name} ({self.uri}): no frame within {timeout:.3f} s") from None

    def _check_alive(self) -> None:
        if self._closed:
            raise CameraDisconnected(f"{self.name} ({self.uri}): camera is closed")
        if self._unplugged:
            raise CameraDisconnected(f"{self.name} ({self.uri}): camera disconnected")

    def _next_free_run(self, k: int) -> int:
        return self._start_ns + int(round(k * 1e9 / self.settings.fps))

    def _run(self) -> None:
        vanish = self.opts["disconnect_after_s"]
        if vanish > 0 and not self._vanished_once:
            timer = threading.Timer(vanish, self.unplug)
            timer.daemon = True
            timer.start()
        free = self.settings.trigger == "free"
        tick = itertools.count()
        next_tick = self._next_free_run(next(tick)) if free else None
        while True:
            with self._cv:
                while self._running and not self._unplugged:
                    due = self._requests[0][0] if self._requests else None
                    if free and (due is None or next_tick < due):
                        due = next_tick
                    if due is not None:
                        wait_ns = due + int(self.exposure_s * 1e9) - monotonic_ns()  # readout at exposure end
                        if wait_ns <= 0:
                            break
                        self._cv.wait(wait_ns / 1e9)
                    else:
                        self._cv.wait(0.1)
                if not self._running or self._unplugged:
                    return
                if free and (not self._requests or next_tick <= self._requests[0][0]):
                    expose_ns, pulse = next_tick, None
                    next_tick = self._next_free_run(next(tick))
                else:
                    expose_ns, _, pulse = heapq.heappop(self._requests)
            self._expose(expose_ns, pulse)

    def _expose(self, expose_ns: int, pulse: Optional[int]) -> None:
        if expose_ns < self._last_exposure_end_ns:
            return  # the sensor is still busy with the previous exposure: this trigger is ignored
        self._last_exposure_end_ns = expose_ns + int(self.exposure_s * 1e9)
        self._frame_counter += 1
        frame_id = self._frame_counter
        if pulse is not None:
            self.truth_pulse[frame_id] = pulse
        if self.opts["drop_rate"] > 0 and self.rng.random() < self.opts["drop_rate"]:
            return  # lost between sensor and host: the id gap tells the host
        t = (expose_ns - SIM_EPOCH_NS) / 1e9
        if self._session is not None:
            # A calibration session counts time in views: exposure k shows station k, whatever the
            # host clock says (every camera of the rig is triggered once per synchronised view).
            t = self._session.scene_time(frame_id - 1)
        # A replayed loop, or a test pattern, is rendered at the opening exposure: scale it; a scene
        # rendered per frame integrates the exposure itself (its motion blur too).
        fixed = self.sensor is None or bool(getattr(self.sensor, "loop_frames", 0))
        rgb = self.source(t, self._rendered_exposure_s if fixed else self.exposure_s, self.rng)
        scale = (self.exposure_s / self._rendered_exposure_s if fixed else 1.0) * 10.0 ** ((self.gain_db - self._rendered_gain_db) / 20.0)
        if scale != 1.0:
            rgb = np.clip(rgb.astype(np.float32) * np.float32(scale) + 0.5, 0, 255).astype(np.uint8)
        s = self.settings
        raw = from_rgb(rgb, s.pixel_format)  # what the sensor sends, decoded as a real backend decodes it
        image = demosaic(raw, s.pixel_format) if is_bayer(s.pixel_format) else raw
        frame = Frame(
            image=image,
            camera=self.name,
            frame_id=frame_id,
            device_ts_ns=self.device_time_ns(expose_ns),
            host_ts_ns=monotonic_ns(),
            pixel_format=s.pixel_format,
            exposure_us=self.exposure_s * 1e6,
            sim_time_s=self.scene_time(t),
        )
        try:
            self._out.put_nowait(frame)
        except queue.Full:
            pass  # host did not keep up: this frame is lost, the id gap shows it
