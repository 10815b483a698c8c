"""`rig calibrate board|run|report|export` from the command line, including bad input."""
from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.boards import CharucoSpec
from calibration.detect import detect
from calibration.synthetic import warp_board
from rig.cli import main

REPO = Path(__file__).resolve().parents[2]
CHARUCO_TOML = 'type = "charuco"\nsquares_x = 7\nsquares_y = 5\nsquare_size = 0.03\nmarker_size = 0.022\ndictionary = "DICT_5X5_100"\n'


def run(argv, capsys):
    rc = main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.fixture
def charuco_file(tmp_path):
    p = tmp_path / "board.toml"
    p.write_text(CHARUCO_TOML)
    return p


def _png_dpi(path: Path) -> float:
    data = path.read_bytes()
    i = data.index(b"pHYs")
    ppm_x, ppm_y, unit = struct.unpack(">IIB", data[i + 4 : i + 13])
    assert unit == 1 and ppm_x == ppm_y
    return ppm_x * 0.0254


def test_board_prints_at_true_size_and_is_detectable(charuco_file, tmp_path, capsys):
    out = tmp_path / "board.png"
    rc, text, _ = run(["calibrate", "board", str(charuco_file), "-o", str(out), "--dpi", "150", "--json"], capsys)
    assert rc == 0
    info = json.loads(text)
    img = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    # 7 x 3 cm squares plus a half-square margin each side = 24 cm wide.
    assert img.shape[1] == info["width_px"] and abs(img.shape[1] - 0.24 / 0.0254 * 150) <= 1.5
    assert info["width_mm"] == pytest.approx(240, abs=0.5)
    assert _png_dpi(out) == pytest.approx(150, rel=2e-4)  # whole pixels per metre: off by at most 0.5 / 5906 (measured 8e-5)
    corners = detect(CharucoSpec(7, 5, 0.03, 0.022), img)
    assert corners is not None and len(corners) == 24


def test_board_file_with_impossible_sizes_is_rejected(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(CHARUCO_TOML.replace("marker_size = 0.022", "marker_size = 0.05"))
    rc, _, err = run(["calibrate", "board", str(bad), "-o", str(tmp_path / "b.png")], capsys)
    assert rc == 2 and str(bad) in err and "marker_size" in err and err.count("\n") == 1
    bad.write_text('type = "chessboard"\ncols = 1\nrows = 6\nsquare_size = 0.024\n')
    rc, _, err = run(["calibrate", "run", "--images", str(tmp_path), "--board", str(bad), "-o", str(tmp_path / "c.json")], capsys)
    assert rc == 2 and str(bad) in err and "at least 2" in err


def test_no_board_found_anywhere(tmp_path, charuco_file, capsys):
    for cam in ("left", "right"):
        (tmp_path / "imgs" / cam).mkdir(parents=True)
        for i in range(3):
            cv2.imwrite(str(tmp_path / "imgs" / cam / f"{i:04d}.png"), np.full((120, 160), 90, np.uint8))
    rc, _, err = run(["calibrate", "run", "--images", str(tmp_path / "imgs"), "--board", str(charuco_file), "-o", str(tmp_path / "c.json")], capsys)
    assert rc == 2 and str(tmp_path / "imgs") in err and "not found in any of the 6 images" in err
    assert "squares_x and squares_y count its squares, and its marker dictionary" in err
    assert not (tmp_path / "c.json").exists()
    chess = tmp_path / "chess.toml"
    chess.write_text('type = "Chessboard"\ncols = 10\nrows = 7\nsquare_size = 0.03\n')  # as other tools write the type
    rc, _, err = run(["calibrate", "run", "--images", str(tmp_path / "imgs"), "--board", str(chess), "-o", str(tmp_path / "c.json")], capsys)
    assert rc == 2 and "cols and rows count its inner corners (a board of 10 x 7 squares has 9 x 6)" in err


def test_images_of_different_sizes_for_one_camera(tmp_path, charuco_file, capsys):
    board = CharucoSpec(7, 5, 0.03, 0.022)
    img, _ = warp_board(board, [[100, 100], [500, 110], [490, 380], [110, 390]], size=(640, 480), ppm=4000)
    d = tmp_path / "imgs" / "left"
    d.mkdir(parents=True)
    cv2.imwrite(str(d / "0001.png"), img)
    cv2.imwrite(str(d / "0002.png"), cv2.resize(img, (320, 240)))
    rc, _, err = run(["calibrate", "run", "--images", str(tmp_path / "imgs"), "--board", str(charuco_file), "-o", str(tmp_path / "c.json")], capsys)
    assert rc == 2 and "0002.png" in err and "320x240" in err and "640x480" in err


def test_empty_image_folder(tmp_path, charuco_file, capsys):
    rc, _, err = run(["calibrate", "run", "--images", str(tmp_path), "--board", str(charuco_file), "-o", str(tmp_path / "c.json")], capsys)
    assert rc == 2 and "no calibration images" in err


@pytest.mark.parametrize("content", ['{"version": 1, "cameras": [', '{"version": 7, "cameras": []}', "", '{"version": 1, "cameras": [{"name": "a"}]}'])
@pytest.mark.parametrize("command", ["report", "export"])
def test_corrupt_calibration_file(tmp_path, capsys, content, command):
    bad = tmp_path / "calib.json"
    bad.write_text(content)
    argv = ["calibrate", command, str(bad)] + (["--format", "opencv", "-o", str(tmp_path / "out")] if command == "export" else [])
    rc, out, err = run(argv, capsys)
    assert rc == 2 and str(bad) in err and err.count("\n") == 1 and out == ""


def test_exit_status_from_the_console_script(tmp_path):
    bad = tmp_path / "calib.json"
    bad.write_text("{not json")
    proc = subprocess.run([sys.executable, "-m", "rig", "calibrate", "report", str(bad)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("rig: error:") and str(bad) in proc.stderr and "Traceback" not in proc.stderr


def test_roles_file_names_the_stereo_pair(tmp_path):
    from calibration.camera import CalibrationError
    from calibration.images import find_images

    for cam in ("cam_a", "cam_b"):
        (tmp_path / cam).mkdir()
        cv2.imwrite(str(tmp_path / cam / "0000.png"), np.zeros((8, 8), np.uint8))
    assert find_images(tmp_path).roles == {}
    (tmp_path / "roles.json").write_text('{"left": "cam_b", "right": "cam_a"}')
    assert find_images(tmp_path).roles == {"left": "cam_b", "right": "cam_a"}
    (tmp_path / "roles.json").write_text('{"left": "cam_c"}')
    with pytest.raises(CalibrationError, match="roles.json.*cam_c"):
        find_images(tmp_path)


def test_unreadable_image_is_named(tmp_path, charuco_file, capsys):
    d = tmp_path / "imgs" / "left"
    d.mkdir(parents=True)
    (d / "0001.png").write_bytes(b"not a png")
    rc, _, err = run(["calibrate", "run", "--images", str(tmp_path / "imgs"), "--board", str(charuco_file), "-o", str(tmp_path / "c.json")], capsys)
    assert rc == 2 and "0001.png" in err and "cannot read" in err


def test_a_failure_with_json_is_also_one_json_object_on_stdout(tmp_path, charuco_file):
    import json

    for cam in ("left", "right"):
        (tmp_path / "imgs" / cam).mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "imgs" / cam / "0000.png"), np.full((120, 160), 90, np.uint8))
    proc = subprocess.run([sys.executable, "-m", "rig", "calibrate", "run", "--images", str(tmp_path / "imgs"), "--board", str(charuco_file),
                           "-o", str(tmp_path / "c.json"), "--json"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    answer = json.loads(proc.stdout)
    assert answer["exit_code"] == 2 and "not found in any of the 2 images" in answer["error"]


def test_the_rig_config_names_the_stereo_pair(tmp_path, charuco_file, capsys):
    for cam in ("cam_a", "cam_b", "cam_c"):
        (tmp_path / "imgs" / cam).mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "imgs" / cam / "0000.png"), np.zeros((8, 8), np.uint8))
    config = tmp_path / "rig.toml"
    config.write_text('[rig]\nname = "r"\n[[cameras]]\nname = "cam_x"\nuri = "sim://cam_x"\nrole = "left"\n'
                      '[[cameras]]\nname = "cam_a"\nuri = "sim://cam_a"\nrole = "right"\n')
    rc, _, err = run(["calibrate", "run", "--images", str(tmp_path / "imgs"), "--board", str(charuco_file), "-o", str(tmp_path / "c.json"),
                      "-c", str(config)], capsys)
    assert rc == 2 and "left camera 'cam_x' has no images" in err and err.count("\n") == 1
