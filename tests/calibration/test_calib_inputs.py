"""Board files and image folders as other tools leave them."""
from __future__ import annotations

import pytest

from calibration.boards import load_board
from calibration.camera import CalibrationError
from calibration.images import find_camera_images, find_images


def test_an_anipose_board_file_is_read_in_millimetres(tmp_path):
    path = tmp_path / "board.toml"
    path.write_text("board_x = 8\nboard_y = 11\nsquare_length = 24.0\nmarker_length = 18.75\nmarker_bits = 4\ndict_size = 1000\n")
    board = load_board(path)
    assert (board.type, board.squares_x, board.squares_y, board.dictionary) == ("charuco", 8, 11, "DICT_4X4_1000")
    assert board.square_size == pytest.approx(0.024) and board.marker_size == pytest.approx(0.01875)


@pytest.mark.parametrize("text, words", [
    ("board_x = 8\nboard_y = 11\nsquare_length = 24.0\nmarker_length = 18.75\nmarker_bits = 4\n", "missing key(s) dict_size"),
    ("board_x = 8\nboard_y = 11\nsquare_length = -2\nmarker_length = 18.75\nmarker_bits = 4\ndict_size = 1000\n", "'square_length' must be a positive"),
    ("board_x = 8\nboard_y = 11\nsquare_length = 24\nmarker_length = 18\nmarker_bits = 4\ndict_size = 77\n", "unknown 'dictionary' 'DICT_4X4_77'"),
    ("board_x = 8\nboard_y = 11\nsquare_length = 24\nmarker_length = 18\nmarker_bits = 4\ndict_size = 50\ncolour = 1\n", "unknown key(s) colour"),
])
def test_a_bad_anipose_board_file_is_one_clear_error(tmp_path, text, words):
    path = tmp_path / "board.toml"
    path.write_text(text)
    with pytest.raises(CalibrationError) as err:
        load_board(path)
    assert words in str(err.value) and "\n" not in str(err.value)


def _touch(folder, names):
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"")


def test_cameras_naming_files_by_time_are_matched_by_the_number_that_ends_the_name(tmp_path):
    _touch(tmp_path / "back", ["back-0224135219-0.jpg", "back-0224135220-1.jpg", "back-0224135221-10.jpg"])
    _touch(tmp_path / "mid", ["mid-0224135221-0.jpg", "mid-0224135222-1.jpg", "mid-0224135223-10.jpg"])
    images = find_images(tmp_path)
    assert images.views == ["0", "1", "10"]
    assert images.paths["mid"]["10"].name == "mid-0224135223-10.jpg"


def test_shared_stems_stay_the_key_and_an_ambiguous_number_changes_nothing(tmp_path):
    _touch(tmp_path / "a" / "x", ["0001.png", "0002.png"])
    _touch(tmp_path / "a" / "y", ["0001.png", "0002.png"])
    assert find_images(tmp_path / "a").views == ["0001", "0002"]
    _touch(tmp_path / "b" / "x", ["x-1.png", "x-01.png"])  # two files end in 1
    _touch(tmp_path / "b" / "y", ["y-1.png"])
    with pytest.raises(CalibrationError, match=r"'x', 'y' is paired"):  # not keyed by number: then nothing pairs
        find_images(tmp_path / "b")


def test_one_cameras_intrinsics_photos_may_lie_directly_in_the_folder(tmp_path):
    _touch(tmp_path / "cam07", ["a.jpg", "b.jpg"])
    assert find_camera_images(tmp_path / "cam07").paths == {"cam07": {"a": tmp_path / "cam07" / "a.jpg", "b": tmp_path / "cam07" / "b.jpg"}}
    with pytest.raises(CalibrationError, match="no images of camera 'cam09'"):
        find_camera_images(tmp_path, ["cam09"])


def test_intrinsics_to_hold_are_checked_before_anything_runs(tmp_path):
    from tests.rig.cli_helpers import assert_one_line_error, run_rig

    def run_rig_error(*argv):
        return assert_one_line_error(run_rig(*argv))

    _touch(tmp_path / "imgs" / "back", ["a.png"])
    _touch(tmp_path / "imgs" / "mid", ["a.png"])
    board = tmp_path / "board.toml"
    board.write_text('type = "chessboard"\ncols = 4\nrows = 7\nsquare_size = 0.06\n')
    toml = tmp_path / "calib.toml"
    toml.write_text('[cam_0]\nname = "back"\nsize = [640, 480]\nmatrix = [[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]\n'
                    'distortions = [-0.1, 0, 0, 0, 0]\n')
    base = ["calibrate", "run", "--images", tmp_path / "imgs", "--board", board, "-o", tmp_path / "out.json"]
    assert "--hold needs --intrinsics" in run_rig_error(*base, "--hold", "back")
    assert "has no camera 'mid'" in run_rig_error(*base, "--intrinsics", toml, "--hold", "mid")
    bad = tmp_path / "bad.toml"
    bad.write_text('[cam_0]\nname = "back"\nsize = [640, 480]\nmatrix = [[-5.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]\ndistortions = [0]\n')
    assert "positive focal lengths" in run_rig_error(*base, "--intrinsics", bad)
    assert not (tmp_path / "out.json").exists()


def test_inverted_is_a_board_file_key(tmp_path):
    path = tmp_path / "board.toml"
    path.write_text('type = "charuco"\nsquares_x = 7\nsquares_y = 5\nsquare_size = 0.08\nmarker_size = 0.06\ninverted = true\n')
    board = load_board(path)
    assert board.inverted and board.to_dict()["inverted"] is True
    assert board.image(200.0)[0, 0] == 0  # printed white on black, margin included
    path.write_text('type = "chessboard"\ncols = 8\nrows = 5\nsquare_size = 0.06\ninverted = "yes"\n')
    with pytest.raises(CalibrationError, match="'inverted' must be true or false"):
        load_board(path)


def test_intrinsics_of_no_camera_is_one_error_and_writes_nothing(tmp_path):
    import json

    import cv2

    from calibration.boards import ChessboardSpec
    from calibration.synthetic import warp_board
    from tests.rig.cli_helpers import run_rig

    board = ChessboardSpec(8, 5, 0.03)
    (tmp_path / "cam").mkdir()
    for i, quad in enumerate(([[100, 80], [500, 90], [520, 380], [90, 370]], [[150, 60], [560, 120], [540, 420], [120, 400]])):
        cv2.imwrite(str(tmp_path / "cam" / f"{i}.png"), warp_board(board, quad, size=(640, 480), ppm=4000)[0])
    (tmp_path / "board.toml").write_text('type = "chessboard"\ncols = 8\nrows = 5\nsquare_size = 0.03\n')
    proc = run_rig("calibrate", "intrinsics", "--images", tmp_path / "cam", "--board", tmp_path / "board.toml", "-o", tmp_path / "i.json", "--json")
    assert proc.returncode == 2 and len(proc.stdout.strip().splitlines()) == 1, proc.stdout
    answer = json.loads(proc.stdout)
    assert "found in only 2 image(s)" in answer["error"] and not (tmp_path / "i.json").exists()


def test_hidden_files_beside_the_images_are_not_views(tmp_path):
    # macOS copies leave `._NAME` (AppleDouble metadata) beside each image: not images, not views
    _touch(tmp_path / "left", ["0001.png", "._0001.png", "0002.png"])
    _touch(tmp_path / "right", ["0001.png", "0002.png", ".0003.png"])
    images = find_images(tmp_path)
    assert images.views == ["0001", "0002"] and sorted(images.paths["left"]) == ["0001", "0002"]
    assert sorted(find_camera_images(tmp_path).paths["left"]) == ["0001", "0002"]
    # and they do not stop the cameras naming their files by time from being paired by the end number
    _touch(tmp_path / "t" / "back", ["back-0224135219-0.jpg", "._back-0224135219-0.jpg", "back-0224135220-1.jpg"])
    _touch(tmp_path / "t" / "mid", ["mid-0224135221-0.jpg", "mid-0224135222-1.jpg"])
    assert find_images(tmp_path / "t").views == ["0", "1"]


def test_a_camera_whose_images_pair_with_no_other_cameras_is_named_before_the_detection(tmp_path):
    _touch(tmp_path / "left", ["left-1-0.jpg", "left-1-1.jpg", "left-2-1.jpg"])  # end numbers repeat: not a key
    _touch(tmp_path / "right", ["right_1.jpg", "right_2.jpg"])
    with pytest.raises(CalibrationError) as err:
        find_images(tmp_path)
    msg = str(err.value)
    assert "'left', 'right'" in msg and "is paired with another camera's" in msg and "\n" not in msg
    _touch(tmp_path / "top", ["right_1.jpg"])  # one camera paired with another is enough for it
    with pytest.raises(CalibrationError, match=r"camera\(s\) 'left' is paired"):
        find_images(tmp_path)
