"""The virtual sensor: exposure and gain scale the signal, noise follows its model, timing follows the
options, and every capture is reproducible from its frame index."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from simulator.errors import SimulatorError
from simulator.render import render
from simulator.rig import virtual_rig
from simulator.scene import Scene
from simulator.sensor import NOMINAL_EXPOSURE_S, SensorModel, SimRig, camera_source


@pytest.fixture(scope="module")
def scene():
    return Scene(seed=4, people=2, name="empty")


@pytest.fixture(scope="module")
def cam():
    return virtual_rig(2, 160, 90)["left"]


def test_exposure_and_gain_scale_the_image(scene, cam):
    quiet = {"shot_noise": 0.0, "read_noise": 0.0, "motion_blur": False}
    s = SensorModel(scene, cam, quiet)
    rng = np.random.default_rng(0)
    E = NOMINAL_EXPOSURE_S
    base = s.expose(1.0, E, rng).astype(float)
    half = s.expose(1.0 + E / 4, E / 2, rng).astype(float)  # same mid-exposure instant: the people stand alike
    unsat = base < 250
    assert np.abs(half[unsat] - base[unsat] / 2).max() <= 1.0
    gained = SensorModel(scene, cam, quiet, gain_db=6.0).expose(1.0 + E / 4, E / 2, rng).astype(float)
    assert np.abs(gained[unsat] - base[unsat] * 10 ** (6 / 20) / 2).max() <= 1.0
    assert SensorModel(scene, cam, quiet).expose(1.0, NOMINAL_EXPOSURE_S * 20, rng).max() == 255


def test_noise_follows_shot_and_read_noise_model(scene, cam):
    clean = SensorModel(scene, cam, {"shot_noise": 0.0, "read_noise": 0.0, "motion_blur": False}).expose(1.0, NOMINAL_EXPOSURE_S, np.random.default_rng(0)).astype(float)
    read = SensorModel(scene, cam, {"shot_noise": 0.0, "read_noise": 3.0, "motion_blur": False})
    diff = read.expose(1.0, NOMINAL_EXPOSURE_S, np.random.default_rng(1)).astype(float) - clean
    mid = (clean > 20) & (clean < 235)
    assert diff[mid].std() == pytest.approx(np.sqrt(3.0 ** 2 + 1 / 12), rel=0.1)
    full_well = 1000.0
    shot = SensorModel(scene, cam, {"shot_noise": 1.0, "read_noise": 0.0, "full_well": full_well, "motion_blur": False})
    diff = shot.expose(1.0, NOMINAL_EXPOSURE_S, np.random.default_rng(2)).astype(float) - clean
    bright, dark = mid & (clean > 150), mid & (clean < 70)
    expect = lambda dn: np.sqrt(dn * 255.0 / full_well)  # noqa: E731 - Poisson in electrons, seen in DN
    assert diff[bright].std() == pytest.approx(expect(clean[bright]).mean(), rel=0.15)
    assert diff[dark].std() < diff[bright].std()


def test_motion_blur_averages_the_exposure(scene, cam):
    sharp = SensorModel(scene, cam, {"shot_noise": 0.0, "read_noise": 0.0, "motion_blur": False})
    blurred = SensorModel(scene, cam, {"shot_noise": 0.0, "read_noise": 0.0, "blur_samples": 4})
    rng = np.random.default_rng(0)
    long_exposure = 0.2  # people move several centimetres
    a = sharp.expose(1.0, long_exposure / 8, rng).astype(float)
    b = blurred.expose(1.0, long_exposure / 8, rng).astype(float)
    assert not np.array_equal(a, b)
    frames = [render(scene, cam, 1.0 + (i + 0.5) / 4 * long_exposure).radiance for i in range(4)]
    assert np.allclose(blurred.radiance(1.0, long_exposure), np.mean(frames, axis=0), atol=1e-5)


def test_capture_is_reproducible_and_timing_follows_the_options(scene, cam):
    opts = {"latency_us": 50.0, "jitter_us": 10.0, "clock_offset_ns": 123_000, "drift_ppm": 100.0, "drop_rate": 0.3, "seed": 9}
    s = SensorModel(scene, cam, opts)
    a, b = s.capture(2.0, 0.004, 17), s.capture(2.0, 0.004, 17)
    assert a.exposure_start_s == b.exposure_start_s and a.device_ts_ns == b.device_ts_ns and a.dropped == b.dropped
    if not a.dropped:
        assert np.array_equal(a.image, b.image)
    starts = np.array([s.exposure_start(1.0, s.frame_rng(i)) for i in range(2000)]) - 1.0
    assert starts.min() >= 50e-6
    assert (starts - 50e-6).mean() == pytest.approx(10e-6 * np.sqrt(2 / np.pi), rel=0.1)  # |N(0, 10 us)|
    assert s.device_time_ns(10.0) == round(10e9 * (1 + 100e-6)) + 123_000
    drops = np.mean([s.dropped(s.frame_rng(i)) for i in range(4000)])
    assert drops == pytest.approx(0.3, abs=0.03)


def test_bayer_sensor_delivers_a_mosaic_and_demosaiced_rgb(scene, cam):
    s = SensorModel(scene, cam, {"bayer": "RG", "read_noise": 0.0, "shot_noise": 0.0, "motion_blur": False})
    clean = SensorModel(scene, cam, {"read_noise": 0.0, "shot_noise": 0.0, "motion_blur": False}).expose(1.0, 0.005, np.random.default_rng(0))
    raw = s.expose(1.0, 0.005, np.random.default_rng(0), raw=True)
    assert raw.shape == (90, 160) and raw.dtype == np.uint8
    assert np.array_equal(raw[0::2, 0::2], clean[0::2, 0::2, 0])  # R at the top-left
    assert np.array_equal(raw[1::2, 1::2], clean[1::2, 1::2, 2])  # B at the bottom-right
    rgb = s.expose(1.0, 0.005, np.random.default_rng(0))
    assert rgb.shape == (90, 160, 3) and np.abs(rgb.astype(float) - clean).mean() < 12


def _config(**scene_opts):
    cams = [SimpleNamespace(name=n, uri=f"sim://{n}", role=r, width=96, height=54, gain=None, sim={"seed": i})
            for i, (n, r) in enumerate((("right", "right"), ("sup1", "supervision"), ("left", "left")))]
    return SimpleNamespace(sim={"people": 1, **scene_opts}, cameras=cams)


def test_sim_rig_places_config_cameras_on_the_arc_and_loops_prerendered_frames():
    rig = SimRig(_config(loop_frames=4, loop_fps=10.0))
    assert rig.calibration.names == ["left", "sup1", "right"], "left first, right last"
    assert rig.calibration["left"].center[0] < rig.calibration["sup1"].center[0] < rig.calibration["right"].center[0]
    s = rig.sensor("sup1")
    a = s.expose(0.0, 0.005, np.random.default_rng(1))
    b = s.expose(0.4, 0.005, np.random.default_rng(2))  # 0.4 s = 4 frames later: the same loop frame
    assert s._loop is not None and s._loop.shape == (4, 54, 96, 3)
    assert 0 < np.abs(a.astype(float) - b).mean() < 3, "same frame, fresh noise"
    assert s.scene_time(0.4, 0.005) == pytest.approx(0.0025) and s.scene_time(0.2, 0.005) == pytest.approx(0.2025)
    c = s.expose(0.2, 0.005, np.random.default_rng(3))
    assert np.abs(a.astype(float) - c).mean() > np.abs(a.astype(float) - b).mean()
    source = camera_source(_config(loop_frames=4, loop_fps=10.0), "left")
    img = source(0.1, 0.005, np.random.default_rng(0))
    assert img.shape == (54, 96, 3) and img.dtype == np.uint8


def test_bad_sensor_options_are_clear_errors(scene, cam):
    with pytest.raises(SimulatorError, match="sim.drop_rate"):
        SensorModel(scene, cam, {"drop_rate": 2.0})
    with pytest.raises(SimulatorError, match="gain"):
        SensorModel(scene, cam, gain_db=99.0)
    with pytest.raises(SimulatorError, match="exposure must be positive"):
        SensorModel(scene, cam).expose(0.0, 0.0, np.random.default_rng(0))
    with pytest.raises(SimulatorError, match="no sim:// cameras"):
        SimRig(SimpleNamespace(sim={}, cameras=[SimpleNamespace(name="a", uri="aravis://x", width=8, height=8)]))
    with pytest.raises(SimulatorError, match="sim.motion"):
        SimRig(_config(motion="fly"))
