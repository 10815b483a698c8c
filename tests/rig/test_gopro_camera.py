"""The gopro:// backend against GoPro emulators on loopback: live frames of two cameras at once, and
the link dropping or answering errors mid-run."""
from __future__ import annotations

import time

import numpy as np
import pytest

from rig.cameras import open_camera
from rig.cameras.gopro import parse_uri
from rig.config import CameraConfig
from rig.errors import CameraDisconnected, CameraTimeout, ConfigError
from simulator.gopro import GoProEmulator

W, H, FPS = 1280, 720, 30.0  # the emulated HERO12 streams 720p or 1080p


def _level(value: int):
    def render(t: float) -> np.ndarray:
        return np.full((H, W, 3), value, np.uint8)
    return render


def _camera(emulator: GoProEmulator, name: str):
    host = emulator.url.split("//", 1)[1].rstrip("/")
    cfg = CameraConfig(name=name, uri=f"gopro://{emulator.serial}@{host}", width=W, height=H, pixel_format="RGB8",
                       fps=FPS, trigger="free")
    cam = open_camera(cfg)
    cam.start()
    return cam


def _frames(cam, seconds: float) -> list:
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            out.append(cam.get_frame(0.2))
        except CameraTimeout:
            pass
    return out


@pytest.fixture
def two():
    emus = [GoProEmulator("C3501324645511", render=_level(40), width=W, height=H, fps=FPS, advertise=False),
            GoProEmulator("C3501324645512", render=_level(210), width=W, height=H, fps=FPS, advertise=False)]
    for e in emus:
        e.start()
    cams = []
    try:
        cams = [_camera(e, f"gp{i}") for i, e in enumerate(emus)]
        yield emus, cams
    finally:
        for c in cams:
            c.close()
        for e in emus:
            e.stop()


def test_two_gopros_stream_at_their_rate_and_never_mix(two):
    emus, cams = two
    assert cams[0].port != cams[1].port  # one UDP port per camera
    for cam in cams:
        cam.get_frame(5.0)  # the stream is there
    got = {c.name: [] for c in cams}
    end = time.monotonic() + 4.0
    while time.monotonic() < end:
        for c in cams:
            try:
                got[c.name].append(c.get_frame(0.005))
            except CameraTimeout:
                pass
    for c, level in zip(cams, (40, 210)):
        frames = got[c.name]
        means = [float(f.image.mean()) for f in frames]
        assert all(abs(m - level) < 8 for m in means), (c.name, min(means), max(means))  # only its own frames
        ids = [f.frame_id for f in frames]
        span = (frames[-1].device_ts_ns - frames[0].device_ts_ns) / 1e9
        rate = (ids[-1] - ids[0]) / span
        print(f"{c.name}: {len(frames)} frames in 4 s, stream rate {rate:.2f} fps, ids {ids[0]}..{ids[-1]}")
        assert abs(rate - FPS) < 0.5 and len(frames) >= 0.9 * 4 * FPS, (rate, len(frames))
        assert ids == sorted(set(ids))
        steps = np.diff([f.device_ts_ns for f in frames]) / 1e9
        assert np.all(steps > 0) and abs(np.median(steps) - 1 / FPS) < 0.002


def test_a_dropped_link_and_http_errors_are_survived(two):
    emus, cams = two
    cam, emu = cams[0], emus[0]
    before = _frames(cam, 1.0)
    assert before
    emu.inject_http_errors(4)  # the next requests fail (the keep-alive's among them): reconnect, go on
    emu.drop_link(3.0)  # no answer and no stream for 3 s
    lost_at = None
    deadline = time.monotonic() + 15
    after = []
    while time.monotonic() < deadline and len(after) < 30:
        try:
            after.append(cam.get_frame(0.5))
        except CameraTimeout:
            continue
        except CameraDisconnected:
            lost_at = lost_at or time.monotonic()
            time.sleep(0.5)
            cam.reconnect()
    assert lost_at is not None, "the silent stream was never reported"
    assert len(after) >= 30, f"frames did not resume: {len(after)}"
    # The gap: nothing while the link was down (a frame already on its way when the link dropped
    # may still come first, on a loaded machine).
    stamps = [f.host_ts_ns for f in before[-1:] + after]
    assert max(b - a for a, b in zip(stamps, stamps[1:])) > 2e9
    ids = [f.frame_id for f in before + after]
    assert ids == sorted(set(ids))  # frame ids go on increasing across the camera's new stream
    assert all(abs(float(f.image.mean()) - 40) < 8 for f in after)
    assert any(e.kind == "link lost" for e in cam.link_events), cam.link_events
    # the other camera never noticed
    other = _frames(cams[1], 1.0)
    assert len(other) >= 20


def test_bad_gopro_uris_and_settings_say_what_is_wrong():
    for uri, words in [("gopro://", "gopro://SERIAL"), ("gopro://XYZ", "three digits"),
                       ("gopro://C3501324645511@nohost", "HOST:PORT"), ("gopro://C3501324645511?port=80", "1024-65535"),
                       ("gopro://C3501324645511?colour=red", "unknown URI option")]:
        with pytest.raises(ConfigError, match=words):
            parse_uri(uri)
    assert parse_uri("gopro://C3501324645511")[1:] == (None, 8554 + 11)
    with GoProEmulator("C3501324645513", render=_level(90), width=W, height=H, advertise=False) as emu:
        host = emu.url.split("//", 1)[1].rstrip("/")
        for kw, words in [({"trigger": "hardware"}, "cannot be triggered"), ({"width": 1000}, "webcam stream is"),
                          ({"pixel_format": "BayerRG8"}, "RGB8 or Mono8")]:
            cfg = CameraConfig(name="gp", uri=f"gopro://C3501324645513@{host}", width=W, height=H, pixel_format="RGB8",
                               fps=FPS, trigger="free")
            for k, v in kw.items():
                setattr(cfg, k, v)
            with pytest.raises(ConfigError, match=words):
                open_camera(cfg)


def test_rig_discover_finds_a_gopro_by_mdns_and_the_uri_it_gives_opens():
    import json

    from tests.rig.cli_helpers import run_rig

    with GoProEmulator("C3501324645514", render=_level(120), width=W, height=H, fps=FPS) as emu:
        assert emu.wait_advertised(5.0)
        proc = run_rig("discover", "--json", timeout=60)
        assert proc.returncode == 0, proc.stderr
        found = [d for d in json.loads(proc.stdout)["devices"] if d["backend"] == "gopro"]
        assert [d["serial"] for d in found] == ["C3501324645514"], found
        cfg = CameraConfig(name="gp", uri=found[0]["uri"], width=W, height=H, pixel_format="RGB8", fps=FPS, trigger="free")
        with open_camera(cfg) as cam:
            cam.start()
            assert abs(float(cam.get_frame(5.0).image.mean()) - 120) < 8
