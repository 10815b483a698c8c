"""Offline flash alignment on simulator video: free-running sim cameras film the LED the emulated
trigger board flashes; the flash onset found in each camera's frames recovers its clock offset."""
from __future__ import annotations

import time

import numpy as np
import pytest

from rig.cameras import sim as sim_backend
from rig.config import CameraConfig
from simulator.led import FlashLed
from simulator.rig import virtual_rig
from simulator.scene import Scene
from simulator.sensor import SensorModel
from simulator.trigger_board import TriggerBoardEmulator
from sync.alignment import brightness_trace, camera_offsets, find_flash, flash_in_frames
from sync.board import TriggerBoard
from sync.errors import SyncError

FPS = 30.0
PERIOD_NS = 1e9 / FPS


def test_flash_alignment_recovers_known_clock_offsets_within_a_tenth_of_a_frame():
    rig = virtual_rig(2, 96, 54)
    scene = Scene(seed=2, people=1, name="studio")
    led = FlashLed((0.0, 2.3, -1.5), radius_m=0.1, epoch_ns=sim_backend.SIM_EPOCH_NS)
    offsets_true = {"left": 1_234_567_891, "right": -98_765_432}  # the cameras' clocks, far apart
    cameras = {}
    for cam_model in rig.cameras:
        name = cam_model.name
        cfg = CameraConfig(name=name, uri=f"sim://{name}", width=96, height=54, pixel_format="RGB8", fps=FPS,
                           trigger="free", exposure_us=30000.0, sim={"clock_offset_ns": offsets_true[name], "drift_ppm": 30.0 if name == "left" else -20.0})
        sensor = SensorModel(scene, cam_model, {"seed": 1 if name == "left" else 2}, gain_db=-18.0)
        cameras[name] = sim_backend.open(cfg.uri, cfg, source=led.image_source(sensor))

    with TriggerBoardEmulator({"seed": 6}) as emu, TriggerBoard(emu.url) as board:
        emu.add_led_output(led.board_output)
        board.connect()
        for cam in cameras.values():
            cam.start()
        time.sleep(0.6)
        flashed = board.flash(150)
        time.sleep(0.2)
        # the cameras render the scene live, maybe slower than real time (their timestamps stay
        # true): read each until it has filmed well past the flash
        flash_end = emu.flashes[0].host_end_ns
        frames = {}
        for name, cam in cameras.items():
            frames[name] = []
            past = cam.device_time_ns(flash_end) + 5 * PERIOD_NS
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and (not frames[name] or frames[name][-1].device_ts_ns < past):
                try:
                    frames[name].append(cam.get_frame(timeout=0.5))
                except Exception:
                    pass
        for cam in cameras.values():
            cam.stop()
            cam.close()
    assert flashed is not None and len(emu.flashes) == 1
    on_host_ns = emu.flashes[0].host_start_ns

    estimates = {}
    for name, fr in frames.items():
        assert len(fr) > 20
        est = flash_in_frames(fr, duration_ns=150e6)
        truth = cameras[name].device_time_ns(on_host_ns)  # the flash onset on this camera's clock
        err = (est.onset_ns - truth) / PERIOD_NS
        print(f"{name}: onset error {err:+.3f} frame periods (reported uncertainty {est.uncertainty_ns / PERIOD_NS:.3f})")
        assert abs(err) < 0.1
        estimates[name] = est
    offsets = camera_offsets(estimates, reference="left")
    true_rel = cameras["right"].device_time_ns(on_host_ns) - cameras["left"].device_time_ns(on_host_ns)
    rel_err = (offsets["right"] - true_rel) / PERIOD_NS
    print(f"right - left clock offset: {offsets['right'] / 1e6:.3f} ms, error {rel_err:+.3f} frame periods")
    assert offsets["left"] == 0.0 and abs(rel_err) < 0.1


def test_a_flash_partway_through_an_exposure_lights_the_frame_in_proportion():
    rig = virtual_rig(1, 64, 36)
    scene = Scene(seed=0, people=0, name="empty")
    sensor = SensorModel(scene, rig.cameras[0], {"read_noise": 0.0, "shot_noise": 0.0}, gain_db=-18.0)
    led = FlashLed((0.0, 1.5, 0.0), radius_m=0.15)
    led.set(True, 1.0075)  # a quarter into the exposure [1.0, 1.03]
    led.set(False, 2.0)
    src = led.image_source(sensor)
    rng = np.random.default_rng(0)
    dark, part, full = (src(t, 0.03, rng).astype(float) for t in (0.9, 1.0, 1.1))
    spot = (full - dark).mean(axis=2) > 20
    assert spot.sum() >= 4  # the LED is a few pixels in this camera
    ratio = float((part - dark)[spot].sum() / (full - dark)[spot].sum())
    assert ratio == pytest.approx(0.75, abs=0.005)  # noise-free: measured 0.748 (8-bit rounding)


def test_a_flash_the_board_tells_late_starts_after_the_frames_already_drawn():
    # On a loaded host the board's thread may tell the LED its flash began at t after a camera has
    # drawn a frame exposed past t: that frame stays dark, and the flash must start where it ended
    # for every frame drawn later, not at t (a frame lit less than the one before it is no flash).
    rig = virtual_rig(1, 64, 36)
    sensor = SensorModel(Scene(seed=0, people=0, name="empty"), rig.cameras[0], {"read_noise": 0.0, "shot_noise": 0.0}, gain_db=-18.0)
    led = FlashLed((0.0, 1.5, 0.0), radius_m=0.15, epoch_ns=0)
    src = led.image_source(sensor)
    rng = np.random.default_rng(0)
    dark = src(1.0, 0.03, rng).astype(float)  # drawn: exposure [1.0, 1.03]
    led.board_output(True, 1_010_000_000)  # told afterwards: on from 1.01 s
    led.board_output(False, 2_000_000_000)
    assert led.lit_seconds(1.0, 1.03) == 0.0  # what that frame showed stays true
    later = src(1.02, 0.03, rng).astype(float)  # [1.02, 1.05]: lit from 1.03, not from 1.01
    full = src(1.1, 0.03, rng).astype(float)
    spot = (full - dark).mean(axis=2) > 20
    ratio = float((later - dark)[spot].sum() / (full - dark)[spot].sum())
    assert ratio == pytest.approx(2 / 3, abs=0.01)
    led.set(True, 0.5)  # a scripted signal is taken as given
    assert led.lit_seconds(0.5, 0.6) == pytest.approx(0.1)


def test_find_flash_reports_a_flash_in_the_dead_time_as_uncertain():
    period, exposure = 33.3e6, 10e6
    times = np.arange(40) * period
    onset = 10 * period + 20e6  # after frame 10's exposure ended, before frame 11 began
    trace = np.array([100.0 + (80.0 if onset <= t and t + exposure <= onset + 200e6 else 0.0) for t in times])
    est = find_flash(times, trace, exposure)
    # the gap is 23.3 ms: the estimate says it cannot tell where in it (half the gap: 11.65 ms)
    assert est.uncertainty_ns > 11e6
    assert abs(est.onset_ns - onset) <= est.uncertainty_ns + 1e6


def test_an_exact_fit_has_zero_residual_not_a_negative_one():
    # syy - sxy * c1 rounds to about -3e-11 for an exact line: the noise estimate then took the
    # square root of a negative number (a NaN that max() happened to skip, with a RuntimeWarning)
    from sync.alignment import _sse
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (2000, 40))
    sse, c0, c1 = _sse(20.0 + 200.0 * x[7], x)
    assert (sse >= 0).all() and sse[7] == pytest.approx(0.0, abs=1e-9)
    assert (c0[7], c1[7]) == (pytest.approx(20.0), pytest.approx(200.0))


def test_no_flash_is_an_error_not_a_guess():
    rng = np.random.default_rng(1)
    with pytest.raises(SyncError, match="no flash"):
        find_flash(np.arange(30) * 33e6, 100 + rng.normal(0, 0.5, 30), 30e6)
    with pytest.raises(SyncError, match="no frames"):
        brightness_trace([])
