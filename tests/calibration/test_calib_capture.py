"""`rig calibrate capture` on a simulated rig, and the rule that decides which views to keep."""
from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.detect import Corners, detect
from calibration.selection import ViewSelector
from rig.cli import main
from tests.calibration.cli_helpers import run_json

pytestmark = pytest.mark.slow

# The simulated cameras render each 1280x720 frame on the CPU: on a loaded two-core machine one
# frame can take longer than the 5 s a real camera is given.
SLOW_RENDER = ["--timeout", "60"]

SIM_CONFIG = """
[rig]
name = "calibration-capture"

[sim]
board = "charuco"
people = 0

[trigger]
uri = "sim://trigger"

[[cameras]]
name = "left"
uri = "sim://left"
role = "left"
width = 1280
height = 720
trigger = "hardware"

[[cameras]]
name = "right"
uri = "sim://right"
role = "right"
width = 1280
height = 720
trigger = "hardware"
"""


def _grid_corners(x0, y0, step=60.0, n=5):
    j, i = np.mgrid[0:n, 0:n]
    return Corners(np.arange(n * n), np.stack([x0 + i.ravel() * step, y0 + j.ravel() * step], axis=1))


def test_selector_keeps_views_that_add_coverage_or_a_new_pose():
    sel = ViewSelector({"left": (1280, 720), "right": (1280, 720)})
    first = {"left": _grid_corners(100, 100), "right": _grid_corners(600, 300)}
    assert sel.consider(first).keep
    # The same board again adds nothing.
    again = sel.consider({"left": _grid_corners(101, 100), "right": _grid_corners(601, 300)})
    assert not again.keep and again.reason == "nothing new"
    # Moved to an unseen part of both images: new coverage.
    moved = sel.consider({"left": _grid_corners(950, 420), "right": _grid_corners(100, 100)})
    assert moved.keep and "new coverage" in moved.reason
    # Not seen at all.
    assert not sel.consider({"left": None, "right": None}).keep
    assert 0 < sel.coverage()["left"] < 1


def test_capture_from_a_simulated_rig_writes_views_for_run(tmp_path):
    from simulator.scene import default_board

    config = tmp_path / "rig.toml"
    config.write_text(SIM_CONFIG)
    board = default_board("charuco")  # the board the simulated scene carries
    board_file = tmp_path / "board.toml"
    board_file.write_text("".join(f"{k} = {json.dumps(v)}\n" for k, v in board.to_dict().items()))
    out = tmp_path / "views"
    summary = run_json("calibrate", "capture", "-c", config, "--board", board_file, "-o", out, "--views", "8", "--max-frames", "12", *SLOW_RENDER)
    print(f"\ncapture: kept {summary['views_kept']} of {summary['views_looked_at']} views; coverage {summary['coverage']}")
    assert 4 <= summary["views_kept"] <= 8
    assert all(n >= 4 for n in summary["views_per_camera"].values())  # what `rig calibrate run` needs
    assert json.loads((out / "roles.json").read_text()) == {"left": "left", "right": "right"}
    for view in summary["kept"]:
        # Every camera's image of a kept view is written; the board is in the cameras that saw it.
        for cam in ("left", "right"):
            assert (out / cam / f"{view['view']}.png").exists()
        import cv2

        for cam in view["cameras"]:
            img = cv2.imread(str(out / cam / f"{view['view']}.png"), cv2.IMREAD_GRAYSCALE)
            assert img.shape == (720, 1280) and detect(board, img) is not None


def test_capture_refuses_a_folder_with_views_in_it(tmp_path, capsys):
    config = tmp_path / "rig.toml"
    config.write_text(SIM_CONFIG)
    board_file = tmp_path / "board.toml"
    board_file.write_text('type = "charuco"\nsquares_x = 8\nsquares_y = 6\nsquare_size = 0.1\nmarker_size = 0.075\ndictionary = "DICT_4X4_50"\n')
    (tmp_path / "views" / "left").mkdir(parents=True)
    (tmp_path / "views" / "left" / "0000.png").write_bytes(b"x")
    rc = main(["calibrate", "capture", "-c", str(config), "--board", str(board_file), "-o", str(tmp_path / "views")])
    err = capsys.readouterr().err
    assert rc == 2 and "not empty" in err and (tmp_path / "views" / "left" / "0000.png").read_bytes() == b"x"


A0_BOARD = 'type = "charuco"\nsquares_x = 11\nsquares_y = 8\nsquare_size = 0.105\nmarker_size = 0.078\ndictionary = "DICT_5X5_100"\n'


def _cli(argv, capsys) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_a_sim_rig_as_config_init_writes_it_calibrates_from_the_printed_next_command(tmp_path, monkeypatch, capsys):
    """The newcomer's journey: `rig config init --sim`, `rig calibrate capture` with a board file,
    then the `next:` line it prints. The simulated rig shows the board itself (no [sim] edits)."""
    import shlex

    monkeypatch.chdir(tmp_path)
    (tmp_path / "board.toml").write_text(A0_BOARD)
    assert _cli(["config", "init", "--sim", "rig.toml"], capsys)[0] == 0
    rc, out, err = _cli(["calibrate", "capture", "-c", "rig.toml", "--board", "board.toml", "-o", "views", *SLOW_RENDER], capsys)
    assert rc == 0, err
    summary_line = next(line for line in out.splitlines() if line.startswith("kept "))
    assert int(summary_line.split()[1]) >= 20, summary_line
    nxt = next(line for line in out.splitlines() if line.startswith("next: "))
    argv = shlex.split(nxt[len("next: "):])
    assert argv[:3] == ["rig", "calibrate", "run"]
    rc, out, err = _cli(argv[1:] + ["--json"], capsys)
    assert rc == 0, err
    result = json.loads(out)
    assert result["cameras"] == ["left", "right"] and all(n >= 10 for n in result["views_used"].values())
    assert result["baseline_m"] == pytest.approx(3.6, abs=0.01)  # the arc's left-right distance, 60 degrees on 3.6 m


def test_a_capture_that_never_sees_the_board_fails_with_the_reason(tmp_path, monkeypatch, capsys):
    """At 160x96 the board's markers are about a pixel: nothing is detected, nothing kept, exit 1."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "board.toml").write_text(A0_BOARD)
    assert _cli(["config", "init", "--sim", "--width", "160", "--height", "96", "rig.toml"], capsys)[0] == 0
    rc, out, err = _cli(["calibrate", "capture", "-c", "rig.toml", "--board", "board.toml", "-o", "views", "--max-frames", "3"], capsys)
    assert rc == 1 and err.count("\n") == 1 and "never seen" in err and "board.toml" in err, err
    assert "next:" not in out


def test_a_capture_too_short_for_calibrate_run_fails_and_keeps_its_views(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "board.toml").write_text(A0_BOARD)
    assert _cli(["config", "init", "--sim", "rig.toml"], capsys)[0] == 0
    rc, out, err = _cli(["calibrate", "capture", "-c", "rig.toml", "--board", "board.toml", "-o", "views", "--max-frames", "2", *SLOW_RENDER], capsys)
    assert rc == 1 and err.count("\n") == 1 and "too few views" in err and "'left' in" in err, err
    assert (tmp_path / "views" / "left" / "0000.png").is_file()  # what was captured stays


def test_a_simulated_capture_is_the_same_every_time(tmp_path, monkeypatch, capsys):
    """The session counts time in views, not host time: start-up time and render speed change
    nothing (`rig demo`'s test relies on it)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "board.toml").write_text(A0_BOARD)
    assert _cli(["config", "init", "--sim", "rig.toml"], capsys)[0] == 0
    runs = []
    for k, pause in enumerate((0.0, 0.3)):
        rc, out, err = _cli(["calibrate", "capture", "-c", "rig.toml", "--board", "board.toml", "-o", f"v{k}", "--views", "5",
                             "--interval", pause, "--json", *SLOW_RENDER], capsys)
        assert rc == 0, err
        runs.append(json.loads(out))
    assert len(runs[0]["kept"]) == 5
    assert runs[0]["kept"] == runs[1]["kept"] and runs[0]["views_looked_at"] == runs[1]["views_looked_at"]
    for cam in ("left", "right"):
        for view in runs[0]["kept"]:
            assert (tmp_path / "v0" / cam / f"{view['view']}.png").read_bytes() == (tmp_path / "v1" / cam / f"{view['view']}.png").read_bytes()


def test_a_camera_slower_than_the_timeout_says_to_raise_it(tmp_path, monkeypatch, capsys):
    """A simulated 1280x720 frame takes longer than 1 ms to render: the capture stops with one line
    that names the camera and the option that gives it longer, and exit 1 (a device error)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "board.toml").write_text(A0_BOARD)
    assert _cli(["config", "init", "--sim", "rig.toml"], capsys)[0] == 0
    rc, out, err = _cli(["calibrate", "capture", "-c", "rig.toml", "--board", "board.toml", "-o", "views", "--timeout", "0.001"], capsys)
    assert rc != 0 and err.count("\n") == 1 and "no frame within 0.001 s" in err and "--timeout SECONDS" in err, (rc, err)
