"""The picture of docs/console.md: the console on a simulated four-camera rig, in headless Chromium.

    .venv/bin/python benchmarks/console_screenshot.py -o docs/console.png
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
    args = ap.parse_args()
    from rig.config import dump_config, load_config, parse_config
    from rig.console.rigstate import ConsoleRig
    from rig.console.server import ConsoleServer
    from rig.sim.rig_config import sim_rig_config
    from tests.live.test_browser import new_driver

    root = Path(tempfile.mkdtemp(prefix="console-shot-"))
    data = sim_rig_config(4, width=640, height=360, fps=10.0)
    data["rig"]["storage"] = str(root / "takes")
    path = root / "rig.toml"
    path.write_text(dump_config(parse_config(data, path)))
    rig = ConsoleRig(load_config(path)).start()
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
    finally:
        driver.quit()
        server.stop()
        rig.close()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
