"""The console's calibration panel in headless Chromium on a simulated three-camera rig whose
calibration does not exist yet: stills with the board drawn on every tile, views kept by hand and
when the board is still, coverage per camera and per pair until it passes, then `rig calibrate
run`'s solve writes the calibration the config names and its report is shown.
"""
from __future__ import annotations

import json
import urllib.error
import urllib.request

import pytest

from tests.console.test_console_browser import data, driver, wait_until  # noqa: F401 (driver: a fixture)
from tests.live.test_browser import CHROMEDRIVER, CHROMIUM

pytestmark = [
    pytest.mark.skipif(not CHROMIUM.exists() or not CHROMEDRIVER.exists(),
                       reason="headless Chromium not installed (/usr/bin/chromium and /usr/bin/chromedriver: "
                              "apt-get install chromium chromium-driver, or make system-deps)"),
    pytest.mark.timeout(400),
]


@pytest.fixture(scope="module")
def rig_config(tmp_path_factory):
    from rig.config import dump_config, load_config, parse_config
    from rig.sim.rig_config import SIM_RIG_BOARD, board_toml, sim_rig_config

    root = tmp_path_factory.mktemp("console-calibration")
    data = sim_rig_config(3, width=640, height=360, fps=10.0)
    data["rig"]["storage"] = str(root / "takes")
    data["rig"]["calibration"] = "calib.json"  # not made yet: the console makes it
    data["sim"]["loop_frames"] = 10
    path = root / "rig.toml"
    path.write_text(dump_config(parse_config(data, path)))
    (root / "board.toml").write_text(board_toml(SIM_RIG_BOARD))
    return load_config(path, check_calibration=False)


@pytest.fixture(scope="module")
def console(rig_config):
    from rig.console.rigstate import ConsoleRig
    from rig.console.server import ConsoleServer

    rig = ConsoleRig(rig_config, board_file=rig_config.path.parent / "board.toml").start()
    server = ConsoleServer(rig, "127.0.0.1", 0).start()
    try:
        wait_until(lambda: all(v.seq > 3 for v in rig.views.values()), 120, "frames from every camera")
        yield rig, server
    finally:
        server.stop()
        rig.close()


def post(server, path: str, body: dict | None = None):
    request = urllib.request.Request(server.url + path, method="POST", data=json.dumps(body or {}).encode(),
                                     headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as r:
        return json.load(r)


def click(driver, action: str) -> None:
    button = driver.find_element("css selector", f'[data-action="{action}"]')
    wait_until(lambda: button.is_enabled(), 20, f"the {action} button")
    button.click()


def test_views_are_captured_until_coverage_passes_and_solve_writes_the_calibration_and_shows_its_report(console, driver):
    from calibration.camera import RigCalibration

    rig, server = console
    target = rig.cfg.resolve(rig.cfg.calibration)
    assert not target.exists()
    driver.get(server.url)
    wait_until(lambda: data(driver, "body", "role") == "operator", 20, "the first status")
    # the missing calibration is a banner until the console makes one
    wait_until(lambda: "calibration" in (data(driver, "body", "faults") or ""), 10, "the missing calibration's banner")
    # bad input: one error, nothing starts
    with pytest.raises(urllib.error.HTTPError) as err:
        post(server, "api/calibration/start", {"auto": "yes"})
    assert err.value.code == 400 and "auto" in json.load(err.value)["error"]
    assert rig.calibration.state == "off"

    # by hand first: automatic keeping off
    driver.find_element("css selector", "#cal-auto").click()
    assert not driver.find_element("css selector", "#cal-auto").is_selected()
    click(driver, "calibrate")
    wait_until(lambda: data(driver, "body", "calibration") == "capturing", 60, "the calibration to start")
    assert not rig.calibration.auto
    # the board found in each still is drawn on the tiles
    wait_until(lambda: driver.execute_script("return document.querySelectorAll('.tile[data-board]:not([data-board=\"\"])').length") >= 2,
               60, "the board drawn on the tiles")
    wait_until(lambda: rig.calibration.capture_obj.looked >= 4, 60, "a few sets looked at")
    assert rig.calibration.capture_obj.kept == []  # nothing is kept by itself with automatic keeping off
    click(driver, "capture-view")
    wait_until(lambda: data(driver, "body", "calibrationViews") == "1", 60, "a view kept by hand")
    # the decision stays shown after later sets ("waiting for the board to be still") replace the last set's line
    assert "kept (by hand)" in rig.calibration.decision
    wait_until(lambda: "last view: view 0000 kept (by hand)" in driver.find_element("css selector", "#cal-last").text
               or "last set: view 0000 kept (by hand)" in driver.find_element("css selector", "#cal-last").text, 10, "the kept view shown")
    # other work is refused while the calibration holds the cameras
    with pytest.raises(urllib.error.HTTPError) as err:
        post(server, "api/record/start", {})
    assert err.value.code == 400 and "calibration" in json.load(err.value)["error"]

    # then by itself: views kept while the board is still, until coverage passes
    driver.find_element("css selector", "#cal-auto").click()
    wait_until(lambda: rig.calibration.auto, 10, "automatic keeping on")
    wait_until(lambda: data(driver, "body", "calibrationReady") == "true", 240, "coverage to pass")
    status = rig.calibration.status()
    assert status["needs"] == [] and all(v >= 10 for v in status["views_per_camera"].values())
    assert {frozenset((p["a"], p["b"])) for p in status["pairs"]} == {frozenset(p) for p in (("left", "right"), ("left", "sup1"), ("right", "sup1"))}
    assert driver.execute_script("return document.querySelectorAll('#cal-coverage [data-coverage]').length") == 3
    assert sum(1 for k in rig.calibration.capture_obj.kept if k["reason"] != "kept by hand") >= 10

    click(driver, "solve")
    wait_until(lambda: data(driver, "body", "calibrationWritten"), 240, "the calibration written")
    assert data(driver, "body", "calibrationWritten") == str(target)
    calib = RigCalibration.load(target)
    assert set(calib.names) == {"left", "right", "sup1"}
    report = driver.find_element("css selector", "#cal-report").text
    assert "verdict:" in report and "stereo pair" in report
    assert rig.calibration.result["verdicts"] == {"left": "good", "right": "good", "sup1": "good"}
    # the cameras go back to the previews, and the banner is gone
    wait_until(lambda: data(driver, "body", "activity") == "previewing", 60, "the previews back")
    wait_until(lambda: "calibration" not in (data(driver, "body", "faults") or ""), 20, "the banner gone")

    # solving again keeps the calibration it replaces
    before = target.read_bytes()
    post(server, "api/calibration/solve")
    wait_until(lambda: rig.calibration.state in ("done", "failed"), 240, "the second solve")
    assert rig.calibration.state == "done", rig.calibration.error
    previous = rig.calibration.result["previous"]
    assert previous and open(previous, "rb").read() == before
