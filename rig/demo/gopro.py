"""`rig demo --gopro`'s rig and truth: the simulated rig's two sources with N GoPros as its
supervision cameras, each an emulator of the Open GoPro API on loopback filming the scene
(simulator/gopro), reached through the real gopro:// backend; and how far `rig record align` put
each GoPro frame from its true pulse and sub-frame offset, known from when its stream began.
"""
from __future__ import annotations

import json
import socket
from contextlib import contextmanager
from pathlib import Path

import numpy as np

GOPRO_SIZE = (1280, 720)  # a HERO12 streams 720p or 1080p in webcam mode: the smaller one, for N streams on the host
GOPRO_FPS = 15.0  # the emulators render, encode and the backend decodes every stream on this host
MAX_GOPROS = 8


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def gopro_rig(n_gopros: int, width: int, height: int, fps: float) -> dict:
    """The rig's configuration: the simulated rig of 2 + N cameras, its supervision cameras made
    GoPros on loopback emulators (a control port and a stream port each, free on this host)."""
    from rig.sim.rig_config import sim_rig_config

    data = sim_rig_config(n_cameras=2 + n_gopros, width=width, height=height, fps=fps)
    data["rig"]["name"] = f"sim-gopro-{n_gopros}"
    data["sim"].update(led=True, loop_frames=20)
    k = 0
    for cam in data["cameras"]:
        if cam["role"] != "supervision":
            continue
        k += 1
        serial = f"C35013246455{10 + k:02d}"
        cam.update(uri=f"gopro://{serial}@127.0.0.1:{_free_port(socket.SOCK_STREAM)}?port={_free_port(socket.SOCK_DGRAM)}",
                   width=GOPRO_SIZE[0], height=GOPRO_SIZE[1], pixel_format="RGB8", trigger="free", fps=GOPRO_FPS)
        for key in ("sim", "exposure_us", "gain"):
            cam.pop(key, None)
    return data


def alignment_truth(take: Path, cameras: list, starts: dict[str, float]) -> dict[str, dict]:
    """Per GoPro: how many of its frames the aligned index puts in the wrong set, and the largest
    error of their places (pulse plus offset, in pulse periods). The truth: a GoPro frame's device
    time is its stream's presentation time, frame k showing the simulated instant t0 + k / fps (t0:
    `starts`, by serial); the pulses' simulated times come from the hardware-triggered left camera's
    frames.

    A frame is in the wrong set when it lies further from its set's pulse than half-way to the next
    plus the uncertainty the alignment states (alignment.json): a frame exposed within that of
    half-way between two pulses may go to either, its offset saying where it lies (a 15 fps GoPro
    against 30 Hz pulses keeps its phase through a take, and that phase can be anything)."""
    from rig.storage.align import REPORT
    from rig.storage.layout import INDEX

    rows = [json.loads(line) for line in (take / INDEX).read_text().splitlines() if line.strip()]
    stated = json.loads((take / REPORT).read_text()).get("cameras", {}) if (take / REPORT).is_file() else {}
    hw = np.array([(r["trigger"], r["frames"]["left"]["device_ts_ns"]) for r in rows if r["frames"].get("left")], dtype=np.float64)
    ns_per_pulse, at_zero = np.polyfit(hw[:, 0], hw[:, 1], 1)
    out = {}
    for cam in cameras:
        t0 = starts.get(cam.uri.split("//", 1)[1].split("@", 1)[0])
        if t0 is None:
            out[cam.name] = {"frames": 0, "wrong_set": 0, "offset_error_max": None}
            continue
        error = (stated.get(cam.name) or {}).get("error_periods") or 0.0
        wrong = n = 0
        worst = 0.0
        for r in rows:
            f = r["frames"].get(cam.name)
            if f is None or f.get("offset") is None:
                continue
            after = (t0 * 1e9 + f["device_ts_ns"] - at_zero) / ns_per_pulse - r["trigger"]  # periods after its set's pulse
            n += 1
            wrong += abs(after) > 0.5 + error
            worst = max(worst, abs(after - f["offset"]))
        out[cam.name] = {"frames": n, "wrong_set": wrong, "offset_error_max": worst if n else None}
    return out


@contextmanager
def gopro_emulators(cfg):
    """The rig's GoPros as emulators serving the Open GoPro API on loopback, each filming the scene
    from its camera's place; stopped on leaving. Yields the emulators (`stream_starts` reads them)."""
    from rig.sim.clock import SIM_EPOCH_NS
    from simulator.gopro.scene import scene_emulators

    emulators = scene_emulators(cfg, SIM_EPOCH_NS)
    try:
        yield emulators
    finally:
        for e in emulators:
            e.stop()


def stream_starts(emulators) -> dict[str, float]:
    """Per serial: the simulated time frame 0 of the emulator's stream shows."""
    from simulator.gopro.scene import stream_start

    return {e.serial: stream_start(e) for e in emulators}
