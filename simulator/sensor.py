"""Virtual image sensors: exposure with motion blur, gain, shot and read noise, colour filter array,
trigger latency with jitter, a drifting device clock and random frame drops.

Brightness model: the renderer's radiance 1.0 fills the 8-bit range at the nominal exposure
(NOMINAL_EXPOSURE_S) and gain 0 dB; the digital number scales with exposure time and gain (dB) and
clips at 255. Noise: shot noise is Poisson in electrons (`full_well` electrons at full scale at
gain 0 dB, so its variance in digital numbers grows with the signal and with the gain), read noise
is Gaussian with `read_noise` DN of standard deviation; `shot_noise` scales the first.

Two ways to get images:
- live: each exposure renders the scene (several renders over the exposure when motion_blur);
- loop (`loop_frames` > 0): the first use renders that many frames once, at `loop_fps`, with their
  motion blur; later exposures replay frame round(t * loop_fps) mod loop_frames, fast enough for
  real-time tests of the capture path (the renderer is not). The noise of a replayed frame is one
  of `noise_variants` realisations drawn at prerender (no cost per frame), or, with
  noise_variants = 0, drawn fresh for every frame (a few ms per 1280x720 frame). A rendered loop is
  kept on disk (simulator.loop_cache), so the next start with the same scene, camera and sensor
  loads it instead of rendering it.

Every random draw comes from the generator the caller passes, or from `frame_rng(index)`, so a
capture is a pure function of (scene seed, sensor seed, camera, frame index).
"""
from __future__ import annotations

import math
import threading
import zlib
from dataclasses import dataclass
from typing import Callable, Optional

import cv2
import numpy as np

from calibration.camera import CameraModel
from common.bayer import demosaic, mosaic
from simulator import loop_cache
from simulator.errors import SimulatorError
from simulator.options import validate_options
from simulator.render import render

NOMINAL_EXPOSURE_S = 0.005  # exposure at which radiance 1.0 is full scale (gain 0 dB)
LOOP_SCALE = 200.0  # stored loop frames: uint8 = radiance * LOOP_SCALE (headroom for highlights)

ImageSource = Callable[[float, float, np.random.Generator], np.ndarray]
Progress = Callable[[int, int], None]  # (frames done, frames in all)


@dataclass
class Capture:
    """One triggered exposure: when it really started, what the device clock said, the image
    (None when the frame was dropped)."""

    frame_index: int
    trigger_s: float
    exposure_start_s: float
    exposure_s: float
    device_ts_ns: int
    image: Optional[np.ndarray]

    @property
    def dropped(self) -> bool:
        return self.image is None


class SensorModel:
    """The sensor of one simulated camera looking at `scene` through `camera` (ground truth).

    options: a camera's `sim = {...}` table (simulator.options.CAMERA_OPTIONS).
    scene: a Scene, or a function that makes one, called at the first render (building a scene's
    textures takes a while, and a loop found in the loop cache needs none); with a function,
    `scene_key` says what the scene is made from (for the loop cache; None: no caching).
    """

    def __init__(self, scene, camera: CameraModel, options: Optional[dict] = None, *, gain_db: float = 0.0,
                 loop_frames: int = 0, loop_fps: float = 30.0, antialias: Optional[int] = None, noise_variants: int = 0,
                 scene_key: Optional[dict] = None):
        try:
            self.opts = validate_options(dict(options or {}), "camera")
        except ValueError as exc:
            raise SimulatorError(f"camera {camera.name}: sim.{exc}") from None
        if not math.isfinite(gain_db) or not -20.0 <= gain_db <= 48.0:
            raise SimulatorError(f"camera {camera.name}: gain must be between -20 and 48 dB, got {gain_db}")
        if loop_frames < 0 or (loop_frames > 0 and not loop_fps > 0):
            raise SimulatorError(f"camera {camera.name}: loop_frames must be >= 0 and loop_fps positive")
        self._scene = scene
        self._scene_key = scene_key if callable(scene) else loop_cache.scene_fingerprint(scene)
        self.camera = camera
        self.gain = 10.0 ** (gain_db / 20.0)
        self.loop_frames = int(loop_frames)
        self.loop_fps = float(loop_fps)
        self.noise_variants = int(noise_variants)
        self.antialias = antialias
        self._seed = (int(self.opts["seed"]) * 1_000_003 + zlib.crc32(camera.name.encode())) & 0x7FFFFFFF
        self._loop: Optional[np.ndarray] = None
        self._loop_exposure_s: Optional[float] = None
        self._noise_bank: Optional[np.ndarray] = None
        self._noise_bank16: Optional[np.ndarray] = None
        self._loop_clean: Optional[np.ndarray] = None
        self._loop_sigma16: Optional[np.ndarray] = None
        self._variants: Optional[list] = None
        self.loop_origin: Optional[str] = None  # "render" or "cache" once the loop is made
        self._lock = threading.RLock()  # prerender draws noise under it
        self.led = None  # a FlashLed in view (SimRig sets it when the scene has one)
        self._led_cover: Optional[np.ndarray] = None

    @property
    def scene(self):
        if callable(self._scene):  # made on first use (a Scene itself is not callable)
            with self._lock:
                if callable(self._scene):
                    self._scene = self._scene()
        return self._scene

    # ---- randomness -------------------------------------------------------------------------
    def frame_rng(self, frame_index: int) -> np.random.Generator:
        """The generator of one frame's random draws (noise, jitter, drop)."""
        return np.random.default_rng([self._seed, int(frame_index) & 0xFFFFFFFFFFFF])

    # ---- timing -----------------------------------------------------------------------------
    def exposure_start(self, trigger_s: float, rng: np.random.Generator) -> float:
        """Start of the exposure a trigger at `trigger_s` causes: latency plus |Gaussian jitter|."""
        latency = self.opts["latency_us"] * 1e-6
        if self.opts["jitter_us"] > 0:
            latency += abs(rng.normal(0.0, self.opts["jitter_us"] * 1e-6))
        return trigger_s + latency

    def device_time_ns(self, t_s: float) -> int:
        """The camera's clock at simulated time t_s: offset plus drift (ppm)."""
        return int(round(t_s * 1e9 * (1.0 + self.opts["drift_ppm"] * 1e-6))) + int(self.opts["clock_offset_ns"])

    def dropped(self, rng: np.random.Generator) -> bool:
        return self.opts["drop_rate"] > 0 and rng.random() < self.opts["drop_rate"]

    # ---- images -----------------------------------------------------------------------------
    def radiance(self, t_start_s: float, exposure_s: float) -> np.ndarray:
        """Linear image integrated over the exposure (float32 HxWx3, 1.0 = full scale nominally)."""
        if t_start_s < 0:
            raise SimulatorError(f"time must be >= 0, got {t_start_s}")
        if not exposure_s > 0:
            raise SimulatorError(f"exposure must be positive, got {exposure_s}")
        n = int(self.opts["blur_samples"]) if self.opts["motion_blur"] else 1
        acc = None
        for i in range(n):  # stratified instants over [t, t + exposure]
            r = render(self.scene, self.camera, t_start_s + (i + 0.5) / n * exposure_s, antialias=self.antialias)
            acc = r.radiance.copy() if acc is None else acc + r.radiance
        return acc if n == 1 else acc * (1.0 / n)

    def digitise(self, radiance: np.ndarray, exposure_s: float, rng: np.random.Generator, raw: bool = False,
                 fast_noise: bool = False) -> np.ndarray:
        """Exposure, gain, noise and quantisation of a radiance image: RGB uint8 (or the Bayer
        mosaic when `raw` and the sensor has a colour filter array)."""
        dn, var = self._signal(radiance, exposure_s)
        noise = self._noise(dn.shape, rng) if fast_noise else rng.standard_normal(dn.shape, dtype=np.float32)
        dn += np.sqrt(var) * noise
        return self._through_filter(np.clip(dn + 0.5, 0.0, 255.0).astype(np.uint8), raw)

    def _through_filter(self, img: np.ndarray, raw: bool) -> np.ndarray:
        """A sensor with a colour filter array sees one colour per pixel: the mosaic when `raw`, else
        the RGB its demosaic gives back (which keeps every sample)."""
        pattern = self.opts["bayer"]
        if not pattern:
            return img
        samples = mosaic(img, pattern)
        return samples if raw else demosaic(samples, pattern)

    def _signal(self, radiance: np.ndarray, exposure_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Mean digital number of each pixel and its noise variance (DN^2)."""
        k = exposure_s / NOMINAL_EXPOSURE_S * self.gain * 255.0
        dn = radiance * np.float32(k)
        # variance in DN: shot noise (electrons = dn / gain * full_well / 255) and read noise
        dn_per_electron = 255.0 * self.gain / self.opts["full_well"]
        var = np.maximum(dn, 0.0) * np.float32(self.opts["shot_noise"] ** 2 * dn_per_electron) + np.float32(self.opts["read_noise"] ** 2)
        return dn, var

    def _noise(self, shape, rng):
        """Standard normal noise for the loop: a window at a random offset into a bank drawn once."""
        n = int(np.prod(shape))
        with self._lock:
            if self._noise_bank is None or self._noise_bank.size < 2 * n:
                self._noise_bank = np.random.default_rng([self._seed, 1 << 40]).standard_normal(2 * n, dtype=np.float32)
        off = int(rng.integers(0, self._noise_bank.size - n))
        return self._noise_bank[off:off + n].reshape(shape)

    def expose(self, t_start_s: float, exposure_s: float, rng: np.random.Generator, raw: bool = False) -> np.ndarray:
        """The image of an exposure starting at simulated time t_start_s (RGB uint8 HxWx3)."""
        image = self._expose_scene(t_start_s, exposure_s, rng, raw)
        return image if self.led is None or raw else self._with_led(image, t_start_s, exposure_s)

    def _with_led(self, image: np.ndarray, t_start_s: float, exposure_s: float) -> np.ndarray:
        """The LED in its dark housing drawn over a finished image (replayed loop frames included):
        the LED adds its disc's coverage times the part of the exposure it was lit (an LED is a step
        function of time, so a flash that starts mid-exposure lights the frame in proportion). It is
        drawn over the scene, so nothing passing in front hides it, and the lens does not blur it."""
        if self._led_cover is None:
            housing = self.led.footprint(self.camera, radius_m=LED_HOUSING_M)
            cover = self.led.footprint(self.camera)
            if housing is None or cover is None:
                self._led_cover = ()  # out of this camera's view
            else:
                rows, cols = np.nonzero(housing)
                box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
                self._led_cover = (box, housing[box][:, :, None], cover[box][:, :, None])
        if not self._led_cover:
            return image
        box, housing, cover = self._led_cover
        lit = self.led.lit_seconds(t_start_s, t_start_s + exposure_s, drawn=True)
        # radiance 1.0 is full scale over the nominal exposure: the light collected is level * lit time
        led = cover * np.float32(self.led.radiance_level * lit / NOMINAL_EXPOSURE_S * self.gain * 255.0)
        patch = image[box].astype(np.float32)
        patch = patch * (1 - housing) + np.float32(LED_HOUSING_DN) * housing + led
        out = image.copy()
        out[box] = np.clip(patch + 0.5, 0, 255).astype(np.uint8)
        return out

    def _expose_scene(self, t_start_s: float, exposure_s: float, rng: np.random.Generator, raw: bool) -> np.ndarray:
        if self.loop_frames > 0:
            if self._loop is None:
                self.prerender(exposure_s)
            if exposure_s == self._loop_exposure_s:
                return self._replay(t_start_s + exposure_s / 2, rng, raw)
            return self.digitise(self._loop_radiance(t_start_s + exposure_s / 2, exposure_s), exposure_s, rng, raw, fast_noise=True)
        return self.digitise(self.radiance(t_start_s, exposure_s), exposure_s, rng, raw)

    def scene_time(self, t_start_s: float, exposure_s: float) -> float:
        """The scene instant an exposure shows (its middle; in loop mode, the replayed frame's)."""
        t_mid = t_start_s + exposure_s / 2
        if self.loop_frames <= 0:
            return t_mid
        return (int(round(t_mid * self.loop_fps)) % self.loop_frames) / self.loop_fps + exposure_s / 2

    def image_source(self) -> ImageSource:
        """A callable (t, exposure_s, rng) -> RGB uint8, the image source of the sim:// backend."""
        return lambda t, exposure_s, rng: self.expose(max(0.0, t), exposure_s, rng)

    def capture(self, trigger_s: float, exposure_s: float, frame_index: int) -> Capture:
        """Everything one trigger produces, deterministic for (sensor seed, frame_index)."""
        rng = self.frame_rng(frame_index)
        start = self.exposure_start(trigger_s, rng)
        ts = self.device_time_ns(start)
        image = None if self.dropped(rng) else self.expose(start, exposure_s, rng)
        return Capture(frame_index, trigger_s, start, exposure_s, ts, image)

    # ---- pre-rendered loop ------------------------------------------------------------------
    def prerender(self, exposure_s: float = NOMINAL_EXPOSURE_S, progress: Optional[Progress] = None) -> None:
        """Make the loop now (otherwise the first exposure does it): load it from the loop cache, or
        render it (calling `progress(done, total)` after each frame) and keep it there."""
        with self._lock:
            if self._loop is not None:
                return
            shape = (self.loop_frames, self.camera.height, self.camera.width, 3)
            key = self.loop_cache_key(exposure_s)
            arrays = loop_cache.load(key, shape) if key is not None else None
            self.loop_origin = "cache"
            if arrays is None:
                arrays = self._render_loop(exposure_s, progress)
                self.loop_origin = "render"
                if key is not None:
                    loop_cache.store(key, arrays)
            self._loop, self._loop_exposure_s = arrays["frames"], exposure_s
            self._loop_clean, self._loop_sigma16 = arrays["clean"], arrays["sigma16"]
            self._variants = None
            if self.noise_variants > 0:
                rng = np.random.default_rng([self._seed, 1 << 42])
                variants = [[self._noisy(i, rng) for _ in range(self.noise_variants)] for i in range(self.loop_frames)]
                for per_frame in variants:
                    for img in per_frame:
                        img.flags.writeable = False  # shared between frames: consumers must not write into it
                self._variants = variants

    def loop_cache_key(self, exposure_s: float) -> Optional[str]:
        """Everything the rendered loop depends on (None: a scene the cache cannot describe). The
        noise variants are not in it: they are drawn from the cached arrays at every start."""
        if self._scene_key is None:
            return None
        return loop_cache.loop_key({
            "scene": self._scene_key, "camera": self.camera.to_dict(), "sensor": self.opts, "gain": self.gain,
            "antialias": self.antialias, "loop_frames": self.loop_frames, "loop_fps": self.loop_fps,
            "exposure_s": float(exposure_s), "loop_scale": LOOP_SCALE, "nominal_exposure_s": NOMINAL_EXPOSURE_S})

    def _render_loop(self, exposure_s: float, progress: Optional[Progress]) -> dict[str, np.ndarray]:
        """frames: radiance * LOOP_SCALE (for other exposures); clean: the noise-free digital image;
        sigma16: its per-pixel noise sigma in 1/16 DN."""
        H, W = self.camera.height, self.camera.width
        frames = np.empty((self.loop_frames, H, W, 3), np.uint8)
        clean = np.empty_like(frames)
        sigma16 = np.empty_like(frames)
        for i in range(self.loop_frames):
            rad = self.radiance(i / self.loop_fps, exposure_s)
            frames[i] = np.clip(rad * LOOP_SCALE + 0.5, 0, 255).astype(np.uint8)
            dn, var = self._signal(rad, exposure_s)
            clean[i] = np.clip(dn + 0.5, 0.0, 255.0).astype(np.uint8)
            sigma16[i] = np.clip(np.sqrt(var) * 16.0 + 0.5, 0, 255).astype(np.uint8)
            if progress is not None:
                progress(i + 1, self.loop_frames)
        return {"frames": frames, "clean": clean, "sigma16": sigma16}

    def _replay(self, t_mid_s: float, rng: np.random.Generator, raw: bool) -> np.ndarray:
        """A loop frame at the loop's own exposure with fresh noise, in a few vectorised uint8/int16
        passes (a few ms at 1280x720): the noise-free digital image plus its per-pixel noise sigma
        (in 1/16 DN) times a window of a standard-normal bank (in 1/16 units), saturated to uint8."""
        i = int(round(t_mid_s * self.loop_fps)) % self.loop_frames
        if self._variants is not None:  # cheapest: one of the noise realisations drawn at prerender
            return self._through_filter(self._variants[i][int(rng.integers(0, len(self._variants[i])))], raw)
        return self._through_filter(self._noisy(i, rng), raw)

    def _noisy(self, i: int, rng: np.random.Generator) -> np.ndarray:
        clean = self._loop_clean[i]
        n = clean.size
        with self._lock:
            if self._noise_bank16 is None or self._noise_bank16.size < 2 * n:
                z = np.random.default_rng([self._seed, 1 << 41]).standard_normal(2 * n, dtype=np.float32)
                self._noise_bank16 = np.clip(np.round(z * 16.0), -127, 127).astype(np.int16)
        off = int(rng.integers(0, self._noise_bank16.size - n))
        z = self._noise_bank16[off:off + n].reshape(clean.shape)
        noise = cv2.multiply(self._loop_sigma16[i], z, dtype=cv2.CV_16S, scale=1.0 / 256.0)
        return cv2.add(clean, noise, dtype=cv2.CV_8U)

    def _loop_radiance(self, t_mid_s: float, exposure_s: float) -> np.ndarray:
        if self._loop is None:
            self.prerender(exposure_s)
        i = int(round(t_mid_s * self.loop_fps)) % self.loop_frames
        return self._loop[i].astype(np.float32) * np.float32(1.0 / LOOP_SCALE)


LED_POSITION = (0.0, 2.05, -0.5)  # world metres (y up): where a scene's flash LED hangs
LED_HOUSING_M, LED_HOUSING_DN = 0.16, 12.0  # its dark housing around it: radius, and how it reads in the image


class SimRig:
    """A simulated rig from a rig configuration: one shared scene, the ground-truth calibration of
    its sim:// cameras, and a sensor per camera.

    `config` is anything shaped like rig.config.RigConfig (`sim` table, `cameras` with name, uri,
    role, width, height, gain, sim). Cameras stand on the virtual rig's arc in the order left, the
    others as listed, right.
    """

    def __init__(self, config, antialias: Optional[int] = None):
        from simulator.rig import arc_rig

        self.options = validate_scene_options(getattr(config, "sim", {}) or {})
        # sim:// cameras; in a simulated rig (one with a [sim] table) also the cameras its emulators
        # stand in for (gopro://, stream:// on simulator/ emulators): they see the same scene
        emulated = ("sim://", "gopro://", "stream://") if getattr(config, "sim", None) else ("sim://",)
        cams = [c for c in config.cameras if str(c.uri).startswith(emulated)]
        if not cams:
            raise SimulatorError("the configuration has no sim:// cameras")
        order = {"left": 0, "right": 2}
        cams = sorted(cams, key=lambda c: order.get(getattr(c, "role", ""), 1))  # stable: others keep their order
        self.cameras = cams
        self._scene = None  # built at first use (the scene property)
        self._scene_lock = threading.Lock()
        self.calibration = arc_rig([(c.name, c.width, c.height) for c in cams], seed=self.options["seed"])
        self._sensors: dict[str, SensorModel] = {}
        self._antialias = antialias
        self.led = None
        if self.options["led"]:
            from simulator.led import FlashLed

            # On a truss above the back of the stage, near the top of every camera's view.
            self.led = FlashLed(LED_POSITION, radius_m=0.08, radiance=0.04)  # unsaturated up to a 1/15 s shutter

    @property
    def scene(self):
        """The shared scene, built at first use: a start whose loops all come from the loop cache
        never needs it."""
        with self._scene_lock:
            if self._scene is None:
                from simulator.scene import Scene

                self._scene = Scene.from_options(self.options)
            return self._scene

    def sensor(self, name: str) -> SensorModel:
        if name not in self._sensors:
            cfg = next((c for c in self.cameras if c.name == name), None)
            if cfg is None:
                raise SimulatorError(f"no sim camera named {name!r} (have: {', '.join(c.name for c in self.cameras)})")
            self._sensors[name] = SensorModel(
                lambda: self.scene, self.calibration[name], getattr(cfg, "sim", None) or {},
                scene_key={"options": self.options},  # a scene is a pure function of its options
                gain_db=float(getattr(cfg, "gain", None) or 0.0),
                loop_frames=self.options["loop_frames"], loop_fps=self.options["loop_fps"], antialias=self._antialias,
                noise_variants=self.options["noise_variants"])
            self._sensors[name].led = self.led
        return self._sensors[name]


def validate_scene_options(table: dict) -> dict:
    try:
        return validate_options(dict(table), "scene")
    except ValueError as exc:
        raise SimulatorError(f"sim.{exc}") from None


_RIGS: dict = {}
_RIGS_LOCK = threading.Lock()


def sim_rig(config) -> SimRig:
    """The SimRig of a configuration, shared by all its cameras (one scene, one set of textures)."""
    import json

    key = json.dumps({"sim": getattr(config, "sim", {}) or {},
                      "cameras": [(c.name, c.uri, getattr(c, "role", ""), c.width, c.height, getattr(c, "gain", None), getattr(c, "sim", None))
                                  for c in config.cameras]}, sort_keys=True, default=str)
    with _RIGS_LOCK:
        rig = _RIGS.get(key)
        if rig is None:
            rig = SimRig(config)
            _RIGS[key] = rig
            while len(_RIGS) > 4:
                _RIGS.pop(next(iter(_RIGS)))
        return rig


def camera_source(config, camera_name: str) -> ImageSource:
    """The image source for the sim:// backend: `source(t, exposure_s, rng) -> RGB uint8`."""
    return sim_rig(config).sensor(camera_name).image_source()
