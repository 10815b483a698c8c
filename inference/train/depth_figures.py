"""Stage 1's depth against ground truth (simulator takes), the figures both training's monitoring and
`rig model eval` report: AbsRel on the pixels both sources see, on those only one sees, within a mask,
and its split into scale and shape."""
from __future__ import annotations

from typing import Optional

import numpy as np

from inference.metrics import covisibility
from inference.model.geometry import relative_pose, transform_points
from inference.runtime.preprocess import pinhole
from inference.train.data import FrameSource


def stage1_depths(affine, L, R, source: FrameSource) -> dict:
    """Stage 1's depth (coarse) in each source's own camera."""
    # The poses follow the point maps (the views may have stayed on the CPU while the model runs on a GPU).
    dev = affine.points_right.device
    to_right = relative_pose(R.poses.to(dev), L.poses.to(dev))
    return {source.left: affine.points_left[0, 2].detach().float().cpu().numpy(),
            source.right: transform_points(to_right, affine.points_right)[0, 2].detach().float().cpu().numpy()}


def depth_ratios(affine, L, R, fs, source: FrameSource, gt_coarse: dict, coarse: tuple[int, int], masks: Optional[dict] = None,
                  single: bool = False) -> list[np.ndarray]:
    """Stage 1's depth over ground truth in each source (coarse, pinhole), on the pixels the other
    source also sees (`single`: on those with ground truth that it does not see; and, given `masks`
    per source at the coarse size, that lie in the mask). One array per source that has such pixels."""
    cams = {c: pinhole(fs.cameras[c], coarse) for c in (source.left, source.right)}
    pred = stage1_depths(affine, L, R, source)
    out = []
    for c, other in ((source.left, source.right), (source.right, source.left)):
        pick = covisibility(cams[c], gt_coarse[c], [(cams[other], gt_coarse[other])])
        if single:
            pick = ~pick & (gt_coarse[c] > 0)
        if masks is not None:
            pick = pick & masks[c]
        if pick.any():
            out.append(pred[c][pick] / gt_coarse[c][pick])
    return out


def stage1_absrel(affine, L, R, fs, source: FrameSource, gt_coarse: dict, coarse: tuple[int, int], masks: Optional[dict] = None,
                  single: bool = False) -> list[float]:
    """AbsRel of stage 1's depth in each source against ground truth (see depth_ratios for the pixels)."""
    return [float(np.mean(np.abs(r - 1.0))) for r in depth_ratios(affine, L, R, fs, source, gt_coarse, coarse, masks, single)]


def stage1_scale_split(affine, L, R, fs, source: FrameSource, gt_coarse: dict, coarse: tuple[int, int]) -> list[tuple[float, float]]:
    """Stage 1's depth error split into its scale and its shape, per source: the median of depth over
    ground truth (1: the metric scale is right) and the AbsRel left once the depth is divided by it."""
    out = []
    for r in depth_ratios(affine, L, R, fs, source, gt_coarse, coarse):
        med = float(np.median(r))
        out.append((med, float(np.mean(np.abs(r / med - 1.0)))))
    return out
