"""The viewer page (rig/live/static/) in headless Chromium, driven by Selenium, against a live server.

Needs Debian's chromium and chromium-driver (the Makefile's system-deps install them); skipped
without them. The page's state is read from `document.body.dataset` and `window.rigLive`.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.live.conftest import model_rate, start_server, wait_until

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
pytestmark = [
    pytest.mark.parametrize("live_rig", ["sim"], indirect=True),  # the real engine on a simulated rig
    pytest.mark.skipif(not CHROMIUM.exists() or not CHROMEDRIVER.exists(),
                       reason="headless Chromium not installed (/usr/bin/chromium and /usr/bin/chromedriver: "
                              "apt-get install chromium chromium-driver, or make system-deps)"),
    pytest.mark.timeout(240),  # the first test also waits for the test model's export and the rig's start
]
TOKEN = "browser-test-token"


def new_driver():
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    os.environ.setdefault("SE_OFFLINE", "true")  # Selenium Manager never looks for a browser online
    options = Options()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1280,900",
                "--disable-dev-shm-usage", "--disable-extensions", "--no-first-run"):
        options.add_argument(arg)
    options.binary_location = str(CHROMIUM)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    driver.set_page_load_timeout(20)
    driver.set_script_timeout(10)
    return driver


@pytest.fixture(scope="module")
def driver():
    d = new_driver()
    try:
        yield d
    finally:
        d.quit()


@pytest.fixture
def page(driver, live_rig, server):
    """The driver on the viewer page of a fresh server, frames drawing."""
    driver.delete_all_cookies()
    driver.get(server.url)
    wait_frames(driver, 3)
    return driver


# --- reading the page ---------------------------------------------------------------------------------------
def data(driver, key: str):
    return driver.execute_script("return document.body.dataset[arguments[0]] ?? null", key)


def frames_drawn(driver) -> int:
    return int(data(driver, "framesDrawn") or 0)


def wait_frames(driver, n: int, timeout: float = 10.0) -> int:
    start = frames_drawn(driver)
    return wait_until(lambda: frames_drawn(driver) >= start + n and frames_drawn(driver), timeout,
                      what=f"{n} frames drawn (console: {console(driver)})")


def console(driver) -> str:
    try:
        return "; ".join(e["message"] for e in driver.get_log("browser"))[-500:]
    except Exception:
        return "?"


def pixel(driver, fx: float = 0.5, fy: float = 0.6) -> tuple[int, int, int]:
    r, g, b, _ = driver.execute_script("return window.rigLive.pixel(arguments[0], arguments[1])", fx, fy)
    return r, g, b


def close_to(rgb, expected, tol: int = 10) -> bool:
    return all(abs(a - b) <= tol for a, b in zip(rgb, expected))


def page_viewer(driver, live_rig):
    vid = int(wait_until(lambda: data(driver, "viewer"), what="the hello message"))
    return next(v for v in live_rig.engine.viewers if v.id == vid)


def wait_view(driver) -> int:
    """Until the page draws frames of the viewpoint it asked for last; that viewpoint's id."""
    def settled():
        state = driver.execute_script("return [document.body.dataset.seq, document.body.dataset.seqAnswered,"
                                      " document.body.dataset.requestedViewpoint, document.body.dataset.lastViewpoint]")
        seq, answered, want, got = state
        return seq is not None and seq == answered and want is not None and want == got and int(want)
    vid = wait_until(settled, what="frames at the requested viewpoint")
    wait_frames(driver, 2)
    return vid


def status_rows(driver) -> dict[str, str]:
    return driver.execute_script(
        "return Object.fromEntries([...document.querySelectorAll('#status tr')]"
        ".map(r => [r.cells[0].textContent, r.cells[1].textContent]))")


def draw_rate(driver, seconds: float) -> float:
    n0, t0 = frames_drawn(driver), time.monotonic()
    time.sleep(seconds)
    return (frames_drawn(driver) - n0) / (time.monotonic() - t0)


# --- tests --------------------------------------------------------------------------------------------------------
def test_page_draws_frames_shows_status_and_screenshot(page, live_rig, tmp_path):
    rate = draw_rate(page, 2.0)
    # the page keeps up with what the engine can give one viewer: the cameras' rate, or the model's
    fps = live_rig.engine.status()["fps_in"] if live_rig.kind == "colour" else min(live_rig.engine.status()["fps_in"], model_rate(live_rig.inner))
    assert rate >= 0.5 * fps, (rate, fps)
    set_a = int(data(page, "lastSet"))
    wait_frames(page, 3)
    assert int(data(page, "lastSet")) > set_a
    if live_rig.expected_rgb:
        assert close_to(pixel(page), live_rig.expected_rgb(None))
    viewer = page_viewer(page, live_rig)
    wait_until(lambda: len(viewer.acks) >= 5, what="acks from the page")

    # the status panel shows live figures, updated
    rows = wait_until(lambda: (r := status_rows(page)).get("fps in") not in (None, "0", "–") and r, what="status figures")
    assert float(rows["fps in"]) > 0 and rows["health"] == "ok" and float(rows["drawn here (fps)"]) > 0
    assert rows["viewers"] == "1" and "this viewer fps out" in rows
    if live_rig.kind == "colour":
        assert rows["ms stage1"] == "12.5" and rows["cameras right ok"] == "yes"
    wait_until(lambda: status_rows(page).get("latency ms p50") not in (None, "–"), what="a latency figure")
    drawn = status_rows(page)["frames drawn here"]
    wait_until(lambda: status_rows(page)["frames drawn here"] != drawn, what="the status panel to update")

    severe = [e["message"] for e in page.get_log("browser") if e["level"] == "SEVERE"]
    assert severe == [], severe  # no script errors, no failed requests

    # a real screenshot: not blank, the view where the page put it
    png = page.get_screenshot_as_png()
    (tmp_path / "viewer.png").write_bytes(png)
    shot = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert shot is not None and shot.shape[0] > 500 and shot.shape[1] > 1000
    assert shot.std() > 10 and len(np.unique(shot.reshape(-1, 3), axis=0)) > 50
    box = page.find_element("id", "view").rect
    ratio = page.execute_script("return window.devicePixelRatio")
    cy, cx = int((box["y"] + 0.6 * box["height"]) * ratio), int((box["x"] + 0.5 * box["width"]) * ratio)
    b, g, r = (int(v) for v in shot[cy, cx])
    if live_rig.expected_rgb:
        assert close_to((r, g, b), live_rig.expected_rgb(None), tol=14), (r, g, b)
    else:
        assert shot[cy - 20:cy + 20, cx - 20:cx + 20].std() > 0 or (r, g, b) != (0, 0, 0)


def test_slider_moves_the_viewpoint_and_the_image(page, live_rig):
    from selenium.webdriver.common.action_chains import ActionChains

    viewer = page_viewer(page, live_rig)
    before = pixel(page)
    slider = page.find_element("id", "slider")
    width = slider.rect["width"]
    ActionChains(page).move_to_element_with_offset(slider, int(0.35 * width), 0).click().perform()  # 85 % along
    t = page.execute_script("return window.rigLive.state.t")
    assert 0.75 < t < 0.95, t
    vid = wait_view(page)
    wait_until(lambda: viewer.messages and viewer.messages[-1] == {"type": "viewpoint", "t": t}, what="the engine to get t")
    assert viewer.ids[-1] == vid
    after = pixel(page)
    assert after != before
    if live_rig.expected_rgb:
        assert close_to(after, live_rig.expected_rgb({"type": "viewpoint", "t": t})), (after, t)
    # dragging the thumb sends a throttled stream of positions, ending where it stops
    n = len(viewer.messages)
    ActionChains(page).click_and_hold(slider).move_by_offset(-int(0.2 * width), 0).pause(0.2) \
        .move_by_offset(-int(0.2 * width), 0).release().perform()
    t2 = page.execute_script("return window.rigLive.state.t")
    assert t2 < 0.5
    wait_until(lambda: viewer.messages[-1] == {"type": "viewpoint", "t": t2}, what="the final slider position")
    assert 2 <= len(viewer.messages) - n <= 20
    wait_view(page)
    if live_rig.expected_rgb:
        assert close_to(pixel(page), live_rig.expected_rgb({"type": "viewpoint", "t": t2}))


def test_preset_snaps_to_a_supervision_camera(page, live_rig):
    viewer = page_viewer(page, live_rig)
    buttons = wait_until(lambda: page.find_elements("css selector", "#presets button"), what="preset buttons")
    names = [(b.get_attribute("data-preset"), b.get_attribute("data-kind")) for b in buttons]
    assert sorted(names) == sorted((p["name"], p["kind"]) for p in live_rig.presets)
    assert names[0][1] == "source"  # sources first
    page.find_element("css selector", f'#presets button[data-preset="{live_rig.supervision}"]').click()
    wait_until(lambda: viewer.messages and viewer.messages[-1] == {"type": "viewpoint", "preset": live_rig.supervision},
               what="the preset to reach the engine")
    wait_view(page)
    assert "active" in page.find_element("css selector", f'#presets button[data-preset="{live_rig.supervision}"]').get_attribute("class")
    t = next(p.get("t") for p in live_rig.presets if p["name"] == live_rig.supervision)
    if t is not None:  # the slider shows where the camera stands between the sources
        assert page.find_element("id", "slider-value").text == f"{t:.3f}"
    if live_rig.expected_rgb:
        assert close_to(pixel(page), live_rig.expected_rgb({"type": "viewpoint", "preset": live_rig.supervision}))


def test_drag_orbits_and_wheel_zooms(page, live_rig):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.wheel_input import ScrollOrigin

    viewer = page_viewer(page, live_rig)
    view = page.find_element("id", "view-box")
    before = pixel(page)
    ActionChains(page).click_and_hold(view).move_by_offset(60, 0).move_by_offset(60, -40).release().perform()
    # 0.3 degree a pixel: 120 px right, 40 px up (the page's values, before the engine clamps them)
    msg = wait_until(lambda: viewer.messages and abs(viewer.messages[-1].get("yaw", 0) - 36) < 0.5
                     and abs(viewer.messages[-1].get("pitch", 0) - 12) < 0.5 and viewer.messages[-1],
                     what="the orbit to reach the engine")
    assert msg == {"type": "viewpoint", "t": 0.5, "yaw": msg["yaw"], "pitch": msg["pitch"], "zoom": 1}
    wait_view(page)
    if live_rig.expected_rgb:
        assert pixel(page) != before and close_to(pixel(page), live_rig.expected_rgb(viewer.messages[-1]))
    ActionChains(page).scroll_from_origin(ScrollOrigin.from_element(view), 0, -300).perform()
    zoom = wait_until(lambda: (z := page.execute_script("return window.rigLive.state.zoom")) > 1.2 and z, what="zoom")
    wait_until(lambda: viewer.messages[-1].get("zoom") == zoom, what="the zoom to reach the engine")
    # beyond the engine's limit (pitch 60 for the colour engine): the controls come back to what it renders
    ActionChains(page).click_and_hold(view).move_by_offset(0, -250).release().perform()
    wait_until(lambda: viewer.messages[-1].get("pitch", 0) > 60, what="the steep pitch to reach the engine")
    if live_rig.kind == "colour":
        wait_until(lambda: page.execute_script("return window.rigLive.state.pitch") == 60, what="the clamped pitch")
        assert page.find_element("id", "pitch").text == "60.0"
    page.find_element("id", "reset-view").click()
    wait_until(lambda: viewer.messages[-1] == {"type": "viewpoint", "t": 0.5}, what="the reset view")


def test_health_banner_appears_and_clears(page, live_rig):
    banner = page.find_element("id", "banner")
    assert not banner.is_displayed()
    said = live_rig.fault("camera right disconnected") or "camera right disconnected"
    t0 = time.monotonic()
    wait_until(lambda: banner.is_displayed(), what="the health banner")
    assert time.monotonic() - t0 < 2.0  # the page says so within 2 s
    assert said in banner.text and data(page, "health") == "fault"
    colour = page.execute_script("return getComputedStyle(arguments[0]).backgroundColor", banner)
    r, g, b = (int(v) for v in colour[colour.index("(") + 1:colour.index(")")].split(",")[:3])
    assert r > 150 and g < 100 and b < 100, colour  # red
    assert status_rows(page)["health"] == "FAULT"
    if live_rig.kind == "colour":
        wait_frames(page, 3)  # frames keep coming
    else:
        assert status_rows(page)["fps in"]  # the server keeps running and serving the page
    live_rig.clear()
    wait_until(lambda: not banner.is_displayed(), what="the banner to clear")
    assert data(page, "health") == "ok" and data(page, "banner") == ""


def test_second_browser_gets_its_own_view_and_the_first_keeps_its_rate(page, live_rig, server):
    other = new_driver()
    try:
        other.get(server.url + "?t=0.1")
        wait_frames(other, 5)
        wait_view(other)
        # Measured against what the engine did in the same window, not against the wall clock: on a
        # loaded machine the model slows for everyone, but each set it renders after one shared stage 1
        # still reaches both viewers (a colour engine has no stage 1: its sets are the ones it took in).
        engine = live_rig.engine
        counter = "sets_in" if live_rig.kind == "colour" else "stage1_runs"
        s0, first0, second0 = engine.status(), frames_drawn(page), frames_drawn(other)
        wait_until(lambda: engine.status()[counter] >= s0[counter] + 8, 60.0, what="8 sets rendered while shared")
        s1, first, second = engine.status(), frames_drawn(page) - first0, frames_drawn(other) - second0
        sets = s1[counter] - s0[counter]
        assert first >= 0.6 * sets and second >= 0.6 * sets, (sets, first, second)
        if live_rig.kind != "colour":
            views = s1["view_runs"] - s0["view_runs"]
            assert views >= 1.5 * sets, (sets, views)  # one stage 1 serves both viewers' views
        first, second = page_viewer(page, live_rig), page_viewer(other, live_rig)
        assert first.id != second.id
        assert second.messages[-1] == {"type": "viewpoint", "t": 0.1}
        if live_rig.expected_rgb:
            assert close_to(pixel(other), live_rig.expected_rgb({"type": "viewpoint", "t": 0.1}))
            assert close_to(pixel(page), live_rig.expected_rgb(None))
        else:
            assert pixel(other) != pixel(page)
        assert status_rows(page)["viewers"] == "2" or wait_until(lambda: status_rows(page)["viewers"] == "2")
    finally:
        other.quit()
    wait_until(lambda: second.id in live_rig.engine.removed, what="the closed tab's viewer to be removed")


def test_token_page(driver, live_rig):
    with start_server(live_rig.engine, token=TOKEN) as srv:
        driver.delete_all_cookies()
        driver.get(srv.url)
        assert "a valid token is needed" in driver.page_source
        driver.get(srv.url + f"?token={TOKEN}&t=0.3")
        wait_frames(driver, 3)
        assert TOKEN not in driver.current_url and driver.current_url.endswith("/?t=0.3")  # out of the address bar
        assert driver.get_cookie("rig_live_token")["httpOnly"] is True
        if live_rig.expected_rgb:
            wait_view(driver)
            assert close_to(pixel(driver), live_rig.expected_rgb({"type": "viewpoint", "t": 0.3}))
        driver.get(srv.url)  # the cookie alone lets the page in again
        wait_frames(driver, 3)
        driver.delete_all_cookies()
