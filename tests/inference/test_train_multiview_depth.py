"""The multi-view stereo teacher of stage 1 (inference.train.multiview_depth) on a simulator frame set.

Each source's depth from its two nearest supervision cameras, at the preview's coarse size: on the
pixels it trusts, it must agree with the simulator's ground truth (which only this test reads), and
it must trust a useful share of the view. With a neighbour's pose wrong, its peaks stop agreeing
and it must trust far fewer pixels (about half) instead of returning a wrong depth.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from inference.runtime.preprocess import pinhole
from inference.train.data import Preprocessor
from inference.train.multiview_depth import multiview_depth, nearest_cameras

SIZE = (256, 144)
NAMES = ["left", "sup1", "sup2", "sup3", "sup4", "right"]


@pytest.fixture(scope="module")
def coarse(sim_frames):
    pre = Preprocessor()
    rig = sim_frames.rig
    images = torch.stack([torch.from_numpy(pre.image(sim_frames.rgb[n], rig[n], SIZE)).permute(2, 0, 1) for n in NAMES])
    Ks = torch.stack([torch.from_numpy(pinhole(rig[n], SIZE).K.astype(np.float32)) for n in NAMES])
    poses = torch.stack([torch.from_numpy(rig[n].extrinsic.astype(np.float32)) for n in NAMES])
    truth = {n: pre.depth(sim_frames.depth[n], rig[n], SIZE) for n in ("left", "right")}
    baseline = float(np.linalg.norm(rig["left"].center - rig["right"].center))
    return images.float(), Ks, poses, truth, baseline


def _depth(coarse, ref: int, poses=None):
    images, Ks, true_poses, _, baseline = coarse
    poses = true_poses if poses is None else poses
    nb = nearest_cameras(true_poses, ref, [1, 2, 3, 4], 2)
    return nb, multiview_depth(images[ref], Ks[ref], poses[ref], images[nb], Ks[nb], poses[nb], 0.2 * baseline, 6.0 * baseline)


@pytest.mark.parametrize("ref", [0, 5])
def test_trusted_depth_agrees_with_ground_truth(coarse, ref):
    truth = coarse[3][NAMES[ref]]
    nb, (depth, mask) = _depth(coarse, ref)
    assert nb == ([1, 2] if ref == 0 else [4, 3])
    rel = (np.abs(depth.numpy() - truth) / truth)[mask.numpy()]
    share = float(mask.float().mean())
    print(f"\n{NAMES[ref]}: trusted {100 * share:.1f} % of the view, AbsRel {100 * rel.mean():.2f} %, median {100 * np.median(rel):.2f} %")
    assert share > 0.25
    assert np.median(rel) < 0.02
    assert rel.mean() < 0.08


def test_a_wrong_neighbour_pose_is_not_trusted(coarse):
    _, (_, mask) = _depth(coarse, 0)
    poses = coarse[2].clone()
    turn = torch.tensor([[np.cos(0.05), 0, np.sin(0.05)], [0, 1, 0], [-np.sin(0.05), 0, np.cos(0.05)]], dtype=poses.dtype)
    poses[2, :3, :3] = turn @ poses[2, :3, :3]  # sup2 turned by about 3 degrees
    _, (_, wrong) = _depth(coarse, 0, poses)
    print(f"\ntrusted: {100 * float(mask.float().mean()):.1f} % with the true poses, {100 * float(wrong.float().mean()):.1f} % with one turned")
    assert float(wrong.float().mean()) < 0.6 * float(mask.float().mean())


def test_bad_arguments_are_refused(coarse):
    images, Ks, poses, _, _ = coarse
    with pytest.raises(ValueError, match="neighbouring camera"):
        multiview_depth(images[0], Ks[0], poses[0], images[:0], Ks[:0], poses[:0], 1.0, 10.0)
    with pytest.raises(ValueError, match="near < far"):
        multiview_depth(images[0], Ks[0], poses[0], images[1:3], Ks[1:3], poses[1:3], 10.0, 1.0)
