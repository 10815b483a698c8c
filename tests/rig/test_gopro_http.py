"""Our Open GoPro HTTP client against the GoPro emulator (a real HTTP peer on loopback): connect,
state, settings, shutter, media, resumable downloads, the keep-alive watchdog, discovery, and every
request it can send checked against the specification."""
from __future__ import annotations

import json
import os
import re
import threading
import time
from pathlib import Path

import pytest
import usb.backend

from rig.cameras import gopro_http
from rig.cameras.gopro_http import (
    ENDPOINTS,
    SETTINGS,
    WEBCAM_FOVS,
    WEBCAM_RESOLUTIONS,
    GoProClient,
    LinkDown,
    discover_mdns,
    discover_usb,
    resolution_for_size,
    usb_base_url,
)
from rig.errors import CameraDisconnected, ConfigError, DeviceError, DeviceNotFound
from simulator.gopro import GoProEmulator

SERIAL = "C3501324645504"
SPEC = Path(__file__).resolve().parents[2].parent / "shared" / "reference" / "open-gopro-http-openapi.json"
FAST = dict(timeout_s=1.0, keep_alive_s=0.2, poll_s=0.02, failures_to_drop=2, reconnect_backoff_s=(0.05, 0.4),
            ready_timeout_s=5.0)


@pytest.fixture()
def camera(tmp_path):
    with GoProEmulator(SERIAL, width=320, height=180, fps=30.0, advertise=False, media_dir=tmp_path / "card",
                       busy_s=0.05, keep_alive_timeout_s=1.0) as cam:
        yield cam


@pytest.fixture()
def client(camera):
    c = GoProClient(SERIAL, base_url=camera.url, **FAST).connect()
    yield c
    c.close()


def record(client: GoProClient, seconds: float) -> None:
    client.shutter_start()
    time.sleep(seconds)
    client.shutter_stop()


def one_line(exc: BaseException) -> str:
    text = str(exc)
    assert "\n" not in text and text.startswith(f"gopro://{SERIAL}")
    return text


# --- the session ------------------------------------------------------------------------------------------------
def test_connect_state_shutter_media_and_download(camera, client, tmp_path):
    assert [r.path for r in camera.requests][:3] == [
        "/gopro/camera/control/wired_usb", "/gopro/camera/analytics/set_client_info", "/gopro/version"]
    assert camera.requests[0].query == {"p": "1"}
    info = client.info()
    assert info.serial_number == SERIAL and info.model_name == "HERO12 Black"
    state = client.state()
    assert state.ready and state.status[116] == 1 and state.settings[2] == 9  # wired control, 1080

    record(client, 0.4)
    items = client.media_list()  # waits until the file is written
    assert [i.path for i in items] == ["100GOPRO/GH010001.MP4"]
    assert client.last_captured().path == "100GOPRO/GH010001.MP4"
    path = client.download(items[0], tmp_path / "take")
    assert path == tmp_path / "take" / "GH010001.MP4"
    assert path.read_bytes() == (camera.media_dir / "DCIM" / "100GOPRO" / "GH010001.MP4").read_bytes()
    assert path.stat().st_size == items[0].size
    assert not (tmp_path / "take" / "GH010001.MP4.part").exists()


def test_settings_and_presets(camera, client):
    client.set_resolution("4K")
    client.set_fps(60)
    client.set_lens("linear")
    state = client.state()
    assert (state.settings[2], state.settings[3], state.settings[121]) == (1, 5, 4)
    assert client.get_setting(gopro_http.FPS) == 5
    presets = {p.id: p for p in client.presets()}
    assert presets[0].modified and presets[0].settings[121] == 4
    client.load_preset(2)
    client.load_preset_group("photo")
    assert client.state().status[96] == 1001
    with pytest.raises(DeviceError, match="refused preset 12345"):
        client.load_preset(12345)
    assert resolution_for_size(1920, 1080) == "1080"
    with pytest.raises(ConfigError, match="not 100x100"):
        resolution_for_size(100, 100)


def test_a_refused_setting_is_one_line_naming_the_setting_and_the_option(client):
    client.set_fps(240)
    with pytest.raises(DeviceError) as refused:
        client.set_resolution("5.3K")
    assert one_line(refused.value) == (
        f"gopro://{SERIAL}: the camera refused video resolution (setting 2) = 5.3k (option 100): "
        "option not available now; allowed now: 2.7K (4), 1080 (9)")
    with pytest.raises(ConfigError, match=r"frame rate '33' is not one of: 240, 200, 120"):
        client.set_fps(33)
    client.shutter_start()
    with pytest.raises(DeviceError, match=r"camera still encoding after 0.3 s \(stop the recording first\)"):
        client.wait_ready(timeout=0.3)
    client.shutter_stop()


def test_commands_wait_until_the_camera_is_ready(camera, client):
    camera.hold_busy(0.5)
    t0 = time.monotonic()
    client.set_lens("wide")
    assert time.monotonic() - t0 >= 0.4
    camera.hold_busy(3.0)
    slow = GoProClient(SERIAL, base_url=camera.url, **{**FAST, "ready_timeout_s": 0.3}, watchdog=False)
    with pytest.raises(DeviceError) as busy:
        slow.connect()
    assert one_line(busy.value) == f"gopro://{SERIAL}: camera still busy after 0.3 s"
    slow.close()


def test_an_interrupted_download_resumes_where_it_stopped(camera, client, tmp_path):
    record(client, 1.0)
    (item,) = client.media_list()
    assert item.size > 12_000
    camera.cut_next_download(item.size // 2)
    with pytest.raises(CameraDisconnected) as cut:
        client.download(item, tmp_path, chunk_size=1024)
    assert "download again to resume" in one_line(cut.value)
    part = tmp_path / "GH010001.MP4.part"
    kept = part.stat().st_size
    assert 0 < kept <= item.size // 2 and not (tmp_path / "GH010001.MP4").exists()

    n = len(camera.requests)
    path = client.download(item, tmp_path)
    downloads = [r for r in list(camera.requests)[n:] if r.path.startswith("/videos/")]
    assert [r.range for r in downloads] == [f"bytes={kept}-"]  # continued, not restarted
    assert path.read_bytes() == (camera.media_dir / "DCIM" / "100GOPRO" / item.name).read_bytes()
    assert not part.exists()
    n = len(camera.requests)
    assert client.download(item, tmp_path) == path  # already complete: nothing fetched
    assert not [r for r in list(camera.requests)[n:] if r.path.startswith("/videos/")]


# --- the watchdog -----------------------------------------------------------------------------------------------
def test_keep_alive_goes_out_every_period(camera, client):
    time.sleep(1.1)
    beats = [r.time for r in camera.requests if r.path == "/gopro/camera/keep_alive"]
    assert 4 <= len(beats) <= 7  # every 0.2 s
    assert max(b - a for a, b in zip(beats, beats[1:])) < 0.45
    assert not [e for e in camera.events if e.kind == "keep-alive lapsed"]


def test_the_watchdog_survives_http_errors(camera):
    seen: list = []
    c = GoProClient(SERIAL, base_url=camera.url, on_event=seen.append, **FAST).connect()
    try:
        camera.inject_http_errors(3)
        lost = c.wait_event("link lost", 3.0)
        back = c.wait_event("reconnected", 3.0)
        assert lost is not None and "HTTP 500" in lost.detail
        assert back is not None and back.monotonic > lost.monotonic and back.time >= lost.time
        assert c.link_up and [e.kind for e in seen] == ["link lost", "reconnected"]
        assert c.state().ready  # commands work again
        assert c.info().serial_number == SERIAL
    finally:
        c.close()


def test_the_watchdog_survives_a_dropped_link(camera, client):
    camera.drop_link(2.5)  # two keep-alives (1 s timeout) go unanswered
    lost = client.wait_event("link lost", 4.0)
    assert lost is not None and "timed out" in lost.detail
    with pytest.raises(LinkDown) as down:
        client.state()
    assert one_line(down.value).endswith("reconnecting")
    back = client.wait_event("reconnected", 4.0)
    assert back is not None and back.monotonic > lost.monotonic
    reconnect = [r for r in camera.requests if r.time >= back.monotonic - 1.0 and r.path.endswith("/wired_usb")]
    assert reconnect and reconnect[-1].query == {"p": "1"}  # the connect sequence ran again
    record(client, 0.2)
    assert [i.name for i in client.media_list()] == ["GH010001.MP4"]


def test_a_camera_that_does_not_answer(tmp_path):
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    c = GoProClient(SERIAL, base_url=f"http://127.0.0.1:{port}", **FAST)
    with pytest.raises(DeviceNotFound) as nobody:
        c.connect()
    assert one_line(nobody.value) == (f"gopro://{SERIAL}: no answer at http://127.0.0.1:{port} (connection refused); "
                                      "is the camera on and plugged in by USB?")
    assert usb_base_url(SERIAL) == "http://172.25.104.51:8080"
    with pytest.raises(ConfigError, match="ending in three digits"):
        GoProClient("C35013246455XY")
    with pytest.raises(ConfigError, match="not a camera media path"):
        c.download("../../etc/passwd", tmp_path)


def test_two_cameras_do_not_interfere(tmp_path):
    with GoProEmulator("C3501324645501", width=64, height=48, advertise=False, media_dir=tmp_path / "a", busy_s=0.02) as a, \
         GoProEmulator("C3501324645502", width=64, height=48, advertise=False, media_dir=tmp_path / "b", busy_s=0.02) as b:
        ca = GoProClient(a.serial, base_url=a.url, **FAST).connect()
        cb = GoProClient(b.serial, base_url=b.url, **FAST).connect()
        try:
            record(ca, 0.2)
            cb.set_fps(60)
            a.inject_http_errors(seconds=0.6)
            assert ca.wait_event("link lost", 3.0) is not None
            assert ca.wait_event("reconnected", 3.0) is not None
            assert [i.name for i in ca.media_list()] == ["GH010001.MP4"] and cb.media_list() == []
            assert cb.events() == [] and cb.state().settings[3] == 5 and ca.state().settings[3] == 8
        finally:
            ca.close()
            cb.close()


# --- discovery --------------------------------------------------------------------------------------------------
@pytest.fixture()
def mdns_lock(tmp_path_factory):
    """Tests that advertise `_gopro-web._tcp` on loopback take turns (pytest-xdist workers share it)."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    with FileLock(str(shared / "gopro-mdns.lock")):
        yield


def test_discovery_by_mdns_on_loopback(mdns_lock, tmp_path):
    with GoProEmulator("C3501324645509", width=64, height=48, media_dir=tmp_path) as cam:
        assert cam.wait_advertised(10)
        found = [d for d in discover_mdns(5.0, interfaces=["127.0.0.1"]) if d.serial == cam.serial]
        assert [(d.address, d.port, d.source, d.uri) for d in found] == [
            ("127.0.0.1", cam.port, "mdns", "gopro://C3501324645509")]
        assert found[0].base_url == cam.url


class _UsbBus(usb.backend.IBackend):
    """A pyusb backend standing in for libusb: the bus shows these devices (vendor, product, name,
    serial) and answers their string descriptors, as the kernel would."""

    def __init__(self, devices):
        self.devices = devices

    def enumerate_devices(self):
        return iter(range(len(self.devices)))

    def get_device_descriptor(self, dev):
        from types import SimpleNamespace

        vid, pid, product, serial = self.devices[dev]
        return SimpleNamespace(bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
                               bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=vid, idProduct=pid, bcdDevice=0x100,
                               iManufacturer=0, iProduct=1, iSerialNumber=2 if serial else 0, bNumConfigurations=1,
                               address=dev + 2, bus=1, port_number=dev + 1, port_numbers=(dev + 1,), speed=3)

    def open_device(self, dev):
        return dev

    def close_device(self, handle):
        pass

    def ctrl_transfer(self, handle, request_type, request, value, index, data, timeout):
        _, _, product, serial = self.devices[handle]
        text = {0: None, 1: product, 2: serial}[value & 0xFF]
        payload = b"\x09\x04" if text is None else text.encode("utf-16-le")  # string 0: the language ids (en-US)
        descriptor = bytes([2 + len(payload), 3]) + payload
        n = min(len(data), len(descriptor))
        data[:n] = type(data)(data.typecode, descriptor[:n])
        return n


def test_discovery_by_usb_finds_gopros_by_vendor_id():
    bus = _UsbBus([(0x2672, 0x0059, "HERO12 Black", "C3501324645504"), (0x046D, 0xC31C, "USB Keyboard", "K1"),
                   (0x2672, 0x0056, "HERO11 Black", "")])
    found = discover_usb(backend=bus)
    assert [(d.serial, d.address, d.name, d.source, d.extra["product_id"]) for d in found] == [
        ("", "", "HERO11 Black", "usb", "0056"),  # serial unreadable: no address
        ("C3501324645504", "172.25.104.51", "HERO12 Black", "usb", "0059")]
    assert all(d.source == "usb" for d in discover_usb())  # this machine: no GoPro (or no USB at all): no error


# --- the specification ------------------------------------------------------------------------------------------
def _spec() -> dict:
    if not SPEC.is_file():
        pytest.skip(f"the Open GoPro specification is not available: {SPEC} is absent (it ships beside the checkout "
                    "in ../shared/reference)")
    return json.loads(SPEC.read_text())


def _params(operation: dict) -> dict[str, dict]:
    return {p["name"]: p for p in operation.get("parameters", [])}


def _spec_operation(spec: dict, path: str, query: dict) -> tuple[str, dict] | None:
    """The spec's GET operation for a request (settings are listed per id: /gopro/camera/setting?setting=N)."""
    paths = spec["paths"]
    if path == "/gopro/camera/setting" and "setting" in query:
        key = f"{path}?setting={query['setting']}"
        return (key, paths[key]["get"]) if key in paths and "get" in paths[key] else None
    for key, item in paths.items():
        if "get" not in item or "?" in key:
            continue
        pattern = "^" + re.sub(r"\\\{[^}]+\\\}", "[^/]+", re.escape(key)) + "$"
        if re.match(pattern, path):
            return key, item["get"]
    return None


def test_every_request_in_the_client_table_is_in_the_specification():
    spec = _spec()
    paths = spec["paths"]
    for name, endpoint in ENDPOINTS.items():
        if endpoint.path == "/gopro/camera/setting":
            for setting in SETTINGS.values():
                key = f"/gopro/camera/setting?setting={setting.id}"
                assert key in paths, f"{setting.name}: {key} is not in the specification"
                option = _params(paths[key]["get"])["option"]
                assert set(setting.options.values()) <= set(option["schema"]["enum"]), setting.name
            continue
        assert endpoint.path in paths and "get" in paths[endpoint.path], f"{name}: {endpoint.path}"
        declared = set(_params(paths[endpoint.path]["get"]))
        path_params = set(re.findall(r"\{([^}]+)\}", endpoint.path))
        assert set(endpoint.params) | path_params <= declared, f"{name}: {endpoint.params} not all declared"
    shutter = _params(paths["/gopro/camera/shutter/{mode}"]["get"])["mode"]["schema"]["enum"]
    assert set(shutter) == {"start", "stop"}
    webcam = _params(paths["/gopro/webcam/start"]["get"])
    for res in WEBCAM_RESOLUTIONS.values():
        assert re.search(rf"\|\s*{res}\s*\|", webcam["res"]["description"])
    for fov in WEBCAM_FOVS.values():
        assert re.search(rf"\|\s*{fov}\s*\|", webcam["fov"]["description"])
    assert "TS" in webcam["protocol"]["schema"]["enum"]
    groups = _params(paths["/gopro/camera/presets/set_group"]["get"])["id"]["schema"]["enum"]
    assert set(gopro_http.PRESET_GROUPS.values()) <= set(groups)


def test_every_request_the_client_sent_in_a_session_is_in_the_specification(camera, client, tmp_path):
    spec = _spec()
    # everything the client can do, including its watchdog's reconnect
    client.info(); client.presets(); client.load_preset(0); client.load_preset_group("video")  # noqa: E702
    for setting in SETTINGS.values():
        client.get_setting(setting)
    client.set_resolution("1080"); client.set_fps(30); client.set_lens("wide"); client.set_hypersmooth("off")  # noqa: E702
    with pytest.raises(DeviceError):
        client.set_resolution("1440")
    record(client, 0.2)
    (item,) = client.media_list()
    client.last_captured()
    client.download(item, tmp_path)
    client.webcam_status()
    client.webcam_exit()
    client.webcam_stop()
    camera.inject_http_errors(2)
    assert client.wait_event("reconnected", 3.0) is not None
    time.sleep(0.3)

    sent = list(camera.requests)
    assert len(sent) > 20
    used = set()
    for request in sent:
        found = _spec_operation(spec, request.path, request.query)
        assert found is not None, f"{request.path} is not in the specification"
        key, operation = found
        declared = set(_params(operation)) | ({"setting"} if "?setting=" in key else set())
        assert set(request.query) <= declared, f"{request.path}: {sorted(request.query)} vs {sorted(declared)}"
        used.add(key.split("?")[0])
    assert used >= {e.path for n, e in ENDPOINTS.items() if not n.startswith("webcam_") or n in ("webcam_status",
                                                                                                    "webcam_exit",
                                                                                                    "webcam_stop")}
