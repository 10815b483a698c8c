"""The sim:// camera honours the camera contract: trigger modes, drops, its own clock, disconnects."""
from __future__ import annotations

import io
import os
import sys
import time

import numpy as np
import pytest

from common.bayer import demosaic, mosaic
from rig.cameras import open_camera
from rig.sim.rig_config import sim_rig_config
from rig.config import CameraConfig, parse_config
from rig.errors import CameraDisconnected, CameraTimeout, ConfigError


def sim_camera(trigger="free", fps=100.0, **sim):
    return open_camera(CameraConfig(name="cam", uri="sim://left", trigger=trigger, fps=fps, width=64, height=48,
                                    pixel_format="RGB8", exposure_us=1000.0, sim=sim))


def test_free_run_delivers_at_fps():
    with sim_camera("free", fps=100) as cam:
        cam.start()
        frames = [cam.get_frame(1.0) for _ in range(30)]
    ids = [f.frame_id for f in frames]
    assert ids == list(range(ids[0], ids[0] + 30))
    period_ms = np.median(np.diff([f.device_ts_ns for f in frames])) / 1e6
    assert period_ms == pytest.approx(10.0, abs=0.5)
    assert frames[0].image.shape == (48, 64, 3) and frames[0].image.dtype == np.uint8


def test_software_trigger_gives_one_frame_per_trigger():
    with sim_camera("software") as cam:
        cam.start()
        for _ in range(5):
            cam.software_trigger()
            cam.get_frame(1.0)
        with pytest.raises(CameraTimeout):
            cam.get_frame(0.1)  # no trigger, no frame
    assert cam.stats.delivered == 5 and cam.stats.timeouts == 1


def test_hardware_trigger_records_which_pulse_each_frame_answered():
    with sim_camera("hardware", latency_us=30.0, jitter_us=5.0) as cam:
        cam.start()
        t0 = time.monotonic_ns()
        for k in range(5):
            cam.hardware_trigger(k, t0 + k * 5_000_000)
        frames = [cam.get_frame(1.0) for _ in range(5)]
    assert [cam.truth_pulse[f.frame_id] for f in frames] == [0, 1, 2, 3, 4]
    with pytest.raises(ConfigError):
        with sim_camera("free") as other:
            other.start()
            other.software_trigger()  # wrong mode is a clear error, not silence


def test_drops_leave_gaps_that_the_stats_count():
    with sim_camera("free", fps=400, drop_rate=0.2, seed=3) as cam:
        cam.start()
        frames = [cam.get_frame(1.0) for _ in range(100)]
    ids = [f.frame_id for f in frames]
    gaps = sum(b - a - 1 for a, b in zip(ids, ids[1:]))
    assert gaps == cam.stats.dropped and 5 < gaps < 60


def test_device_clock_has_offset_and_drift():
    with sim_camera("free", fps=200, clock_offset_ns=5_000_000_000, drift_ppm=1000.0) as cam:
        cam.start()
        frames = [cam.get_frame(1.0) for _ in range(40)]
    dev = np.array([f.device_ts_ns for f in frames], dtype=np.float64)
    nominal = 5e6 * np.arange(len(frames))  # 200 fps ticks on the host clock
    slope = np.polyfit(nominal, dev - dev[0], 1)[0]
    assert slope == pytest.approx(1.001, abs=2e-5)
    assert dev[0] > 5e9


def test_bayer_sensor_delivers_rgb_frames():
    cfg = CameraConfig(name="cam", uri="sim://left", trigger="free", fps=100, width=64, height=48, pixel_format="BayerRG8")
    with open_camera(cfg) as cam:
        cam.start()
        f = cam.get_frame(1.0)
    assert f.image.shape == (48, 64, 3) and f.pixel_format == "BayerRG8"
    # the demosaic kept every sensor sample: the mosaic a recording stores gives back this very image
    assert np.array_equal(demosaic(mosaic(f.image, "BayerRG8"), "BayerRG8"), f.image)


def test_a_rig_camera_shows_its_pre_render_on_a_terminal_and_not_when_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("RIG_CACHE_DIR", str(tmp_path))
    data = sim_rig_config(2, width=64, height=48)
    data["sim"].update(loop_frames=3, seed=4242)  # a rig no other test has rendered in this process
    cfg = parse_config(data)
    master, slave = os.openpty()
    terminal = os.fdopen(slave, "w")
    monkeypatch.setattr(sys, "stderr", terminal)
    try:
        with open_camera(cfg.camera("left")) as cam:
            cam.prepare()
            assert cam.sensor.loop_origin == "render"
        terminal.flush()
        shown = os.read(master, 65536).decode(errors="replace")
        assert "left: pre-rendering" in shown and "3/3" in shown
    finally:
        terminal.close()
        os.close(master)
    quiet = io.StringIO()  # piped: nothing is drawn
    monkeypatch.setattr(sys, "stderr", quiet)
    with open_camera(cfg.camera("right")) as cam:
        cam.prepare()
        assert cam.sensor.loop_origin == "render"
    assert quiet.getvalue() == ""


def test_unplugged_camera_reports_disconnect():
    with sim_camera("free") as cam:
        cam.start()
        cam.get_frame(1.0)
        cam.unplug()
        with pytest.raises(CameraDisconnected):
            for _ in range(200):
                cam.get_frame(0.5)


def test_exposure_and_gain_change_while_acquiring_and_the_image_follows():
    from rig.errors import ConfigError

    with sim_camera("free", fps=100) as cam:
        cam.start()
        def settled(exposure_us):
            for _ in range(20):  # frames exposed before the change may still be queued
                frame = cam.get_frame(1.0)
                if frame.exposure_us == pytest.approx(exposure_us):
                    return np.mean([cam.get_frame(1.0).image.mean() for _ in range(3)])
            raise AssertionError("frames never carried the new exposure")

        before = settled(1000.0)
        got = cam.set_controls(exposure_us=500.0)
        assert got["exposure_us"] == 500.0 and got["gain"] == 0.0 and got["live"]
        assert settled(500.0) == pytest.approx(before / 2, rel=0.1)  # half the light
        got = cam.set_controls(gain=6.0206)
        assert settled(500.0) == pytest.approx(before, rel=0.1)  # +6 dB: twice the signal again
        lo, hi = got["ranges"]["exposure_us"]
        assert hi == pytest.approx(10000.0)  # one frame period at 100 fps
        for bad in ({"exposure_us": hi + 1}, {"exposure_us": -5}, {"gain": 99}, {"exposure_us": "1000"}, {"gain": True}):
            with pytest.raises(ConfigError):
                cam.set_controls(**bad)
        assert cam.controls()["exposure_us"] == 500.0 and cam.controls()["gain"] == 6.0206
