"""benchmarks/depth_chain.py's per-stage figures on made-up depth maps: a person whose inside is right
and whose edge shows the wall counts as farther at the edge only; the wall through its middle counts
inside and as behind."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import depth_chain  # noqa: E402


def scene():
    truth = np.full((20, 20), 4.0, dtype=np.float32)  # the wall
    mask = np.zeros((20, 20), dtype=bool)
    mask[4:16, 6:14] = True  # the person, 12 x 8 pixels
    truth[mask] = 2.0
    return truth, mask


def test_the_wall_at_the_silhouette_is_farther_but_not_inside():
    truth, mask = scene()
    depth = truth.copy()
    edge = mask & ~depth_chain.eroded(mask, 1)
    depth[edge] = 4.0  # the wall shows through on the silhouette's outer ring
    chain = depth_chain.Chain()
    chain.add(torch.from_numpy(depth)[None, None], truth, mask)
    r = chain.summary()
    assert r["person_farther"] == round(edge.sum() / mask.sum(), 5) and r["person_behind"] == r["person_farther"]
    assert r["interior_farther"] == 0.0 and r["person_nearer"] == 0.0


def test_the_wall_through_the_middle_is_farther_inside_and_behind_while_a_small_error_is_not_behind():
    truth, mask = scene()
    depth = truth.copy()
    depth[9:11, 9:11] = 4.0  # a hole in the person's middle: the wall
    depth[4, 6:14] = 2.2  # the top row 10 % too far: farther than the 6 % range, not behind (20 %)
    chain = depth_chain.Chain()
    chain.add(torch.from_numpy(depth)[None, None], truth, mask)
    r = chain.summary()
    assert r["person_farther"] == round(12 / 96, 5) and r["person_behind"] == round(4 / 96, 5)
    inside = depth_chain.eroded(mask, 2)
    assert r["interior_farther"] == round(4 / inside.sum(), 5)


def test_erosion_steps_in_from_the_edge_of_the_image_too():
    m = np.ones((6, 6), dtype=bool)
    assert depth_chain.eroded(m, 1).sum() == 16 and depth_chain.eroded(m, 3).sum() == 0
