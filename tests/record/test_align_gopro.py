"""A take with two hardware-triggered sources and two free-running GoPros (emulators filming the
simulated scene, the board's LED in view), recorded through the gopro:// backend and aligned: every
GoPro frame's pulse and its offset against the truth.

The truth: a GoPro frame's device time is its stream's presentation time, frame k at k / fps from
the stream's start, which shows the simulated instant t0 + k / fps (simulator.gopro.scene); a
hardware camera's device time is its pulse's simulated time (plus a 20 us trigger latency).
"""
from __future__ import annotations

import json
import socket

import numpy as np

from rig.sim.clock import SIM_EPOCH_NS
from rig.sim.rig_config import sim_rig_config
from rig.capture.record import record
from rig.config import dump_config, load_config, parse_config
from rig.storage.align import align
from rig.storage.layout import INDEX
from simulator.gopro.scene import scene_emulators, stream_start


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_gopro_frames_are_aligned_to_the_pulses(tmp_path, monkeypatch):
    monkeypatch.setenv("RIG_CACHE_DIR", str(tmp_path / "cache"))
    data = sim_rig_config(n_cameras=4, width=640, height=360)
    data["sim"].update(led=True, loop_frames=6)
    for i, cam in enumerate(data["cameras"][1:3], 1):
        cam.update(uri=f"gopro://C35013246455{30 + i}@127.0.0.1:{_free_port()}", width=1280, height=720,
                   pixel_format="RGB8", trigger="free", fps=15.0)  # two 720p streams encoded, sent and decoded on two cores: at 15 fps
        cam.pop("sim", None)
        cam.pop("exposure_us", None)
    path = tmp_path / "rig.toml"
    path.write_text(dump_config(parse_config(data)))
    cfg = load_config(path, check_calibration=False)
    emulators = scene_emulators(cfg, SIM_EPOCH_NS)
    try:
        result = record(cfg, tmp_path / "take", seconds=6.0)
        starts = {e.serial: stream_start(e) for e in emulators}
    finally:
        for e in emulators:
            e.stop()
    assert not result.errors, result.errors
    assert result.flashes == 2
    live = [json.loads(line) for line in (tmp_path / "take" / INDEX).read_text().splitlines()]
    report = align(tmp_path / "take")
    rows = [json.loads(line) for line in (tmp_path / "take" / INDEX).read_text().splitlines()]
    hw = np.array([(r["trigger"], r["frames"]["left"]["device_ts_ns"]) for r in rows if r["frames"]["left"]], dtype=np.float64)
    ns_per_pulse, at_zero = np.polyfit(hw[:, 0], hw[:, 1], 1)
    first, last = min(r["trigger"] for r in rows), max(r["trigger"] for r in rows)

    def pulse_of(t0: float, f: dict) -> tuple[float, int]:
        pos = (t0 * 1e9 + f["device_ts_ns"] - at_zero) / ns_per_pulse  # its exposure start on the simulated clock
        return pos, int(np.floor(pos + 0.5))

    for cam in cfg.cameras[1:3]:
        rep = report["cameras"][cam.name]
        assert rep["problem"] is None, rep
        t0 = starts[cam.uri.split("//")[1].split("@")[0]]
        # The frames of the take exposed within its pulses: a frame exposed before the first pulse
        # (the stream's latency, a few hundred ms, delivers some after the take began) has no set.
        placeable = sum(1 for r in live if r["frames"][cam.name] is not None and first <= pulse_of(t0, r["frames"][cam.name])[1] <= last)
        wrong, worst, n = 0, 0.0, 0
        for r in rows:
            f = r["frames"][cam.name]
            if f is None:
                continue
            pos, nearest = pulse_of(t0, f)
            n += 1
            if nearest != r["trigger"]:
                wrong += 1
            else:
                worst = max(worst, abs((pos - nearest) - f["offset"]))
        print(f"{cam.name}: {n} frames placed of {placeable} exposed within the take's pulses ({result.frames[cam.name]} received; "
              f"{rep['moved']} moved from the live grouping), {wrong} in the wrong set, "
              f"offset error at most {worst:.4f} periods (stated {rep['error_periods']}); latency {rep['latency_ms']} ms, clock {rep['rate_ppm']} ppm")
        # Every frame exposed within the take's pulses is placed (how many arrive depends on how loaded
        # the two cores are: a floor of a quarter of the stream's rate only says the stream kept flowing).
        # It asked for 95 % of every frame received, and failed once at 90 of 95: the 5 were exposed
        # before the first pulse (latency 344 ms at 15 fps).
        assert n >= 0.95 * placeable and wrong == 0, (cam.name, n, placeable, result.frames[cam.name], wrong)
        assert n >= 0.25 * len(rows) * cam.fps / cfg.trigger.rate_hz, (cam.name, n, len(rows))
        # Offsets within 0.1 periods, or within what the alignment states where it states more: a frame
        # missing at a flash's edge leaves its onset a few ms loose, and the rate's error carries that to
        # the take's ends (once 0.107 periods at 555 ppm on CI, where the report had said 0.064).
        assert worst < max(0.1, rep["error_periods"] + 0.02), (cam.name, worst, rep["error_periods"])
        assert rep["error_periods"] < 0.5, rep
