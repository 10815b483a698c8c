"""The pictures of docs/console.md: the console on a simulated four-camera rig, in headless Chromium.

    .venv/bin/python benchmarks/console_screenshot.py -o docs/console.png [--calibration-out docs/console-calibration.png]

The second picture is taken while the calibration panel captures views: the board drawn on each
tile, coverage maps and the views each pair of cameras shares.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--out", type=Path, required=True)
    ap.add_argument("--calibration-out", type=Path, help="also a picture while calibration views are captured")
    args = ap.parse_args()
    from rig.config import dump_config, load_config, parse_config
    from rig.console.rigstate import ConsoleRig
    from rig.console.server import ConsoleServer
    from rig.sim.rig_config import SIM_RIG_BOARD, board_toml, sim_rig_config
    from tests.live.test_browser import new_driver

    root = Path(tempfile.mkdtemp(prefix="console-shot-"))
    data = sim_rig_config(4, width=640, height=360, fps=10.0)
    data["rig"]["storage"] = str(root / "takes")
    data["rig"]["calibration"] = "calib.json"
    path = root / "rig.toml"
    path.write_text(dump_config(parse_config(data, path)))
    (root / "board.toml").write_text(board_toml(SIM_RIG_BOARD))
    rig = ConsoleRig(load_config(path, check_calibration=False), board_file=root / "board.toml").start()
    server = ConsoleServer(rig, "127.0.0.1", 0).start()
    driver = new_driver()
    try:
        driver.set_window_size(1400, 1000)
        driver.get(server.url)
        deadline = time.monotonic() + 180
        while not all(int(e.get_attribute("data-previews") or 0) > 2 for e in driver.find_elements("css selector", "[data-camera]")) \
                or not driver.find_elements("css selector", "[data-camera]"):
            if time.monotonic() > deadline:
                raise SystemExit("error: no previews")
            time.sleep(0.5)
        time.sleep(2.0)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(args.out))
        print(f"wrote {args.out}")
        if args.calibration_out is not None:
            button = driver.find_element("css selector", '[data-action="calibrate"]')
            deadline = time.monotonic() + 60
            while not button.is_enabled():  # enabled while the rig previews
                if time.monotonic() > deadline:
                    raise SystemExit("error: the calibration cannot start: " + str(rig.activity))
                time.sleep(0.1)
            button.click()
            deadline = time.monotonic() + 120
            while int(driver.execute_script("return document.body.dataset.calibrationViews || 0")) < 12 \
                    or not driver.find_elements("css selector", '.tile[data-board="still"]'):
                if time.monotonic() > deadline:
                    raise SystemExit("error: no calibration views: " + str(rig.calibration.status().get("state")) + " " + str(rig.calibration.error) + " " + str(rig.calibration.last))
                time.sleep(0.2)
            driver.set_window_size(1400, 1500)  # the tiles with the board drawn, and the calibration panel
            time.sleep(1.0)
            args.calibration_out.parent.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(str(args.calibration_out))
            print(f"wrote {args.calibration_out}")
    finally:
        driver.quit()
        server.stop()
        rig.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
