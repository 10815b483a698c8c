"""The console attached to the daemons of `rig up`: its previews and its takes read the cameras from
the daemons' rings (the session every command runs), and a camera whose backend takes its settings
only when it opens says so in one line."""
from __future__ import annotations

import json
import time
import urllib.request

import pytest

from rig.storage.validate import validate
from tests.console.test_console_browser import wait_until
from tests.daemon.test_daemon import Up, rig_file, wait_running

pytestmark = pytest.mark.timeout(300)


def call(url: str, method: str = "GET", body: dict | None = None):
    request = urllib.request.Request(url, method=method, data=None if body is None else json.dumps(body).encode(),
                                     headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as r:
        return json.load(r)


def test_the_console_on_rig_up_daemons_previews_and_records_a_take_that_validates(tmp_path, monkeypatch):
    from rig.cameras.daemon import DaemonCamera
    from rig.config import load_config
    from rig.console.rigstate import ConsoleRig
    from rig.console.server import ConsoleServer

    config = rig_file(tmp_path, n=2)
    up = Up(config, tmp_path / "shm")
    try:
        wait_running(up.root, "sim-2cam", 2)
        monkeypatch.setenv("RIG_SHM_ROOT", str(up.root))  # where this host's daemons keep their rings
        rig = ConsoleRig(load_config(config)).start()
        server = ConsoleServer(rig, "127.0.0.1", 0).start()
        try:
            wait_until(lambda: all(v.seq > 10 for v in rig.views.values()), 60, "frames from the daemons")
            session = rig.session
            assert session is not None and all(isinstance(c, DaemonCamera) for c in session.cameras.values()), \
                {n: type(c).__name__ for n, c in session.cameras.items()}
            wait_until(lambda: all(c["fps"] for c in call(server.url + "api/status")["cameras"]), 20, "fps on every tile")
            status = call(server.url + "api/status")
            for cam in status["cameras"]:
                assert abs(cam["fps"] / 30.0 - 1) < 0.05, cam
                assert cam["health"] == "ok", cam
            # a daemon's camera takes its settings when it opens: the tile says so in one line
            answer = call(server.url + "api/controls", "POST", {"camera": "left", "exposure_us": 2000})["left"]
            assert answer["ok"] is False and "\n" not in answer["error"], answer
            left = next(c for c in call(server.url + "api/status")["cameras"] if c["name"] == "left")
            assert left["control_error"] == answer["error"] and not left["live_controls"]
            # a take from the console, through rig record's own recorder reading the rings
            call(server.url + "api/record/start", "POST", {"take": "on-daemons", "seconds": 2})
            wait_until(lambda: call(server.url + "api/status")["recording"]["state"] == "done", 60, "the take to end")
            v = validate(rig.storage / "on-daemons")
            assert v.readable and v.errors == [], v.errors
            assert v.sets >= 50
            wait_until(lambda: rig.activity == "previewing", 30, "the previews back")
            seq = rig.views["left"].seq
            time.sleep(1.0)
            assert rig.views["left"].seq > seq + 10
        finally:
            server.stop()
            rig.close()
    finally:
        print(up.stop())
