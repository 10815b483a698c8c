"""Rig configuration: `rig config init --sim` writes a rig that checks; every mistake is one line naming the key."""
from __future__ import annotations

import pytest

from rig.config import dump_config, load_config, parse_config
from tests.rig.cli_helpers import assert_one_line_error, run_rig

GOOD = """
[rig]
name = "venue-a"
[[cameras]]
name = "left"
uri = "aravis://127.0.0.1"
role = "left"
width = 640
height = 480
pixel_format = "Mono8"
fps = 30
trigger = "software"
exposure_us = 5000
gain = 0.0
[[cameras]]
name = "right"
uri = "sim://right"
role = "right"
[trigger]
uri = "sim://trigger"
rate_hz = 30
"""


def test_init_sim_writes_a_rig_that_checks(tmp_path):
    path = tmp_path / "rig.toml"
    proc = run_rig("config", "init", "--sim", path)
    assert proc.returncode == 0, proc.stderr
    check = run_rig("config", "check", path)
    assert check.returncode == 0, check.stderr
    cfg = load_config(path)
    assert [c.role for c in cfg.cameras] == ["left", "right"]
    assert all(c.uri.startswith("sim://") for c in cfg.cameras)


def test_init_six_cameras_and_refuses_to_overwrite(tmp_path):
    path = tmp_path / "rig.toml"
    assert run_rig("config", "init", "--sim", "--cameras", "6", path).returncode == 0
    cfg = load_config(path)
    assert [c.name for c in cfg.cameras] == ["left", "sup1", "sup2", "sup3", "sup4", "right"]
    assert [c.role for c in cfg.cameras].count("supervision") == 4
    assert_one_line_error(run_rig("config", "init", "--sim", path), "already exists")


def test_good_config_parses_and_round_trips(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(GOOD)
    cfg = load_config(path)
    assert cfg.name == "venue-a"
    assert cfg.camera("left").exposure_us == 5000.0 and cfg.camera("left").trigger == "software"
    assert cfg.trigger.uri == "sim://trigger" and cfg.trigger.rate_hz == 30.0
    again = parse_config(__import__("tomllib").loads(dump_config(cfg)))
    assert again.cameras == cfg.cameras and again.trigger == cfg.trigger


BAD = [
    ("unknown key", GOOD.replace('gain = 0.0', 'gian = 0.0'), ["gian", "allowed"]),
    ("wrong type", GOOD.replace("width = 640", 'width = "640"'), ["width", "integer"]),
    ("missing uri", GOOD.replace('uri = "sim://right"\n', ""), ["uri", "missing"]),
    ("duplicate names", GOOD.replace('name = "right"', 'name = "left"'), ["name", "duplicate"]),
    ("two left roles", GOOD.replace('role = "right"', 'role = "left"'), ["role", "left"]),
    ("bad pixel format", GOOD.replace('"Mono8"', '"YUV422"'), ["pixel_format", "Mono8", "BayerRG8"]),
    ("unknown scheme", GOOD.replace("aravis://127.0.0.1", "firewire://1"), ["uri", "firewire", "aravis", "sim"]),
    ("bad trigger mode", GOOD.replace('trigger = "software"', 'trigger = "auto"'), ["trigger", "hardware", "software", "free"]),
    ("bad role", GOOD.replace('role = "right"', 'role = "middle"'), ["role", "supervision"]),
    ("not toml", "[rig\nname=", ["not valid TOML"]),
    ("unknown sim option", GOOD.replace('role = "right"', 'role = "right"\nsim = { drop = 0.1 }'), ["sim", "drop", "drop_rate"]),
]


@pytest.mark.parametrize("label,text,fragments", BAD, ids=[b[0] for b in BAD])
def test_check_reports_each_mistake_in_one_line(tmp_path, label, text, fragments):
    path = tmp_path / "rig.toml"
    path.write_text(text)
    line = assert_one_line_error(run_rig("config", "check", path), *fragments)
    assert str(path) in line


def test_check_missing_file(tmp_path):
    assert_one_line_error(run_rig("config", "check", tmp_path / "nope.toml"), "no such config file")
