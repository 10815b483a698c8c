"""The venue console (rig console) in headless Chromium on a simulated rig: tiles and previews,
exposure set and read back, a take recorded, validated and listed, and who may do what.

Needs Debian's chromium and chromium-driver (the Makefile's system-deps install them); skipped without.
"""
from __future__ import annotations

import json
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.live.test_browser import CHROMEDRIVER, CHROMIUM, new_driver

pytestmark = [
    pytest.mark.skipif(not CHROMIUM.exists() or not CHROMEDRIVER.exists(),
                       reason="headless Chromium not installed (/usr/bin/chromium and /usr/bin/chromedriver: "
                              "apt-get install chromium chromium-driver, or make system-deps)"),
    pytest.mark.timeout(300),
]
OPERATOR, VIEWER = "operator-token-123", "viewer-token-456"


def wait_until(fn, timeout: float = 20.0, what: str = "condition", step: float = 0.05):
    deadline = time.monotonic() + timeout
    while True:
        value = fn()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(step)


@pytest.fixture(scope="module")
def rig_config(tmp_path_factory):
    from rig.config import dump_config, load_config, parse_config
    from rig.sim.rig_config import sim_rig_config

    root = tmp_path_factory.mktemp("console")
    data = sim_rig_config(4, width=320, height=180, fps=10.0)
    data["rig"]["storage"] = str(root / "takes")
    data["sim"]["loop_frames"] = 10
    data["cameras"][0]["sim"]["reconnect_after_s"] = 2.0  # the left camera comes back after an unplug
    path = root / "rig.toml"
    path.write_text(dump_config(parse_config(data, path)))
    return load_config(path)


@pytest.fixture(scope="module")
def console(rig_config):
    """The console on loopback without tokens (the operator is whoever reaches it), previews running."""
    from rig.console.rigstate import ConsoleRig
    from rig.console.server import ConsoleServer

    rig = ConsoleRig(rig_config).start()
    server = ConsoleServer(rig, "127.0.0.1", 0).start()
    try:
        wait_until(lambda: all(v.seq > 5 for v in rig.views.values()), 120, "frames from every camera")
        yield rig, server
    finally:
        server.stop()
        rig.close()


@pytest.fixture(scope="module")
def driver():
    d = new_driver()
    try:
        yield d
    finally:
        d.quit()


def data(driver, selector: str, key: str):
    return driver.execute_script("const e = document.querySelector(arguments[0]); return e ? (e.dataset[arguments[1]] ?? null) : null",
                                 selector, key)


def test_every_tile_shows_a_changing_preview_and_its_fps(console, driver):
    rig, server = console
    driver.get(server.url)
    names = sorted(rig.views)
    for name in names:
        wait_until(lambda: int(data(driver, f'[data-camera="{name}"]', "previews") or 0) >= 3, 20, f"3 previews of {name}")
    first = {n: data(driver, f'[data-camera="{n}"]', "seq") for n in names}
    srcs = {n: driver.execute_script(f"return document.querySelector('[data-camera=\"{n}\"] img').src") for n in names}
    time.sleep(1.5)
    for n in names:
        assert data(driver, f'[data-camera="{n}"]', "seq") != first[n], f"{n}'s preview did not change"
        assert driver.execute_script(f"return document.querySelector('[data-camera=\"{n}\"] img').src") != srcs[n]
        fps = float(wait_until(lambda: data(driver, f'[data-camera="{n}"]', "fps"), 10, f"{n}'s fps"))
        assert fps == pytest.approx(10.0, rel=0.05)
        text = driver.execute_script(f"return document.querySelector('[data-camera=\"{n}\"] .fps').textContent")
        assert "/ 10 fps" in text
        assert data(driver, f'[data-camera="{n}"]', "health") in ("ok", "warn")
    # the status API the tests and tools read
    with urllib.request.urlopen(server.url + "api/status") as r:
        status = json.load(r)
    assert {c["name"] for c in status["cameras"]} == set(names)
    assert all({"name", "role", "fps", "dropped", "exposure_us"} <= set(c) for c in status["cameras"])
    assert {"state", "take", "sets", "lost"} <= set(status["recording"]) and isinstance(status["takes"], list)


def test_an_exposure_set_on_the_page_is_reported_back_by_the_camera_and_a_refused_one_says_why(console, driver):
    rig, server = console
    driver.get(server.url)
    tile = '[data-camera="left"]'
    wait_until(lambda: data(driver, tile, "exposure"), 20, "the left tile's exposure")
    box = driver.find_element("css selector", f"{tile} input.exposure")
    box.clear()
    box.send_keys("2500")
    driver.find_element("css selector", f'{tile} [data-action="set-controls"]').click()
    wait_until(lambda: data(driver, tile, "exposure") == "2500", 5, "the camera's read-back of 2500 us", step=0.01)
    shown_after = float(data(driver, tile, "changedAt")) - float(data(driver, "body", "clickAt"))  # the page's own clock
    assert 0 < shown_after < 200, f"the new exposure showed {shown_after:.0f} ms after the click"
    # the frames carry it too, not only the camera's read-back
    wait_until(lambda: rig.views["left"].frame.exposure_us == pytest.approx(2500.0), 5, "frames exposed at 2500 us")
    box.clear()
    box.send_keys("250000")  # beyond one frame period at 10 fps
    driver.find_element("css selector", f'{tile} [data-action="set-controls"]').click()
    err = wait_until(lambda: driver.execute_script(f"return document.querySelector('{tile} .control-error').textContent"), 5, "the error")
    assert "outside what the camera takes" in err
    assert data(driver, tile, "exposure") == "2500"  # nothing changed
    # every camera at once
    driver.find_element("id", "all-gain").send_keys("3")
    driver.find_element("css selector", '[data-action="set-all"]').click()
    wait_until(lambda: all(data(driver, f'[data-camera="{n}"]', "gain") == "3" for n in rig.views), 5, "gain 3 dB on every camera")


def test_a_take_is_recorded_under_a_typed_name_stopped_validated_and_listed(console, driver):
    rig, server = console
    driver.get(server.url)
    wait_until(lambda: driver.execute_script("return document.body.dataset.activity") == "previewing", 20, "previews")
    name = driver.find_element("id", "take-name")
    name.clear()
    name.send_keys("scene-07")
    notes = driver.find_element("id", "take-notes")
    notes.send_keys("two walkers, lights at 60 %")
    wait_until(lambda: driver.execute_script("return document.body.dataset.notesSaved"), 5, "the notes saved as typed")
    draft = Path(rig.storage) / ".console" / "notes" / "scene-07.txt"
    assert draft.read_text() == "two walkers, lights at 60 %"
    driver.find_element("css selector", '[data-action="record"]').click()
    wait_until(lambda: driver.execute_script("return document.body.dataset.recording") in ("starting", "recording"), 2,
               "the take's state", step=0.01)
    shown_after = float(data(driver, "body", "recordingChangedAt")) - float(data(driver, "body", "clickAt"))
    assert 0 < shown_after < 200, f"the take's state showed {shown_after:.0f} ms after the click"
    wait_until(lambda: driver.execute_script("return document.body.dataset.recording") == "recording", 60, "recording")
    assert driver.find_element("id", "take-name").get_attribute("disabled")  # locked while the take runs
    wait_until(lambda: rig.status()["recording"]["sets"] >= 20, 60, "20 sets recorded")
    driver.find_element("css selector", '[data-action="stop"]').click()
    wait_until(lambda: driver.execute_script("return document.body.dataset.recording") == "done", 60, "the take's end")
    row = '[data-take="scene-07"]'
    wait_until(lambda: data(driver, row, "valid") == "true", 30, "scene-07 listed as valid")
    take = Path(rig.storage) / "scene-07"
    from rig.storage.validate import validate

    v = validate(take)
    assert v.readable and v.sets >= 20 and v.complete_sets == v.sets
    assert (take / "notes.txt").read_text() == "two walkers, lights at 60 %" and not draft.exists()
    wait_until(lambda: driver.find_element("id", "take-name").get_attribute("value") == "scene-08", 5, "the next name offered")
    # the same name again is refused, in one line, and nothing is recorded
    r = _post(server.url + "api/record/start", {"take": "scene-07"})
    assert r[0] == 400 and "exists already" in r[1]["error"]


def _post(url: str, body: dict, headers: dict | None = None) -> tuple[int, dict]:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                 headers={"Content-Type": "application/json", **(headers or {})})
    try:
        with urllib.request.urlopen(req) as r:
            return r.status, json.load(r)
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"{}")


def test_bad_values_get_one_clear_error_each_and_change_nothing(console):
    rig, server = console
    before = rig.status()["cameras"][0]["exposure_us"]
    for body, said in (({"camera": "left", "exposure_us": "fast"}, "must be a finite number"),
                       ({"camera": "left", "exposure_us": -3}, "outside"),
                       ({"camera": "left", "gain": 1e9}, "outside"),
                       ({"camera": "nope", "gain": 1}, "no camera 'nope'"),
                       ({"camera": "left", "exposure_us": 1000, "colour": 1}, "unknown field"),
                       ({"camera": "*"}, "give exposure_us and/or gain")):
        status, reply = _post(server.url + "api/controls", body)
        assert status == 400 and said in reply["error"], (body, reply)
    assert rig.status()["cameras"][0]["exposure_us"] == before
    req = urllib.request.Request(server.url + "api/controls", data=b"{not json", method="POST")
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(req)
    assert e.value.code == 400
    status, reply = _post(server.url + "api/record/start", {"take": "../escape"})
    assert status == 400 and "take name" in reply["error"]
    status, reply = _post(server.url + "api/controls", {"camera": "left", "gain": 1, "pad": "x" * 20000})
    assert status == 413


def test_a_foreign_origin_a_missing_token_and_a_viewer_token_are_refused(rig_config, driver):
    from rig.console.rigstate import ConsoleRig
    from rig.console.server import ConsoleServer

    rig = ConsoleRig(rig_config)  # not started: access is under test, not the cameras
    server = ConsoleServer(rig, "127.0.0.1", 0, operator_token=OPERATOR, viewer_token=VIEWER).start()
    try:
        url = server.url
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(url + "api/status")
        assert e.value.code == 401
        ok = urllib.request.Request(url + "api/status", headers={"Authorization": f"Bearer {VIEWER}"})
        with urllib.request.urlopen(ok) as r:
            assert json.load(r)["role"] == "viewer"
        status, reply = _post(url + "api/record/start", {"take": "x1"}, {"Authorization": f"Bearer {VIEWER}"})
        assert status == 403 and "viewer" in reply["error"]
        status, reply = _post(url + "api/record/stop", {}, {"Authorization": f"Bearer {OPERATOR}", "Origin": "http://evil.example"})
        assert status == 403 and "origin" in reply["error"]
        # the viewer's page: controls disabled
        driver.delete_all_cookies()
        driver.get(url + f"?token={VIEWER}")
        wait_until(lambda: driver.execute_script("return document.body.dataset.role") == "viewer", 10, "the viewer's status")
        assert driver.find_element("css selector", '[data-action="record"]').get_attribute("disabled")
        # a WebSocket from another origin is refused
        import websockets.sync.client as wsc

        with pytest.raises(Exception):
            with wsc.connect(url.replace("http", "ws") + f"ws?token={OPERATOR}", origin="http://evil.example", open_timeout=5):
                pass
    finally:
        server.stop()


def test_a_sync_check_from_the_page_gives_its_verdict_and_the_board_figures_show(console, driver):
    rig, server = console
    driver.get(server.url)
    wait_until(lambda: driver.execute_script("return document.body.dataset.activity") == "previewing", 60, "previews")
    wait_until(lambda: (rig.status()["sync"]["board"] or {}).get("pulses"), 20, "the board's pulses")
    shown = lambda: driver.execute_script("const e = document.querySelector('[data-figure=\"pulses\"]'); return e ? e.textContent : ''")
    wait_until(lambda: shown().isdigit() and int(shown()) > 0, 5, "the pulses on the page")
    box = driver.find_element("id", "sync-seconds")
    box.clear()
    box.send_keys("3")
    driver.find_element("css selector", '[data-action="sync-check"]').click()
    wait_until(lambda: driver.execute_script("return document.body.dataset.syncCheck") in ("starting", "running", "done"), 2, "the check's state")
    assert driver.find_element("css selector", '[data-action="record"]').get_attribute("disabled")  # one piece of work at a time
    verdict = wait_until(lambda: driver.execute_script("return document.body.dataset.syncVerdict"), 90, "the verdict")
    assert verdict == "pass", rig.status()["sync"]["check"]
    report = rig.status()["sync"]["check"]["report"]
    assert report["sets"] >= 25 and report["skew_us"]["p99"] is not None
    # previews went on during the check and come back after it
    wait_until(lambda: driver.execute_script("return document.body.dataset.activity") == "previewing", 60, "previews again")
    status, reply = _post(server.url + "api/sync-check", {"seconds": -1})
    assert status == 400 and "seconds" in reply["error"]


def test_a_camera_that_goes_and_comes_back_is_a_banner_and_the_host_checks_are_a_panel(console, driver):
    rig, server = console
    driver.get(server.url)
    wait_until(lambda: driver.execute_script("return document.body.dataset.activity") == "previewing", 60, "previews")
    wait_until(lambda: rig.session is not None and "left" in rig.session.cameras, 10, "the preview session")
    rig.session.cameras["left"].unplug()  # the simulated camera's own fault: its cable pulled
    wait_until(lambda: "camera" in (driver.execute_script("return document.body.dataset.faults") or "").split()
               or "camera_lost" in (driver.execute_script("return document.body.dataset.faults") or ""), 20, "a banner for the lost camera")
    wait_until(lambda: "camera_back" in (driver.execute_script("return document.body.dataset.faults") or ""), 30, "the camera back")
    text = driver.find_element("id", "banners").text
    assert "left" in text
    wait_until(lambda: data(driver, '[data-camera="left"]', "health") in ("ok", "warn"), 20, "the left tile healthy again")
    driver.find_element("css selector", '[data-action="doctor"]').click()
    verdict = wait_until(lambda: driver.execute_script("return document.body.dataset.doctor") not in ("", "running", None)
                         and driver.execute_script("return document.body.dataset.doctor"), 120, "the doctor's verdict")
    assert verdict in ("ok", "warn", "fail")
    rows = driver.execute_script("return document.querySelectorAll('#doctor tbody tr').length")
    assert rows >= 5  # a line per check: usb, network, devices, memory, disk, compute
    assert any(c["area"] == "disk" for c in rig.status()["health"]["checks"])


def test_the_live_tab_starts_rig_lives_engine_on_the_consoles_frames_and_shows_the_novel_view(console, driver):
    import cv2
    import numpy as np

    rig, server = console
    driver.get(server.url)
    wait_until(lambda: data(driver, "body", "role") == "operator", 20, "the first status")
    driver.find_element("css selector", '[data-action="live"]').click()
    assert data(driver, "body", "tab") == "live"
    wait_until(lambda: data(driver, "body", "live") == "running", 120, "the live view to start")
    try:
        frame = wait_until(lambda: driver.find_elements("css selector", "#live-frame[src='live/']"), 10, "the live frame")[0]
        driver.switch_to.frame(frame)
        first = int(wait_until(lambda: data(driver, "body", "lastSet"), 60, "a novel view drawn in the live tab"))
        wait_until(lambda: int(data(driver, "body", "lastSet") or 0) > first, 60, "a newer frame set drawn")
        driver.switch_to.default_content()
        # the novel view is a picture of the rig's scene, rendered from the console's own frame sets
        with urllib.request.urlopen(server.url + "live/snapshot.png", timeout=60) as r:
            shot = cv2.imdecode(np.frombuffer(r.read(), np.uint8), cv2.IMREAD_COLOR)
        assert shot is not None and shot.std() > 10
        assert rig.live.source is not None and rig.live.source.incomplete == 0
        # the previews keep running beside it
        seq = rig.views["left"].seq
        wait_until(lambda: rig.views["left"].seq > seq + 3, 10, "previews beside the live view")
    finally:
        driver.switch_to.default_content()
        driver.find_element("css selector", '[data-tab="rig"]').click()
        request = urllib.request.Request(server.url + "api/live/stop", method="POST", data=b"{}",
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=30) as r:
            assert json.load(r)["state"] == "off"
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(server.url + "live/status", timeout=10)
    assert err.value.code == 503
