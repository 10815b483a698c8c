"""The report's epipolar error: the residual across the epipolar lines, along whichever axis the
rectification aligned (rows for a side-by-side pair, columns for one camera above the other)."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.camera import CameraModel, look_at
from calibration.report import epipolar_error


def _camera(name: str, eye, target=(0.0, 0.0, 4.0)) -> CameraModel:
    K = np.array([[900.0, 0.0, 640.0], [0.0, 900.0, 360.0], [0.0, 0.0, 1.0]])
    R, t = look_at(eye, target)
    return CameraModel(name, 1280, 720, K, np.array([-0.12, 0.05, 0.001, -0.0005, 0.0]), R, t)


def _views(a: CameraModel, b: CameraModel, n_views: int = 4, noise_px: float = 0.0, seed: int = 0):
    """Matched points of a few board-like point clouds in front of both cameras."""
    rng = np.random.default_rng(seed)
    pairs = []
    for _ in range(n_views):
        pts = rng.uniform([-0.6, -0.4, 3.2], [0.6, 0.4, 4.8], size=(40, 3))
        pa, _ = a.project(pts)
        pb, _ = b.project(pts)
        pairs.append((pa + rng.normal(0, noise_px, pa.shape), pb + rng.normal(0, noise_px, pb.shape)))
    return pairs


@pytest.mark.parametrize("offset", [(0.5, 0.0, 0.0), (0.0, -0.5, 0.0), (0.35, -0.35, 0.0)], ids=["horizontal", "vertical", "diagonal"])
def test_an_exact_pair_has_no_epipolar_error_whatever_its_direction(offset):
    a = _camera("a", (0.0, 0.0, 0.0))
    b = _camera("b", offset)
    e = epipolar_error(a, b, _views(a, b))
    assert e["rms_px"] < 0.01 and e["max_px"] < 0.05, e  # a perfect calibration: the lines meet exactly


@pytest.mark.parametrize("offset", [(0.5, 0.0, 0.0), (0.0, -0.5, 0.0)], ids=["horizontal", "vertical"])
def test_the_error_is_the_noise_across_the_lines(offset):
    a = _camera("a", (0.0, 0.0, 0.0))
    b = _camera("b", offset)
    e = epipolar_error(a, b, _views(a, b, n_views=10, noise_px=0.5, seed=3))
    # half a pixel of noise in each image on both axes: sqrt(2) x 0.5 px across the lines
    assert 0.55 < e["rms_px"] < 0.9, e
