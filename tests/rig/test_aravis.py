"""The aravis:// backend against Aravis's fake GigE Vision camera (a real GVCP/GVSP peer on loopback)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from rig.cameras import open_camera
from rig.config import CameraConfig
from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig

ONE_CAMERA = """
[rig]
name = "fake"
[[cameras]]
name = "left"
uri = "{uri}"
role = "left"
width = 640
height = 480
pixel_format = "Mono8"
fps = 30
trigger = "{trigger}"
"""


def write_config(tmp_path: Path, uri="aravis://127.0.0.1", trigger="software") -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(ONE_CAMERA.format(uri=uri, trigger=trigger))
    return path


def read_index(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]


def test_grab_returns_exactly_n_consecutive_frames(fake_camera, tmp_path):
    n = 140  # the fake camera's 16-bit frame counter starts near 65400: this crosses its wrap
    out = tmp_path / "out"
    proc = run_rig("grab", "-c", write_config(tmp_path), "-n", n, "-o", out, "--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["frames"] == {"left": n} and summary["dropped"] == {"left": 0}
    records = read_index(out)
    assert len(records) == n
    ids = [r["frame_id"] for r in records]
    assert ids == list(range(ids[0], ids[0] + n))
    assert all(np.diff([r["device_ts_ns"] for r in records]) > 0)
    assert all(np.diff([r["host_ts_ns"] for r in records]) > 0)
    img = cv2.imread(str(out / records[-1]["file"]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (480, 640) and img.dtype == np.uint8


def test_settings_reach_the_camera(fake_camera):
    cfg = CameraConfig(name="left", uri=fake_camera.uri, width=320, height=240, pixel_format="Mono8", fps=50.0,
                       trigger="software", exposure_us=2000.0, gain=5.0)
    with open_camera(cfg) as cam:
        dev = cam._cam
        assert dev.get_float("ExposureTimeAbs") == pytest.approx(2000.0)
        assert dev.get_integer("GainRaw") == 5
        assert dev.get_float("AcquisitionFrameRate") == pytest.approx(50.0)
        assert dev.get_string("TriggerMode") == "On" and dev.get_string("TriggerSource") == "Software"
        cam.start()
        cam.software_trigger()
        frame = cam.get_frame(2.0)
    assert frame.image.shape == (240, 320)


def test_free_run_has_no_gaps_and_bayer_becomes_rgb(fake_camera):
    cfg = CameraConfig(name="left", uri=fake_camera.uri, width=320, height=240, pixel_format="BayerRG8", fps=100.0, trigger="free")
    with open_camera(cfg) as cam:
        cam.start()
        frames = [cam.get_frame(2.0) for _ in range(60)]
        stats = cam.stream_statistics()
    ids = [f.frame_id for f in frames]
    assert ids == list(range(ids[0], ids[0] + 60)) and cam.stats.dropped == 0
    assert frames[0].image.shape == (240, 320, 3)
    assert stats["n_completed_buffers"] >= 60


def test_free_run_start_loses_nothing_on_a_busy_host(fake_camera):
    """Frames sent before Aravis sizes its socket overflowed the default buffer on a loaded host
    (the second frame lost 24 of its 60 packets in about one start in five); priming fixes it."""
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(3 * (os.cpu_count() or 2))]
    try:
        cfg = CameraConfig(name="left", uri=fake_camera.uri, width=320, height=240, pixel_format="BayerRG8", fps=100.0, trigger="free")
        for _ in range(6):
            with open_camera(cfg) as cam:
                cam.start()
                ids = [cam.get_frame(2.0).frame_id for _ in range(10)]
            assert ids == list(range(ids[0], ids[0] + 10)) and cam.stats.dropped == 0 and cam.stats.incomplete == 0, (ids, cam.stats)
    finally:
        for p in busy:
            p.kill()
            p.wait()


def test_uri_no_device_answers(tmp_path):
    proc = run_rig("grab", "-c", write_config(tmp_path, uri="aravis://127.0.0.9"), "-n", 1, "-o", tmp_path / "out")
    assert_one_line_error(proc, "aravis://127.0.0.9", "no camera answers")


def test_unknown_backend_in_grab(tmp_path):
    proc = run_rig("grab", "-c", write_config(tmp_path, uri="gige://1"), "-n", 1, "-o", tmp_path / "out")
    assert_one_line_error(proc, "unknown scheme 'gige'")


def test_camera_killed_mid_grab_keeps_written_frames(fake_camera, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "rig", "grab", "-c", str(write_config(tmp_path)), "-n", "1000", "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    index = out / "frames.jsonl"
    deadline = time.monotonic() + 30
    while not (index.exists() and len(index.read_text().splitlines()) >= 10):
        assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    fake_camera.kill()
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode != 0
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in stderr and "left" in lines[0], stderr
    records = read_index(out)
    assert len(records) >= 10
    for r in records:  # every listed frame is on disk and decodes
        img = cv2.imread(str(out / r["file"]), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.shape == (480, 640)
    assert not list(out.rglob("*.part.png"))


def test_a_camera_powered_off_and_on_again_is_reconnected(fake_camera):
    from rig.errors import CameraDisconnected, CameraTimeout
    from tests.rig.conftest import FakeCamera

    cfg = CameraConfig(name="left", uri=fake_camera.uri, width=320, height=240, pixel_format="Mono8", fps=100.0, trigger="free")
    with open_camera(cfg) as cam:
        cam.start()
        assert cam.get_frame(2.0).image.shape == (240, 320)
        fake_camera.kill()  # powered off
        deadline = time.monotonic() + 20
        with pytest.raises(CameraDisconnected):
            while time.monotonic() < deadline:
                try:
                    cam.get_frame(0.5)
                except CameraTimeout:
                    pass
        assert cam.reconnect() is False  # nothing answers at its address
        again = FakeCamera()  # powered on again, same address
        try:
            assert cam.reconnect() is True
            frames = [cam.get_frame(2.0) for _ in range(10)]
            assert all(f.image.shape == (240, 320) for f in frames)  # the same settings as before
            ids = [f.frame_id for f in frames]
            assert ids == sorted(ids)
        finally:
            again.kill()


def test_exposure_and_gain_change_while_acquiring_and_are_read_back_from_the_device(fake_camera):
    """The console sets them live: what the device reports comes back (and rides on every frame);
    a value beyond the device's own bounds is refused and changes nothing."""
    from rig.errors import ConfigError

    cfg = CameraConfig(name="left", uri=fake_camera.uri, width=320, height=240, pixel_format="Mono8", fps=30.0,
                       trigger="free", exposure_us=2000.0, gain=5.0)
    with open_camera(cfg) as cam:
        cam.start()
        cam.get_frame(2.0)
        before = cam.controls()
        assert before["live"] and before["exposure_us"] == pytest.approx(2000.0) and before["gain"] == 5.0
        lo, hi = before["ranges"]["exposure_us"]
        after = cam.set_controls(exposure_us=3500.0, gain=7)
        assert after["exposure_us"] == pytest.approx(3500.0) and after["gain"] == 7.0
        assert cam._cam.get_float("ExposureTimeAbs") == pytest.approx(3500.0)
        deadline = time.monotonic() + 3.0
        while cam.get_frame(2.0).exposure_us != pytest.approx(3500.0):
            assert time.monotonic() < deadline, "frames never carried the new exposure"
        with pytest.raises(ConfigError, match="outside what the camera takes"):
            cam.set_controls(exposure_us=hi * 10 + 1, gain=6)
        with pytest.raises(ConfigError, match="must be a number"):
            cam.set_controls(exposure_us=float("nan"))
        assert cam.controls()["exposure_us"] == pytest.approx(3500.0) and cam.controls()["gain"] == 7.0
