"""Bad input found trying `rig calibrate` on real recordings from other labs (trial-calib): each is one
line on stderr, exit 2, no traceback, nothing written."""
from __future__ import annotations

import shutil

import pytest

from rig.cli import main

CHESSBOARD = 'type = "chessboard"\ncols = 9\nrows = 6\nsquare_size = 0.024\n'


@pytest.fixture()
def board(tmp_path):
    path = tmp_path / "board.toml"
    path.write_text(CHESSBOARD)
    return path


def _one_line_exit_2(argv, capsys) -> str:
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("command", ["run", "intrinsics"])
def test_an_empty_image_file_is_one_line(tmp_path, board, capsys, command):
    """Measured before: a zero-byte JPEG (a copy cut off) ended in OpenCV's assertion from imdecode,
    a traceback and exit 1."""
    for cam in ("a", "b"):
        (tmp_path / "images" / cam).mkdir(parents=True)
        (tmp_path / "images" / cam / "0001.jpg").write_bytes(b"")
    out = tmp_path / "out.json"
    err = _one_line_exit_2(["calibrate", command, "--images", tmp_path / "images", "--board", board, "-o", out], capsys)
    assert "0001.jpg: cannot read this image (the file is empty)" in err, err
    assert not out.exists()


def test_an_empty_camera_folder_is_named_not_left_out_of_the_rig(tmp_path, board, capsys):
    """Measured before: DIR/back with 21 images and an empty DIR/mid gave a one-camera 'rig' (exit 0)
    and no word of mid."""
    (tmp_path / "images" / "back").mkdir(parents=True)
    (tmp_path / "images" / "back" / "0001.jpg").write_bytes(b"x")
    (tmp_path / "images" / "mid").mkdir()
    (tmp_path / "images" / "__MACOSX").mkdir()  # what macOS's zip leaves is not a camera
    out = tmp_path / "out.json"
    err = _one_line_exit_2(["calibrate", "run", "--images", tmp_path / "images", "--board", board, "-o", out], capsys)
    assert "no images in the folder of camera(s) 'mid'" in err and "__MACOSX" not in err, err
    assert not out.exists()
