"""The GoPro emulator, driven by the official Open GoPro Python SDK (`open-gopro`, `WiredGoPro`) and by
plain HTTP: it must pass for a camera to the SDK, and answer as the specification says.

The SDK builds its base URL from the serial (172.2X.1YZ.51:8080); `LoopbackGoPro` overrides the
SDK's `_base_url` property, the one place it reads the address from, to reach the emulator's port.
Its mDNS scanner (`open_gopro.network.wifi.mdns_scanner.find_first_ip_addr`) runs unchanged.
"""
from __future__ import annotations

import asyncio
import io
import json
import os
import socket
import time
from pathlib import Path

import av
import numpy as np
import pytest
import requests

from simulator.errors import SimulatorError
from simulator.gopro import GoProEmulator, read_time_code, usb_address

open_gopro = pytest.importorskip("open_gopro", reason="the official SDK is in the test extra (open-gopro)")
from open_gopro import WiredGoPro  # noqa: E402
from open_gopro.models import constants  # noqa: E402
from open_gopro.models.constants import settings as sdk_settings  # noqa: E402

SERIAL = "C3501324645504"


class LoopbackGoPro(WiredGoPro):
    """The SDK's wired GoPro, reaching the emulator on loopback instead of the USB subnet."""

    def __init__(self, url: str, serial: str | None = None, **kwargs):
        super().__init__(serial, **kwargs)
        self._loopback_url = url

    @property
    def _base_url(self) -> str:
        return self._loopback_url + "/"


@pytest.fixture()
def mdns_lock(tmp_path_factory):
    """Tests that advertise `_gopro-web._tcp` on loopback take turns (pytest-xdist workers share it)."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    with FileLock(str(shared / "gopro-mdns.lock")):
        yield


@pytest.fixture()
def camera(tmp_path):
    with GoProEmulator(SERIAL, width=320, height=180, fps=30.0, advertise=False, media_dir=tmp_path / "card",
                       busy_s=0.05) as cam:
        yield cam


def get(cam: GoProEmulator, path: str, **kw) -> requests.Response:
    return requests.get(cam.url + path, timeout=5, **kw)


def decode(data: bytes) -> list[np.ndarray]:
    with av.open(io.BytesIO(data)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


def wait_ready(cam: GoProEmulator, timeout: float = 10.0) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        state = get(cam, "/gopro/camera/state").json()
        if not state["status"]["8"] and not state["status"]["10"]:
            return state
        assert time.monotonic() < deadline, f"camera not ready: {state['status']}"
        time.sleep(0.02)


# --- the official SDK ------------------------------------------------------------------------------------------
async def _sdk_session(cam: GoProEmulator, download_to: Path) -> dict:
    found = {}
    async with LoopbackGoPro(cam.url, SERIAL, poll_period=0.05) as gopro:
        state = (await gopro.http_command.get_camera_state()).data
        found["ready"] = (state[constants.StatusId.BUSY], state[constants.StatusId.ENCODING])
        found["resolution"] = state[constants.SettingId.VIDEO_RESOLUTION]
        found["info"] = (await gopro.http_command.get_camera_info()).data
        assert (await gopro.http_command.set_shutter(shutter=constants.Toggle.ENABLE)).ok  # waits for encoding
        found["encoding"] = (await gopro.http_command.get_camera_state()).data[constants.StatusId.ENCODING]
        await asyncio.sleep(0.6)
        assert (await gopro.http_command.set_shutter(shutter=constants.Toggle.DISABLE)).ok
        media = (await gopro.http_command.get_media_list()).data  # waits for busy and encoding to clear
        found["files"] = [m.filename for m in media.files]
        found["last"] = str((await gopro.http_command.get_last_captured_media()).data)
        found["download"] = (await gopro.http_command.download_file(camera_file=media.files[0].filename,
                                                                     local_file=download_to)).ok
        await gopro.http_setting.frames_per_second.set(sdk_settings.FramesPerSecond.NUM_240_0)
        refused = await gopro.http_setting.video_resolution.set(sdk_settings.VideoResolution.NUM_5_3K)
        found["refused"] = (refused.ok, refused.data)
    return found


def test_the_official_sdk_connects_reads_state_records_and_lists_media(camera, tmp_path):
    found = asyncio.run(_sdk_session(camera, tmp_path / "clip.mp4"))

    assert found["ready"] == (False, False)
    assert found["resolution"] == sdk_settings.VideoResolution.NUM_1080
    assert found["info"].serial_number == SERIAL and found["info"].model_name == "HERO12 Black"
    assert found["encoding"] is True
    assert found["files"] == ["100GOPRO/GH010001.MP4"] and found["last"] == "100GOPRO/GH010001.MP4"
    assert found["download"]
    card_file = camera.media_dir / "DCIM" / "100GOPRO" / "GH010001.MP4"
    assert (tmp_path / "clip.mp4").read_bytes() == card_file.read_bytes()
    ok, body = found["refused"]  # 5.3K does not do 240 fps: the specification's 403 body
    assert not ok and body["error"] == 3 and body["setting_id"] == 2 and body["option_id"] == 100
    assert {o["id"] for o in body["supported_options"]} == {4, 9}
    # the SDK's opening sequence, in the order the SDK sends it
    paths = [r.path for r in camera.requests]
    assert paths[:3] == ["/gopro/camera/control/wired_usb", "/gopro/camera/analytics/set_client_info", "/gopro/version"]


async def _sdk_discovers(cam: GoProEmulator) -> tuple[str, bool]:
    gopro = LoopbackGoPro(cam.url, None, poll_period=0.05)  # no serial: the SDK browses mDNS for one
    await gopro.open(timeout=10)
    try:
        state = (await gopro.http_command.get_camera_state()).data
        return gopro.identifier, state[constants.StatusId.BUSY]
    finally:
        await gopro.close()


def test_the_sdk_mdns_scanner_finds_the_emulator_unchanged(mdns_lock, tmp_path):
    with GoProEmulator(SERIAL, width=64, height=48, media_dir=tmp_path, advertise=True) as cam:
        assert cam.wait_advertised(10)
        serial, busy = asyncio.run(_sdk_discovers(cam))
    assert serial == SERIAL and busy is False


# --- media ------------------------------------------------------------------------------------------------------
def test_a_recording_is_an_mp4_of_the_frames_of_its_encoding_interval(camera):
    get(camera, "/gopro/camera/control/wired_usb", params={"p": 1})
    assert get(camera, "/gopro/camera/shutter/start").status_code == 200
    status = get(camera, "/gopro/camera/state").json()["status"]
    assert status["10"] == 1 and status["8"] == 1  # encoding, and busy for a moment
    time.sleep(0.5)
    get(camera, "/gopro/camera/shutter/stop")
    assert get(camera, "/gopro/camera/state").json()["status"]["10"] == 0
    wait_ready(camera)

    listing = get(camera, "/gopro/media/list").json()
    (entry,) = listing["media"][0]["fs"]
    assert listing["media"][0]["d"] == "100GOPRO" and entry["n"] == "GH010001.MP4"
    assert all(isinstance(entry[k], str) for k in ("n", "cre", "mod", "s"))  # the camera sends strings
    assert abs(int(entry["cre"]) - time.time()) < 60
    data = get(camera, "/videos/DCIM/100GOPRO/GH010001.MP4").content
    assert len(data) == int(entry["s"])

    (rec,) = camera.recordings
    frames = decode(data)
    assert len(frames) == rec.frames and 14 <= rec.frames <= 20  # 0.5 s at 30 fps, and a request's latency
    assert frames[0].shape == (180, 320, 3)
    codes = [read_time_code(f) for f in frames]
    assert codes == [round(rec.frame_time(k) * 1000) & 0xFFFFFFFF for k in range(rec.frames)]
    assert get(camera, "/gopro/media/last_captured").json() == {"folder": "100GOPRO", "file": "GH010001.MP4"}


def test_a_photo_preset_takes_a_jpeg(camera):
    assert get(camera, "/gopro/media/last_captured").status_code == 204
    assert get(camera, "/gopro/camera/presets/load", params={"id": 65536}).status_code == 200
    wait_ready(camera)
    get(camera, "/gopro/camera/shutter/start")
    wait_ready(camera)
    last = get(camera, "/gopro/media/last_captured").json()
    assert last == {"folder": "100GOPRO", "file": "GOPR0001.JPG"}
    import cv2

    image = cv2.imdecode(np.frombuffer(get(camera, "/videos/DCIM/100GOPRO/GOPR0001.JPG").content, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (180, 320, 3)
    state = get(camera, "/gopro/camera/state").json()
    assert state["status"]["97"] == 65536 and state["status"]["96"] == 1001 and state["status"]["38"] == 1


def test_downloads_answer_byte_ranges(camera):
    get(camera, "/gopro/camera/shutter/start")
    time.sleep(0.2)
    get(camera, "/gopro/camera/shutter/stop")
    wait_ready(camera)
    url = "/videos/DCIM/100GOPRO/GH010001.MP4"
    whole = get(camera, url)
    size = len(whole.content)
    assert whole.status_code == 200 and whole.headers["Accept-Ranges"] == "bytes"

    tail = get(camera, url, headers={"Range": "bytes=100-"})
    assert tail.status_code == 206 and tail.headers["Content-Range"] == f"bytes 100-{size - 1}/{size}"
    assert tail.content == whole.content[100:]
    middle = get(camera, url, headers={"Range": "bytes=10-19"})
    assert middle.content == whole.content[10:20]
    suffix = get(camera, url, headers={"Range": "bytes=-7"})
    assert suffix.content == whole.content[-7:]
    past = get(camera, url, headers={"Range": f"bytes={size}-"})
    assert past.status_code == 416 and past.headers["Content-Range"] == f"bytes */{size}"
    assert get(camera, "/videos/DCIM/100GOPRO/GH019999.MP4").status_code == 404
    assert get(camera, "/videos/DCIM/100GOPRO/..%2F..%2Fetc").status_code == 404


# --- settings and presets ---------------------------------------------------------------------------------------
def test_settings_refused_as_the_specification_says(camera):
    setting = lambda sid, opt: get(camera, "/gopro/camera/setting", params={"setting": sid, "option": opt})  # noqa: E731
    assert get(camera, "/gopro/camera/setting", params={"setting": 3}).json() == {"option": 8}  # 30 fps
    assert setting(2, 100).status_code == 200  # 5.3K at 30 fps
    wait_ready(camera)
    refused = setting(3, 0)  # 240 fps at 5.3K
    assert refused.status_code == 403
    body = refused.json()
    assert body["error"] == 3 and body["setting_id"] == 3 and body["option_id"] == 0
    assert {o["id"] for o in body["supported_options"]} == {5, 6, 8, 9, 10}
    assert setting(2, 7).json()["error"] == 4  # 1440 is not an option of this camera
    assert setting(999, 1).json()["error"] == 2
    get(camera, "/gopro/camera/shutter/start")
    while_encoding = setting(121, 4)
    assert while_encoding.status_code == 403 and while_encoding.json()["error"] == 1
    get(camera, "/gopro/camera/shutter/stop")
    wait_ready(camera)
    assert setting(121, 4).status_code == 200
    state = wait_ready(camera)
    assert state["settings"]["121"] == 4 and state["settings"]["2"] == 100


def test_presets_hold_their_own_settings(camera):
    presets = get(camera, "/gopro/camera/presets/get").json()
    groups = {g["id"]: g for g in presets["presetGroupArray"]}
    assert set(groups) == {1000, 1001, 1002}
    cinematic = next(p for p in groups[1000]["presetArray"] if p["id"] == 2)
    assert {s["id"]: s["value"] for s in cinematic["settingArray"]}[2] == 1  # 4K
    assert get(camera, "/gopro/camera/presets/load", params={"id": 2}).status_code == 200
    state = wait_ready(camera)
    assert state["settings"]["2"] == 1 and state["status"]["97"] == 2
    assert get(camera, "/gopro/camera/presets/set_group", params={"id": 1002}).status_code == 200
    state = wait_ready(camera)
    assert state["status"]["96"] == 1002
    video_setting_in_timelapse = get(camera, "/gopro/camera/setting", params={"setting": 2, "option": 9})
    assert video_setting_in_timelapse.status_code == 403 and video_setting_in_timelapse.json()["error"] == 1
    assert get(camera, "/gopro/camera/presets/load", params={"id": 77}).status_code == 403


# --- keep-alive and faults --------------------------------------------------------------------------------------
def test_a_keep_alive_lapse_releases_wired_control(tmp_path):
    with GoProEmulator(SERIAL, width=64, height=48, advertise=False, media_dir=tmp_path, keep_alive_timeout_s=0.4) as cam:
        get(cam, "/gopro/camera/control/wired_usb", params={"p": 1})
        for _ in range(8):  # kept alive: stays in control
            time.sleep(0.1)
            get(cam, "/gopro/camera/keep_alive")
        assert get(cam, "/gopro/camera/state").json()["status"]["116"] == 1
        assert not [e for e in cam.events if e.kind == "keep-alive lapsed"]
        time.sleep(0.7)
        assert get(cam, "/gopro/camera/state").json()["status"]["116"] == 0
        assert [e.kind for e in cam.events] == ["keep-alive lapsed"]


def test_injected_errors_and_a_dropped_link(camera):
    camera.inject_http_errors(2, status=503)
    codes = [get(camera, "/gopro/camera/keep_alive").status_code for _ in range(3)]
    assert codes == [503, 503, 200]
    camera.inject_http_errors(seconds=0.3)
    assert get(camera, "/gopro/version").status_code == 500
    time.sleep(0.35)
    assert get(camera, "/gopro/version").status_code == 200

    camera.drop_link(0.8)
    with pytest.raises(requests.Timeout):
        requests.get(camera.url + "/gopro/version", timeout=0.3)
    time.sleep(0.6)
    assert get(camera, "/gopro/version").json() == {"version": "2.0"}
    assert [e.kind for e in camera.events] == ["link dropped", "link back"]
    with pytest.raises(SimulatorError, match="one of them"):
        camera.inject_http_errors(1, seconds=1.0)


def test_bad_serials_and_the_usb_address():
    assert usb_address("C0000123456789") == "172.27.189.51"  # the specification's example
    assert usb_address(SERIAL) == WiredGoPro(SERIAL).ip_address == "172.25.104.51"  # and the SDK's formula
    with pytest.raises(SimulatorError, match="three digits"):
        GoProEmulator("C35013246455XX")


def test_two_emulators_answer_on_their_own_ports(tmp_path):
    with GoProEmulator("C3501324645501", width=64, height=48, advertise=False, media_dir=tmp_path / "a", busy_s=0.02) as a, \
         GoProEmulator("C3501324645502", width=64, height=48, advertise=False, media_dir=tmp_path / "b", busy_s=0.02) as b:
        assert a.port != b.port
        get(a, "/gopro/camera/shutter/start")
        assert get(b, "/gopro/camera/state").json()["status"]["10"] == 0
        time.sleep(0.1)
        get(a, "/gopro/camera/shutter/stop")
        wait_ready(a)
        assert len(get(a, "/gopro/media/list").json()["media"][0]["fs"]) == 1
        assert get(b, "/gopro/media/list").json()["media"] == []
        assert get(b, "/gopro/camera/info").json()["serial_number"] == "C3501324645502"


# --- the webcam stream ------------------------------------------------------------------------------------------
class UdpSink:
    """A UDP port on loopback that keeps every datagram with its arrival time."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.datagrams: list[tuple[float, bytes]] = []
        self._stop = False
        import threading

        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop:
            try:
                data = self.sock.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                return
            self.datagrams.append((time.monotonic(), data))

    def data(self) -> bytes:
        return b"".join(d for _, d in list(self.datagrams))

    def close(self):
        self._stop = True
        self._thread.join(1)
        self.sock.close()


def decode_ts(data: bytes) -> list[np.ndarray]:
    with av.open(io.BytesIO(data), format="mpegts") as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


def test_two_webcams_stream_their_own_frames_to_their_own_ports(tmp_path):
    sinks = [UdpSink(), UdpSink()]
    cams = [GoProEmulator(f"C350132464550{i}", width=320, height=180, fps=fps, advertise=False,
                          media_dir=tmp_path / str(i)) for i, fps in ((1, 30.0), (2, 15.0))]
    try:
        for cam, sink in zip(cams, sinks):
            cam.start()
            answer = get(cam, "/gopro/webcam/start", params={"res": 12, "fov": 0, "port": sink.port, "protocol": "TS"})
            assert answer.json() == {"status": 2, "error": 0}
        time.sleep(1.5)
        for cam in cams:
            assert get(cam, "/gopro/webcam/stop").json() == {"status": 1, "error": 0}
        for cam, sink, other in zip(cams, sinks, reversed(cams)):
            frames = decode_ts(sink.data())
            assert abs(len(frames) - 1.5 * cam.fps) <= 0.5 * cam.fps, (cam.serial, len(frames))
            codes = [read_time_code(f) for f in frames]
            assert all(b > a for a, b in zip(codes, codes[1:]))
            steps = np.diff(codes) / 1000.0
            assert abs(np.median(steps) - 1 / cam.fps) < 0.25 / cam.fps  # each at its own rate
            for frame, code in zip(frames[::5], codes[::5]):
                own = np.abs(frame[30:].astype(int) - cam.render(code / 1000.0)[30:]).mean()
                theirs = np.abs(frame[30:].astype(int) - other.render(code / 1000.0)[30:]).mean()
                assert own < 12 and theirs > 3 * own, (own, theirs)  # never the other camera's picture
            assert cam.webcam.frames_sent >= len(frames)
    finally:
        for cam in cams:
            cam.stop()
        for sink in sinks:
            sink.close()


def test_a_stream_on_the_scene_clock_shows_each_frame_when_it_was_exposed_however_late_it_is_drawn(tmp_path):
    """A busy host draws the stream's first frame 0.3 s late (4.5 frame periods): frame k still shows
    t0 + k / fps, t0 the stream's start, none is skipped, and none is drawn before its exposure
    is over (an LED edge within it has then happened)."""
    calls: list[tuple[float, float]] = []  # (instant shown, when drawn)

    def render(t: float) -> np.ndarray:
        if not calls:
            time.sleep(0.3)
        calls.append((t, time.monotonic()))
        return np.zeros((180, 320, 3), np.uint8)

    sink = UdpSink()
    cam = GoProEmulator("C3501324645507", render, width=320, height=180, fps=15.0, advertise=False,
                        media_dir=tmp_path, stream_on_clock=True)
    try:
        cam.start()
        before = time.monotonic()
        assert get(cam, "/gopro/webcam/start", params={"port": sink.port, "protocol": "TS"}).json()["error"] == 0
        time.sleep(1.2)
        get(cam, "/gopro/webcam/stop")
    finally:
        cam.stop()
        sink.close()
    t0 = cam.stream_t0
    assert t0 is not None and before <= t0 < calls[0][1] - 0.3
    k = [(t - t0) * 15.0 for t, _ in calls]
    assert np.allclose(k, np.round(k), atol=1e-6) and [int(round(x)) for x in k] == list(range(len(k))), k
    assert all(drawn >= t + 1 / 15.0 - 1e-3 for t, drawn in calls)
    assert len(decode_ts(sink.data())) >= len(calls) - 1


def test_webcam_parameters_and_states(camera):
    sink = UdpSink()
    try:
        assert get(camera, "/gopro/webcam/status").json() == {"status": 0, "error": 0}
        bad = get(camera, "/gopro/webcam/start", params={"res": 99, "port": sink.port})
        assert bad.status_code == 200 and bad.json() == {"status": 0, "error": 6}
        assert get(camera, "/gopro/webcam/start", params={"protocol": "RTSP"}).status_code == 501
        get(camera, "/gopro/camera/shutter/start")
        assert get(camera, "/gopro/webcam/start", params={"port": sink.port}).json()["error"] == 4  # shutter
        get(camera, "/gopro/camera/shutter/stop")
        wait_ready(camera)
        assert get(camera, "/gopro/webcam/start", params={"port": sink.port}).json() == {"status": 2, "error": 0}
        assert get(camera, "/gopro/camera/state").json()["status"]["32"] == 1
        refused = get(camera, "/gopro/camera/setting", params={"setting": 135, "option": 0})
        assert refused.status_code == 403 and refused.json()["error"] == 1  # hypersmooth only with the webcam off
        assert get(camera, "/gopro/webcam/stop").json() == {"status": 1, "error": 0}
        assert get(camera, "/gopro/webcam/exit").json() == {"status": 0, "error": 0}
        assert get(camera, "/gopro/camera/setting", params={"setting": 135, "option": 0}).status_code == 200
        assert get(camera, "/gopro/webcam/preview").json() == {"status": 3, "error": 0}
        assert camera.webcam.port == sink.port
        get(camera, "/gopro/webcam/exit")
    finally:
        sink.close()


def test_a_keep_alive_lapse_stops_the_webcam_and_a_dropped_link_silences_it(tmp_path):
    sink = UdpSink()
    try:
        with GoProEmulator(SERIAL, width=160, height=96, fps=20.0, advertise=False, media_dir=tmp_path,
                           keep_alive_timeout_s=1.2) as cam:
            get(cam, "/gopro/camera/control/wired_usb", params={"p": 1})
            get(cam, "/gopro/webcam/start", params={"port": sink.port})
            time.sleep(0.4)
            get(cam, "/gopro/camera/keep_alive")
            cam.drop_link(0.6)
            t_drop = time.monotonic()
            time.sleep(0.6)
            during = [t for t, _ in sink.datagrams if t_drop + 0.05 < t < t_drop + 0.55]
            assert during == []  # silent while the link is down
            time.sleep(0.3)
            assert [t for t, _ in sink.datagrams if t > t_drop + 0.65]  # and back after it
            time.sleep(1.0)  # no keep-alive for 1.2 s: the camera gives the client up
            assert get(cam, "/gopro/webcam/status").json() == {"status": 0, "error": 5}
            t_off = time.monotonic()
            time.sleep(0.3)
            assert not [t for t, _ in sink.datagrams if t > t_off + 0.1]
            assert [e.kind for e in cam.events] == ["link dropped", "link back", "keep-alive lapsed"]
    finally:
        sink.close()
