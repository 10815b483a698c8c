"""Rig configuration: `rig config init --sim` writes a rig that checks; every mistake is one line naming the key."""
from __future__ import annotations

import pytest

from rig.config import dump_config, load_config, parse_config
from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig

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


# ---- the calibration file a config names (issue 11, point 5) -----------------------------------------

def _sim_rig_with_calibration(tmp_path, calibration_text=None, cameras=(("left", 640, 360), ("right", 640, 360))):
    """A `config init --sim` rig whose [rig] names calib.json; calib.json holds `cameras` (name, w, h)
    from the simulator's arc rig, or `calibration_text` verbatim."""
    from simulator.rig import arc_rig

    path = tmp_path / "rig.toml"
    assert run_rig("config", "init", "--sim", path).returncode == 0
    path.write_text(path.read_text().replace('storage = "recordings"', 'storage = "recordings"\ncalibration = "calib.json"'))
    calib = tmp_path / "calib.json"
    if calibration_text is not None:
        calib.write_text(calibration_text)
    elif cameras:
        arc_rig(list(cameras)).save(calib)
    return path


def test_a_matching_calibration_passes(tmp_path):
    path = _sim_rig_with_calibration(tmp_path)
    proc = run_rig("config", "check", path)
    assert proc.returncode == 0, proc.stderr
    assert load_config(path).calibration == "calib.json"


CALIBRATION_FAULTS = [
    ("missing file", None, (), ["rig.calibration", "calib.json", "does not exist"]),
    ("garbage", "\x00\x01 this is not json", None, ["rig.calibration", "calib.json", "not valid JSON"]),
    ("wrong schema", '{"version": 1, "cameras": []}', None, ["rig.calibration", "cameras"]),
    ("camera missing", None, (("left", 640, 360), ("sup1", 640, 360)), ["'right'", "calib.json", "it has: left, sup1"]),
    ("other size", None, (("left", 640, 360), ("right", 1280, 720)), ["'right'", "640x360 in the config", "1280x720 in", "calib.json"]),
]


@pytest.mark.parametrize("label,text,cameras,fragments", CALIBRATION_FAULTS, ids=[c[0] for c in CALIBRATION_FAULTS])
def test_check_rejects_a_calibration_that_does_not_fit(tmp_path, label, text, cameras, fragments):
    path = _sim_rig_with_calibration(tmp_path, text, cameras)
    line = assert_one_line_error(run_rig("config", "check", path), *fragments)
    assert str(path) in line


def test_every_command_that_loads_the_config_checks_the_calibration(tmp_path):
    """`rig record` wrote a take that validated as NOT readable from a garbage calibration: now it,
    and every other command that loads a config, refuses before opening a camera."""
    path = _sim_rig_with_calibration(tmp_path, "garbage")
    commands = [
        ("record", "-c", path, "-o", tmp_path / "take", "--sets", "3"),
        ("grab", "-c", path, "-n", "1", "-o", tmp_path / "grab"),
        ("sync", "check", "-c", path, "--seconds", "1"),
        ("sim", "snapshot", "-c", path, "-t", "0", "-o", tmp_path / "snap"),
    ]
    for cmd in commands:
        assert_one_line_error(run_rig(*cmd), "rig.calibration", "not valid JSON")
    assert not (tmp_path / "take").exists() and not (tmp_path / "grab").exists() and not (tmp_path / "snap").exists()


def test_check_lists_every_problem_one_line_each(tmp_path):
    """`rig config check` reported only the first problem; now every one, and other commands say how many more."""
    path = tmp_path / "rig.toml"
    path.write_text(GOOD.replace('gain = 0.0', 'gian = 0.0').replace("width = 640", 'width = "640"')
                    .replace('role = "right"', 'role = "middle"').replace("rate_hz = 30", "rate_hz = -1"))
    proc = run_rig("config", "check", path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 4, proc.stderr
    assert all(line.startswith(f"rig: error: {path}: ") for line in lines), lines
    for fragment in ("'gian'", "width: must be an integer", "'middle'", "rate_hz: must be between"):
        assert sum(fragment in line for line in lines) == 1, (fragment, lines)
    as_json = run_rig("config", "check", "--json", path)
    assert as_json.returncode == 2
    assert __import__("json").loads(as_json.stdout) == {"ok": False, "problems": [line.split("rig: error: ", 1)[1] for line in lines]}
    other = assert_one_line_error(run_rig("grab", "-c", path, "-n", "1", "-o", tmp_path / "g"), "gian")
    assert "3 more problems" in other and "rig config check" in other


FREE_RUNNING = GOOD + """
[[cameras]]
name = "gp"
uri = "gopro://C3501324645504@127.0.0.1:8080?port=9000"
width = 1280
height = 720
pixel_format = "RGB8"
trigger = "free"
[[cameras]]
name = "cam"
uri = "uvc:///dev/video0?fourcc=YUYV"
pixel_format = "RGB8"
[[cameras]]
name = "net"
uri = "stream://rtsp://192.0.2.7/stream1"
pixel_format = "RGB8"
"""

BACKEND_BAD = [
    ("gopro triggered", FREE_RUNNING.replace('trigger = "free"', 'trigger = "hardware"'), ["'gp'", "GoPro cannot be triggered", "free"]),
    ("gopro size", FREE_RUNNING.replace("width = 1280", "width = 1024"), ["'gp'", "1920x1080", "1024x720"]),
    ("gopro pixels", FREE_RUNNING.replace('"RGB8"\ntrigger = "free"', '"BayerRG8"\ntrigger = "free"'), ["'gp'", "RGB8 or Mono8", "BayerRG8"]),
    ("gopro serial", FREE_RUNNING.replace("C3501324645504@", "xyz@"), ["'gp'", "xyz"]),
    ("uvc path", FREE_RUNNING.replace("uvc:///dev/video0", "uvc://video0"), ["'cam'", "uvc:///dev/videoN"]),
    ("uvc fourcc", FREE_RUNNING.replace("fourcc=YUYV", "fourcc=H264"), ["'cam'", "fourcc", "MJPG"]),
    ("stream scheme", FREE_RUNNING.replace("stream://rtsp://", "stream://ftp://"), ["'net'", "stream://URL", "rtsp://"]),
    ("stream software trigger", FREE_RUNNING + 'trigger = "software"\n',
     ["'net'", "network stream cannot be triggered"]),
]


def test_the_free_running_backends_check_as_a_good_config(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(FREE_RUNNING)
    proc = run_rig("config", "check", path)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize("label,text,fragments", BACKEND_BAD, ids=[b[0] for b in BACKEND_BAD])
def test_check_asks_each_backend_about_its_cameras(tmp_path, label, text, fragments):
    """GoPro, webcam and stream settings their backend cannot take are found by `rig config check`
    (before: only when the camera was opened, mid-command)."""
    assert text != FREE_RUNNING
    path = tmp_path / "rig.toml"
    path.write_text(text)
    line = assert_one_line_error(run_rig("config", "check", path), *fragments)
    assert str(path) in line


def test_init_to_an_unwritable_or_bad_path_is_one_line(tmp_path):
    assert_one_line_error(run_rig("config", "init", "--sim", "/proc/no/rig.toml"), "/proc")
    assert_one_line_error(run_rig("config", "init", "--sim", tmp_path), "folder")
    assert_one_line_error(run_rig("config", "init", "--sim", "--width", "0", tmp_path / "r.toml"), "width", "command line")
    assert not (tmp_path / "r.toml").exists()


# ---- docs/configuration.md (issue 11, point 11) -----------------------------------------------------

def test_every_configuration_doc_example_checks_and_the_sim_one_runs(tmp_path):
    """Each ```toml block of docs/configuration.md is a complete config that passes `rig config check`
    (the calibration example with the calibration made for its cameras); the simulated ones grab."""
    import re
    import tomllib

    from simulator.rig import arc_rig

    doc = (REPO / "docs" / "configuration.md").read_text()
    blocks = re.findall(r"```toml\n(.*?)```", doc, re.S)
    assert len(blocks) >= 3
    keys = set()
    for i, text in enumerate(blocks):
        folder = tmp_path / f"example{i}"
        folder.mkdir()
        path = folder / "rig.toml"
        path.write_text(text)
        data = tomllib.loads(text)
        keys |= set(data) | set(data.get("rig", {}))
        if "calibration" in data.get("rig", {}):
            arc_rig([(c["name"], c["width"], c["height"]) for c in data["cameras"]]).save(folder / data["rig"]["calibration"])
        check = run_rig("config", "check", path)
        assert check.returncode == 0, (i, check.stderr)
        if all(c["uri"].startswith("sim://") for c in data["cameras"]):
            grab = run_rig("grab", "-c", path, "-n", "2", "-o", folder / "grab")
            assert grab.returncode == 0, (i, grab.stderr)
    assert {"sim", "live", "calibration"} <= keys  # an example of each


def test_configuration_doc_lists_every_simulator_option():
    from simulator.options import OPTIONS

    doc = (REPO / "docs" / "configuration.md").read_text()
    for kind, spec in OPTIONS.items():
        for key in spec:
            assert f"| `{key}` |" in doc, (kind, key)


def test_an_exposure_or_pulse_longer_than_the_frame_period_is_refused(tmp_path):
    """A trial found `exposure_us = 200000` at 30 Hz accepted: the take then lost most frames, and
    1e12 never ended."""
    hardware = GOOD.replace('name = "right"\nuri = "sim://right"', 'name = "right"\nuri = "sim://right"\ntrigger = "hardware"\nexposure_us = 40000')
    problems = {
        "left": (GOOD.replace("exposure_us = 5000", "exposure_us = 40000"), "cameras[0] ('left').exposure_us: 40000 us is not shorter than its frame time (33333.3 us at 30 fps)"),
        "right": (hardware, "cameras[1] ('right').exposure_us: 40000 us is not shorter than the trigger's period (33333.3 us at 30 Hz)"),
        "pulse": (GOOD.replace("rate_hz = 30", "rate_hz = 30\npulse_width_us = 1e9"), "trigger.pulse_width_us: 1e+09 us is not shorter than the pulse period"),
    }
    for name, (text, fragment) in problems.items():
        path = tmp_path / f"{name}.toml"
        path.write_text(text)
        assert_one_line_error(run_rig("config", "check", path), fragment)
    path = tmp_path / "fine.toml"
    path.write_text(GOOD.replace("exposure_us = 5000", "exposure_us = 33000"))
    assert run_rig("config", "check", path).returncode == 0
