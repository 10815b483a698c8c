"""The board detections' cache: a second run over the same images finds the same corners without
detecting again; another board, changed pixels or a damaged entry are detected afresh."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

import calibration.detect as detect_mod
from calibration import detection_cache
from calibration.boards import CharucoSpec
from calibration.images import detect_images, find_images
from calibration.synthetic import warp_board

BOARD = CharucoSpec(7, 5, 0.08, 0.06, "DICT_5X5_100")
QUADS = ([[400, 150], [900, 200], [880, 560], [420, 600]], [[300, 100], [800, 160], [760, 520], [330, 560]])


@pytest.fixture
def images(tmp_path, monkeypatch):
    monkeypatch.setenv("RIG_CACHE_DIR", str(tmp_path / "cache"))
    for shift, cam in enumerate(("left", "right")):
        (tmp_path / "views" / cam).mkdir(parents=True)
        for k, quad in enumerate(QUADS):
            image, _ = warp_board(BOARD, [[x + 7 * shift, y] for x, y in quad])
            cv2.imwrite(str(tmp_path / "views" / cam / f"{k:04d}.png"), image)
        cv2.imwrite(str(tmp_path / "views" / cam / "0002.png"), np.full((720, 1280), 128 + shift, np.uint8))  # no board
    return tmp_path / "views"


class CountingDetector:
    """Counts the detector's calls on images (the cache's hits make none)."""

    def __init__(self, monkeypatch):
        self.calls = 0
        real = detect_mod.AnyFaceDetector.__call__

        def counted(det, image):
            self.calls += 1
            return real(det, image)

        monkeypatch.setattr(detect_mod.AnyFaceDetector, "__call__", counted)


def _same(a, b) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[v].ids, b[v].ids) and np.array_equal(a[v].points, b[v].points) for v in a)


def test_a_second_run_reads_what_the_first_found(images, monkeypatch):
    counter = CountingDetector(monkeypatch)
    first = detect_images(find_images(images), BOARD)
    assert counter.calls == 6 and sorted(first.corners["left"]) == ["0000", "0001"]
    again = detect_images(find_images(images), BOARD)
    assert counter.calls == 6  # nothing detected again, the board's absence included
    for cam in ("left", "right"):
        assert _same(first.corners[cam], again.corners[cam])
    assert again.images_seen == first.images_seen and again.image_size == first.image_size and again.sources == first.sources


def test_another_board_changed_pixels_or_a_damaged_entry_are_detected_again(images, monkeypatch):
    counter = CountingDetector(monkeypatch)
    detect_images(find_images(images), BOARD)
    assert counter.calls == 6
    # another board: every image again
    detect_images(find_images(images), dataclasses.replace(BOARD, square_size=0.1))
    assert counter.calls == 12
    # one image's pixels change: that image only
    img = cv2.imread(str(images / "left" / "0000.png"), cv2.IMREAD_GRAYSCALE)
    img[0, 0] ^= 1
    cv2.imwrite(str(images / "left" / "0000.png"), img)
    detect_images(find_images(images), BOARD)
    assert counter.calls == 13
    # a damaged entry is ignored and written again, never an error
    entries = sorted(detection_cache.cache_dir().rglob("*.npz"))
    assert len(entries) == 13
    for e in entries:
        e.write_bytes(e.read_bytes()[:40])
    found = detect_images(find_images(images), BOARD)
    assert counter.calls == 19 and sorted(found.corners["right"]) == ["0000", "0001"]
    # turned off: nothing read or written
    monkeypatch.setenv("RIG_DETECTION_CACHE", "0")
    detect_images(find_images(images), BOARD)
    assert counter.calls == 25
