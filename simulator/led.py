"""The trigger board's flash LED as a light in the simulated scene.

Cameras that cannot take a trigger (GoPros, webcams) are aligned afterwards by a flash they all
saw. Here that flash is an LED at a point of the scene, wired to the emulated board's LED output:
each camera sees it through its own geometry (projection and lens distortion of its ground-truth
CameraModel), hidden when something stands in front of it, and its light is integrated over each
exposure exactly, since an LED is a step function of time: a flash that starts mid-exposure lights
that frame in proportion to the part of the exposure it covers.

    led = FlashLed((0.0, 1.6, 0.0), epoch_ns=SIM_EPOCH_NS)
    board.add_led_output(led.board_output)              # the emulator drives it
    source = led.image_source(sensor)                   # a sim:// camera's image source
"""
from __future__ import annotations

import bisect
import threading
from typing import Optional

import numpy as np

from calibration.camera import CameraModel
from simulator.render import render


class FlashLed:
    """An LED of `radius_m` at `position` (world, metres) adding `radiance` (1.0 = full scale at
    the sensor's nominal exposure) while lit. Times are simulated seconds: host monotonic ns minus
    `epoch_ns`, as the sim:// cameras count them."""

    def __init__(self, position=(0.0, 1.6, 0.0), radius_m: float = 0.08, radiance: float = 0.3, epoch_ns: int = 0):
        self.position = np.asarray(position, dtype=np.float64)
        self.radius_m = float(radius_m)
        self.radiance_level = float(radiance)
        self.epoch_ns = int(epoch_ns)
        self._times: list[float] = []  # edge times, sorted
        self._states: list[bool] = []  # the LED's state from that edge on
        self._drawn_until = float("-inf")  # the latest exposure end a camera has drawn the LED for
        self._lock = threading.Lock()

    # --- the wire from the board ------------------------------------------------------------------
    def board_output(self, on: bool, host_ns: int) -> None:
        """The board's LED output changed at host monotonic time `host_ns`."""
        self.set_live(bool(on), (host_ns - self.epoch_ns) / 1e9)

    def set(self, on: bool, t: float) -> None:
        """The LED's state from simulated time t on (a scripted signal: any t, in any order)."""
        with self._lock:
            self._insert(on, t)

    def set_live(self, on: bool, t: float) -> None:
        """The LED's state from t on, told as it happens (the emulated board's output). A thread
        that tells it late on a loaded host (its state at t may reach the LED after a camera has
        drawn a frame exposed past t) must not leave those frames dark and later ones lit: the
        edge then comes at the end of the latest exposure drawn, so every camera sees one LED,
        a step function of time, only later by that much."""
        with self._lock:
            self._insert(on, max(t, self._drawn_until))

    def _insert(self, on: bool, t: float) -> None:
        i = bisect.bisect_right(self._times, t)
        self._times.insert(i, t)
        self._states.insert(i, on)

    def lit_seconds(self, t0: float, t1: float, drawn: bool = False) -> float:
        """How long the LED was on during [t0, t1] (the exact integral of its on/off signal);
        `drawn`: a camera draws an exposure ending at t1 with it (a live edge never comes before)."""
        with self._lock:
            times, states = list(self._times), list(self._states)
            if drawn:
                self._drawn_until = max(self._drawn_until, t1)
        total = 0.0
        i = bisect.bisect_right(times, t0)
        on = states[i - 1] if i > 0 else False
        start = t0
        while i < len(times) and times[i] < t1:
            if on:
                total += times[i] - start
            start, on = times[i], states[i]
            i += 1
        if on:
            total += t1 - start
        return total

    # --- what a camera sees -----------------------------------------------------------------------
    def footprint(self, camera: CameraModel, depth: Optional[np.ndarray] = None,
                  radius_m: Optional[float] = None) -> Optional[np.ndarray]:
        """Coverage (0..1 per pixel, HxW) of the LED's disc (or a disc of `radius_m` around it: its
        housing) in this camera; None when out of view or hidden (the scene's depth at the LED's
        pixel is nearer than the LED)."""
        uv, z = camera.project(self.position.reshape(1, 3))
        uv, z = uv[0], float(z[0])
        if not z > 0.05:
            return None
        fx = float(camera.K[0, 0])
        r_px = max(0.5, fx * (self.radius_m if radius_m is None else radius_m) / z)
        H, W = camera.height, camera.width
        u0, u1 = int(np.floor(uv[0] - r_px - 1)), int(np.ceil(uv[0] + r_px + 1))
        v0, v1 = int(np.floor(uv[1] - r_px - 1)), int(np.ceil(uv[1] + r_px + 1))
        if u1 < 0 or v1 < 0 or u0 >= W or v0 >= H:
            return None
        if depth is not None:
            ui, vi = int(np.clip(round(uv[0]), 0, W - 1)), int(np.clip(round(uv[1]), 0, H - 1))
            d = float(depth[vi, ui])
            if 0 < d < z - 2 * (self.radius_m if radius_m is None else radius_m):
                return None  # something stands between the LED and this camera
        cover = np.zeros((H, W), np.float32)
        u0c, u1c, v0c, v1c = max(u0, 0), min(u1, W - 1), max(v0, 0), min(v1, H - 1)
        # 4x4 samples per pixel: an anti-aliased disc (pixel centres at integer coordinates)
        sub = (np.arange(4) + 0.5) / 4 - 0.5
        vv, uu = np.mgrid[v0c:v1c + 1, u0c:u1c + 1].astype(np.float64)
        inside = np.zeros(vv.shape, np.float64)
        for dv in sub:
            for du in sub:
                inside += ((uu + du - uv[0]) ** 2 + (vv + dv - uv[1]) ** 2) <= r_px ** 2
        cover[v0c:v1c + 1, u0c:u1c + 1] = inside / 16.0
        return cover

    def exposure_radiance(self, camera: CameraModel, t0: float, exposure_s: float, scene=None) -> Optional[np.ndarray]:
        """The LED's radiance (HxW) integrated over the exposure [t0, t0 + exposure_s]; None when dark."""
        lit = self.lit_seconds(t0, t0 + exposure_s, drawn=True)
        if lit <= 0:
            return None
        depth = render(scene, camera, t0 + exposure_s / 2).depth if scene is not None else None
        cover = self.footprint(camera, depth)
        if cover is None:
            return None
        return cover * np.float32(self.radiance_level * lit / exposure_s)

    def image_source(self, sensor):
        """A sim:// image source: the sensor's exposure of the scene with this LED in it."""

        def source(t: float, exposure_s: float, rng: np.random.Generator) -> np.ndarray:
            t = max(0.0, t)
            radiance = sensor.radiance(t, exposure_s)
            led = self.exposure_radiance(sensor.camera, t, exposure_s, sensor.scene)
            if led is not None:
                radiance = radiance + led[:, :, None]
            return sensor.digitise(radiance, exposure_s, rng)

        return source
