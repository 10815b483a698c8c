"""Corner detection: exact corners with ids, partial ChArUco views, a consistent chessboard order."""
from __future__ import annotations

import cv2
import numpy as np

from calibration.boards import CharucoSpec, ChessboardSpec
from calibration.detect import canonical_chessboard_order, detect
from calibration.synthetic import warp_board

QUAD = [[400, 150], [900, 200], [880, 560], [420, 600]]


def _errors(board, corners, H):
    _, obj = board.object_points()
    truth = cv2.perspectiveTransform(obj[corners.ids, :2].reshape(-1, 1, 2), H).reshape(-1, 2)
    e = corners.points - truth
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1)))), float(np.abs(e).max())


def test_charuco_corners_are_subpixel_accurate():
    board = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
    image, H = warp_board(board, QUAD)
    corners = detect(board, image)
    assert corners is not None and len(corners) == board.n_corners
    rms, worst = _errors(board, corners, H)
    print(f"\nChArUco corner error: RMS {rms:.3f} px, max {worst:.3f} px")
    assert rms < 0.15 and worst < 0.3


def test_partial_charuco_view_keeps_the_visible_corners_with_their_ids():
    board = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
    image, H = warp_board(board, QUAD)
    image[:, :650] = 255  # something hides the left half of the board
    corners = detect(board, image)
    assert corners is not None and 6 <= len(corners) < board.n_corners
    rms, _ = _errors(board, corners, H)
    assert rms < 0.15
    _, obj = board.object_points()
    assert obj[corners.ids, 0].min() > 0.2  # only corners of the right-hand columns


def test_chessboard_corners_are_subpixel_accurate():
    board = ChessboardSpec(9, 6, 0.06)
    image, H = warp_board(board, QUAD)
    corners = detect(board, image)
    assert corners is not None and len(corners) == 54
    rms, worst = _errors(board, corners, H)
    print(f"\nchessboard corner error: RMS {rms:.3f} px, max {worst:.3f} px")
    assert rms < 0.15 and worst < 0.3


def test_chessboard_order_is_the_same_when_the_board_is_turned_half_way():
    # A 9x6 chessboard turned by 180 degrees looks the same; the detector may number it from either end.
    # Canonical order numbers it from the end nearest the image's top-left both times.
    board = ChessboardSpec(9, 6, 0.06)
    image, _ = warp_board(board, QUAD)
    turned = cv2.rotate(image, cv2.ROTATE_180)
    a = detect(board, image)
    b = detect(board, turned)
    assert a is not None and b is not None
    d = a.points[-1] - a.points[0]
    assert d.sum() > 0
    d = b.points[-1] - b.points[0]
    assert d.sum() > 0
    assert np.allclose(canonical_chessboard_order(a.points[::-1]), a.points)


def test_no_board_gives_none():
    blank = np.full((480, 640), 128, np.uint8)
    assert detect(ChessboardSpec(9, 6, 0.024), blank) is None
    assert detect(CharucoSpec(5, 7, 0.04, 0.03), blank) is None


def test_rgb_and_grey_images_give_the_same_corners():
    board = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
    image, _ = warp_board(board, QUAD)
    rgb = np.repeat(image[:, :, None], 3, axis=2)
    a, b = detect(board, image), detect(board, rgb)
    assert np.array_equal(a.ids, b.ids) and np.allclose(a.points, b.points)


def test_a_white_on_black_board_is_found_whatever_the_board_file_says():
    from calibration.detect import make_detector

    for board_cls, args in ((CharucoSpec, (7, 5, 0.08, 0.06, "DICT_5X5_100")), (ChessboardSpec, (8, 5, 0.06))):
        printed = board_cls(*args, inverted=True)
        image, H = warp_board(printed, QUAD)
        for stated in (printed, board_cls(*args)):  # the file says so, or it does not
            detector = make_detector(stated)
            corners = detector(image)
            assert corners is not None and len(corners) == stated.n_corners, (board_cls, stated)
            assert _errors(stated, corners, H)[0] < 0.15
            if board_cls is CharucoSpec:  # its markers read only in their own polarity (a chessboard's corners read in both)
                assert list(detector.found_as) == [(True, False)]


def test_a_chessboard_file_wrongly_saying_white_on_black_changes_no_corner():
    """The classic detector (refined by cornerSubPix) tries both polarities before the sector-based
    one: the latter finds an inverted board too, but less exactly (0.09 px off here, 0.74 px on the
    xi-stereo recording), which moved its focal length by 1 %."""
    from calibration.detect import make_detector

    board = ChessboardSpec(9, 6, 0.06)
    image, _ = warp_board(board, QUAD)
    right, wrong = make_detector(board)(image), make_detector(ChessboardSpec(9, 6, 0.06, inverted=True))(image)
    assert np.array_equal(right.points, wrong.points)


def test_a_charuco_board_seen_from_the_back_gives_its_corners_in_the_images_own_pixels():
    board = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
    image, H = warp_board(board, QUAD)
    mirrored = np.ascontiguousarray(image[:, ::-1])
    flip = np.array([[-1.0, 0, image.shape[1] - 1], [0, 1, 0], [0, 0, 1]])
    corners = detect(board, mirrored)
    assert corners is not None and len(corners) == board.n_corners
    rms, worst = _errors(board, corners, flip @ H)
    assert rms < 0.15 and worst < 0.3


def test_no_board_anywhere_says_what_was_tried(tmp_path):
    from calibration.camera import CalibrationError
    from calibration.images import detect_images, find_images

    (tmp_path / "left").mkdir()
    cv2.imwrite(str(tmp_path / "left" / "0001.png"), np.full((240, 320), 128, np.uint8))
    board = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
    try:
        detect_images(find_images(tmp_path), board)
    except CalibrationError as exc:
        msg = str(exc)
    else:
        raise AssertionError("no error")
    assert "7x5 squares" in msg and "DICT_5X5_100" in msg and "white on black" in msg and "mirrored" in msg and "\n" not in msg
