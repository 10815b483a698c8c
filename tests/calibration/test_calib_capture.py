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
    summary = run_json("calibrate", "capture", "-c", config, "--board", board_file, "-o", out,
                       "--views", "3", "--max-frames", "6", "--interval", "0.7")
    print(f"\ncapture: kept {summary['views_kept']} of {summary['views_looked_at']} views; coverage {summary['coverage']}")
    assert 1 <= summary["views_kept"] <= 3
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
