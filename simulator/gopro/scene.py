"""GoPro emulators that film the simulated scene: one per gopro:// camera of a simulated rig.

    emulators = scene_emulators(config, epoch_ns)      # started; each serves the address its URI names
    ...
    for e in emulators: e.stop()

Each emulator's webcam stream shows the scene from where its camera stands on the simulated rig
(simulator.sensor.SimRig), with the trigger board's LED when the scene has one, at a 1/fps shutter
as a video camera's. Frame k of a stream shows the instant t0 + k / fps of the simulated clock
(host monotonic ns minus `epoch_ns`, as the sim:// cameras count), t0 being when the stream's
schedule began (read by the streaming thread as it starts it, so a loaded host that draws frame 0
late, or skips it, does not move the stream's timeline): `stream_start(emulator)` says it once the
stream runs, so a test can know each frame's true time. A frame is drawn once its exposure is over,
so the LED's edges within it have happened.

A video the emulator records to its card on the shutter (`?record=card` cameras) is on the simulated
clock too: the emulator's clock is the simulated one, so its `recordings` say the simulated instant
t0 whose picture frame 0 shows (frame k: t0 + k / fps), each frame exposed for 1 / fps from it.
"""
from __future__ import annotations

import time
from typing import Optional
from urllib.parse import urlsplit

import numpy as np

from simulator.errors import SimulatorError
from simulator.gopro.emulator import GoProEmulator


def _address(uri: str) -> tuple[str, str, int]:
    parts = urlsplit(uri)
    serial, _, address = parts.netloc.partition("@")
    host, _, port = address.rpartition(":")
    if not serial or host not in ("127.0.0.1", "localhost") or not port.isdigit():
        raise SimulatorError(f"{uri}: an emulated GoPro needs a loopback control address, gopro://SERIAL@127.0.0.1:PORT")
    return serial, host, int(port)


def scene_emulators(config, epoch_ns: int, *, advertise: bool = False, **options) -> list[GoProEmulator]:
    from simulator.sensor import sim_rig

    rig = sim_rig(config)
    emulators = []
    try:
        for cam in config.cameras:
            if not str(cam.uri).startswith("gopro://"):
                continue
            serial, host, port = _address(cam.uri)
            sensor = rig.sensor(cam.name)
            exposure_s = 1.0 / cam.fps
            sensor.prerender(exposure_s)  # now, not in the stream's first frame
            source = sensor.image_source()
            rng = np.random.default_rng(abs(hash(serial)) % (1 << 32))

            def render(t: float, source=source, exposure_s=exposure_s, rng=rng) -> np.ndarray:
                return source(t, exposure_s, rng)  # t: the simulated instant itself (the emulator's clock)

            def scene_clock() -> float:
                return (time.monotonic_ns() - epoch_ns) / 1e9

            emu = GoProEmulator(serial, render=render, width=cam.width, height=cam.height, fps=cam.fps, host=host,
                                http_port=port, advertise=advertise, clock=scene_clock, stream_on_clock=True, **options)
            emulators.append(emu.start())
    except BaseException:
        for emu in emulators:
            emu.stop()
        raise
    return emulators


def stream_start(emulator: GoProEmulator) -> Optional[float]:
    """The simulated time frame 0 of the emulator's current stream shows (None before it streams)."""
    return emulator.stream_t0
