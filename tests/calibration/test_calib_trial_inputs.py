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


def test_held_intrinsics_of_the_wrong_size_are_refused_naming_the_file_before_the_detection(tmp_path, board, capsys):
    """Measured before: 'camera 'back': camera 'back' is 640x480 there but ...' (no file named, the
    camera twice), after the detection of every image (25 s on the sleap-anipose recording)."""
    import json

    import cv2
    import numpy as np

    for cam in ("a", "b"):
        (tmp_path / "images" / cam).mkdir(parents=True)
        for n in range(4):
            cv2.imwrite(str(tmp_path / "images" / cam / f"{n:04d}.png"), np.zeros((48, 64), np.uint8))
    given = tmp_path / "intr.json"
    given.write_text(json.dumps({"format": "rig-intrinsics", "version": 1, "cameras": {"a": {
        "width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 320, "cy": 240, "dist": [0, 0, 0, 0, 0]}}}))
    out = tmp_path / "out.json"
    err = _one_line_exit_2(["calibrate", "run", "--images", tmp_path / "images", "--board", board, "-o", out,
                            "--intrinsics", given], capsys)
    assert f"{given}: camera 'a' is 640x480 there but its images are 64x48" in err, err  # not 'the board was not found'
    assert not out.exists()


def test_a_prior_term_given_twice_and_offsets_int_alone_reads_are_refused():
    from calibration.camera import CalibrationError
    from calibration.known import parse_prior
    from calibration.pairing import parse_offsets

    with pytest.raises(CalibrationError, match="f is given a sigma twice"):
        parse_prior("f=1%,f=2%")  # before: the last one won, silently
    for spec in ("cam=1_0", "cam=\uff11", "cam=1.0"):  # before: int() read the first two as 10 and 1
        with pytest.raises(CalibrationError, match="expected CAMERA=N"):
            parse_offsets([spec])
    assert parse_offsets(["cam=+2", "b=-1", "c=0"]) == {"cam": 2, "b": -1, "c": 0}


def test_a_huge_prior_sigma_is_no_weight_and_no_overflow_warning():
    """Measured before: --prior-sigma f=1e300 printed numpy's 'overflow encountered in square' on stderr."""
    import warnings

    import numpy as np

    from calibration import bundle

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        blocks = bundle._prior_blocks(1, np.arange(bundle.N_INTR), np.full((1, bundle.N_INTR), 1e300), None)
    assert all(not np.any(b[2]) for b in blocks)


def test_held_intrinsics_no_view_fits_are_named_as_the_likely_fault():
    """Measured before on the sleap-anipose recording with a lens of k1 = 0 held for `back`: 'every view
    was rejected as an outlier; check the images of this camera'."""
    from calibration.boards import CharucoSpec
    from calibration.camera import CalibrationError
    from calibration.known import KnownIntrinsics
    from calibration.solve import Options, calibrate_rig
    from calibration.synthetic import arc_rig, board_poses, observe

    board = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
    truth = arc_rig(3)
    det = observe(truth, board, board_poses(20), noise_px=0.2)
    c = truth.cameras[1]
    wrong = KnownIntrinsics(c.name, (c.width, c.height), c.K, c.dist + [3.0, 0, 0, 0, 0], source="lenses.json")  # another lens's k1
    with pytest.raises(CalibrationError) as err:
        calibrate_rig(det, board, Options(known={c.name: wrong}))
    msg = str(err.value)
    assert f"camera '{c.name}': every view was rejected" in msg and "given and held (--intrinsics: lenses.json)" in msg, msg


def test_a_camera_the_joint_fit_leaves_with_under_four_views_is_unusable_and_not_written():
    """Measured before: a held lens with another lens's p1 kept 2 of its camera's 20 views in the joint
    fit, verdict 'weak', and `run` wrote the rig; on the sleap-anipose recording with `side` three
    instants late and `--offset side=-2`, 1 of 21 views, written (exit 0)."""
    from calibration.boards import CharucoSpec
    from calibration.known import KnownIntrinsics
    from calibration.solve import Options, calibrate_rig
    from calibration.synthetic import arc_rig, board_poses, observe
    from rig.calibrate.run import _unusable_cameras, _unusable_message

    board = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
    truth = arc_rig(3)
    det = observe(truth, board, board_poses(20), noise_px=0.2)
    c = truth.cameras[1]
    wrong = KnownIntrinsics(c.name, (c.width, c.height), c.K, c.dist + [0, 0, 0.05, 0, 0])
    rig = calibrate_rig(det, board, Options(known={c.name: wrong})).rig
    entry = rig.meta["report"]["cameras"][c.name]
    assert entry["views_used"] < 4 and entry["verdict"] == "unusable", entry
    assert entry["reasons"][0].startswith("the joint rig fit kept only"), entry["reasons"]
    assert _unusable_cameras(rig) == [c.name]
    msg = _unusable_message(rig, [c.name], "out.json")
    assert f"the joint rig fit kept only {entry['views_used']} of '{c.name}''s views" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("damage", ["lens_prior_without_beyond", "lens_prior_a_string", "pairing_without_keys"])
def test_a_damaged_report_section_is_one_line(tmp_path, capsys, damage):
    """Measured before: `rig calibrate report` on a file whose report was edited ended in a KeyError or
    TypeError traceback (exit 1)."""
    import json

    from calibration.boards import CharucoSpec
    from calibration.solve import Options, calibrate_rig
    from calibration.synthetic import arc_rig, board_poses, observe

    board = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
    rig = calibrate_rig(observe(arc_rig(2), board, board_poses(12), noise_px=0.2), board, Options()).rig
    path = tmp_path / "calib.json"
    rig.save(path)
    doc = json.loads(path.read_text())
    name = rig.names[-1]
    if damage == "lens_prior_without_beyond":
        doc["report"]["cameras"][name]["lens_prior"] = {"kept": False}
    elif damage == "lens_prior_a_string":
        doc["report"]["cameras"][name]["lens_prior"] = "kept"
    else:
        doc["report"]["pairing"] = [{"camera": name}, 3]
    path.write_text(json.dumps(doc))
    err = _one_line_exit_2(["calibrate", "report", path], capsys)
    assert "its 'report') are malformed" in err, err


def test_intrinsics_lists_an_empty_camera_folder_as_failed(tmp_path, board, shared_data):
    """`rig calibrate intrinsics` calibrates each camera on its own: an empty camera folder is listed
    in `failed` (before: left out without a word), the others still calibrated."""
    from tests.calibration.cli_helpers import run_json

    xi = shared_data / "xi-stereo-chessboard"
    (tmp_path / "images" / "left").mkdir(parents=True)
    (tmp_path / "images" / "right").mkdir()
    for f in sorted(xi.glob("left*.jpg"))[:8]:
        (tmp_path / "images" / "left" / f.name).symlink_to(f)
    doc = run_json("calibrate", "intrinsics", "--images", tmp_path / "images", "--board", board, "-o", tmp_path / "intr.json")
    assert list(doc["cameras"]) == ["left"]
    assert doc["failed"] == {"right": f"camera 'right': no images in its folder {tmp_path / 'images' / 'right'}"}, doc["failed"]
