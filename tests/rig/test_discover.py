"""`rig discover`: every backend's devices; `--json` prints one object, as every other --json does."""
from __future__ import annotations

import json

from tests.rig.cli_helpers import run_rig


def _discover_json() -> dict:
    proc = run_rig("discover", "--json")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("\n") == 1, proc.stdout  # one JSON object on one line
    out = json.loads(proc.stdout)
    assert isinstance(out, dict) and set(out) == {"devices", "errors"}, out
    assert isinstance(out["errors"], dict)  # backend -> why it could not look (empty when every backend looked)
    return out


def test_discover_json_is_one_object_listing_sim_devices():
    out = _discover_json()
    sims = [d for d in out["devices"] if d["backend"] == "sim"]
    assert {d["uri"] for d in sims} >= {"sim://left", "sim://right"}
    for d in out["devices"]:
        assert {"uri", "backend", "model", "serial"} <= set(d)
    assert "sim" not in out["errors"]


def test_discover_text_lists_the_same_devices():
    # Other tests running beside this one start and stop devices (a GoPro emulator on mDNS): the
    # text must list every device found both before and after it.
    before = {d["uri"] for d in _discover_json()["devices"]}
    proc = run_rig("discover")
    assert proc.returncode == 0, proc.stderr
    uris = {line.split()[0] for line in proc.stdout.splitlines()}
    assert uris >= before & {d["uri"] for d in _discover_json()["devices"]}


def test_discover_finds_the_fake_gige_camera(fake_camera):
    out = _discover_json()
    aravis = [d for d in out["devices"] if d["backend"] == "aravis"]
    assert any(d["uri"] == "aravis://127.0.0.1" and d["serial"] == "GV01" for d in aravis), out
