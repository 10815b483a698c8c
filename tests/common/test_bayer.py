"""The one Bayer mosaic/demosaic: every sensor sample survives the round trip, the patterns are the
GenICam ones (block at (0, 0)) and agree with OpenCV's own naming (block at (1, 1)), and the camera
path and the simulator both use it."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.bayer import PATTERNS, bayer_pattern, demosaic, mosaic

SIZES = [(2, 2), (3, 3), (4, 6), (5, 7), (90, 160), (91, 161)]


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_demosaic_keeps_every_sample_so_the_mosaic_comes_back_exactly(pattern, dtype):
    rng = np.random.default_rng(7)
    for h, w in SIZES:
        raw = rng.integers(0, np.iinfo(dtype).max, size=(h, w), dtype=dtype, endpoint=True)
        rgb = demosaic(raw, pattern)
        assert rgb.shape == (h, w, 3) and rgb.dtype == dtype
        assert np.array_equal(mosaic(rgb, pattern), raw), f"{pattern} {h}x{w}: a sample changed"


def test_the_border_gets_the_interior_treatment():
    # OpenCV alone fills the outermost rows and columns from their neighbours: samples are lost there
    raw = np.random.default_rng(1).integers(0, 256, size=(12, 16), dtype=np.uint8)
    plain = cv2.cvtColor(raw, cv2.COLOR_BayerBG2RGB)
    assert not np.array_equal(mosaic(plain, "RG"), raw), "the check below would prove nothing"
    assert np.array_equal(mosaic(demosaic(raw, "RG"), "RG"), raw)
    assert np.array_equal(demosaic(raw, "RG")[2:-2, 2:-2], plain[2:-2, 2:-2]), "inside, it is OpenCV's demosaic"


@pytest.mark.parametrize("pattern, opencv", [("RG", cv2.COLOR_BayerBG2RGB), ("BG", cv2.COLOR_BayerRG2RGB),
                                              ("GR", cv2.COLOR_BayerGB2RGB), ("GB", cv2.COLOR_BayerGR2RGB)])
def test_patterns_are_named_by_the_top_left_block_and_match_opencv(pattern, opencv):
    colour = np.array([200, 120, 40], np.uint8)  # R, G, B all different: a swapped channel shows
    flat = np.broadcast_to(colour, (8, 10, 3)).copy()
    raw = mosaic(flat, pattern)
    top_left = {"R": 200, "G": 120, "B": 40}[pattern[0]]
    right_of_it = {"R": 200, "G": 120, "B": 40}[pattern[1]]
    assert raw[0, 0] == top_left and raw[0, 1] == right_of_it
    assert np.array_equal(demosaic(raw, pattern), flat)
    assert np.array_equal(cv2.cvtColor(raw, opencv)[2:-2, 2:-2], flat[2:-2, 2:-2]), "OpenCV reads our pattern as this code"


def test_genicam_pixel_formats_name_the_same_patterns():
    raw = np.random.default_rng(2).integers(0, 256, size=(6, 8), dtype=np.uint8)
    for pattern in PATTERNS:
        assert bayer_pattern(f"Bayer{pattern}8") == pattern
        assert np.array_equal(demosaic(raw, f"Bayer{pattern}8"), demosaic(raw, pattern))


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="not a Bayer pattern"):
        mosaic(np.zeros((4, 4, 3), np.uint8), "RGB8")
    with pytest.raises(ValueError, match="not a Bayer pattern"):
        demosaic(np.zeros((4, 4), np.uint8), "BayerRG16")
    with pytest.raises(ValueError, match="HxWx3"):
        mosaic(np.zeros((4, 4), np.uint8), "RG")
    with pytest.raises(ValueError, match="at least 2x2"):
        demosaic(np.zeros((1, 4), np.uint8), "RG")
    with pytest.raises(ValueError, match="uint8 or uint16"):
        demosaic(np.zeros((4, 4), np.float32), "RG")


def test_the_camera_path_and_the_simulator_share_it():
    from rig.cameras import pixels
    from simulator.sensor import SensorModel
    from simulator.rig import virtual_rig
    from simulator.scene import Scene

    raw = np.random.default_rng(3).integers(0, 256, size=(10, 12), dtype=np.uint8)
    assert np.array_equal(pixels.buffer_to_image(raw.tobytes(), 12, 10, "BayerGR8"), demosaic(raw, "GR"))
    assert np.array_equal(pixels.from_rgb(demosaic(raw, "GR"), "BayerGR8"), raw)

    cam = virtual_rig(2, 64, 36)["left"]
    quiet = {"read_noise": 0.0, "shot_noise": 0.0, "motion_blur": False}
    scene = Scene(seed=1, people=1, name="empty")
    rgb = SensorModel(scene, cam, quiet).expose(1.0, 0.005, np.random.default_rng(0))
    sensor = SensorModel(scene, cam, {**quiet, "bayer": "GB"})
    samples = sensor.expose(1.0, 0.005, np.random.default_rng(0), raw=True)
    assert np.array_equal(samples, mosaic(rgb, "GB"))
    assert np.array_equal(sensor.expose(1.0, 0.005, np.random.default_rng(0)), demosaic(samples, "GB"))
