"""Geometry without training, on a simulator frame set (the acceptance of the model pipeline).

Oracle backbone in metric scale, affine transform bypassed, preview sizes (coarse 256x144, fine
512x288, output 640x360), sources 'left' and 'right' (60 degrees apart), each supervision camera
as the target:
- the initial depth splatted into the target agrees with its ground truth within 2 % on at least
  95 % of the pixels both sources see;
- the sources' colours warped with that depth match the target image at PSNR >= 25 dB there;
- the renderer fed the target's ground-truth depth and colours reproduces it at PSNR >= 30 dB.
"""
from __future__ import annotations

import pytest

from inference.config import Sizes
from inference.evaluate.geometry import View, evaluate_geometry, target_views


@pytest.mark.parametrize("target", ["sup1", "sup2", "sup3", "sup4"])
def test_geometry_on_simulator_frames(sim_frames, target):
    sizes = Sizes.preset("preview")
    rig = sim_frames.rig
    left = View(rig["left"], sim_frames.rgb["left"], sim_frames.depth["left"])
    right = View(rig["right"], sim_frames.rgb["right"], sim_frames.depth["right"])
    views = []
    for cam in target_views(rig[target], sizes):  # the target's pinhole at the fine and output sizes
        r = sim_frames.render(cam)
        views.append(View(cam, r.rgb, r.depth))
    fig = evaluate_geometry(sizes, left, right, *views)
    print(
        f"\n{target}: initial depth within 2 % on {100 * fig.depth_within_2pct:.1f} % of covisible pixels "
        f"(median error {100 * fig.depth_median_rel_error:.2f} %, covisible {100 * fig.covisible_fraction:.0f} % of the view); "
        f"warped colour PSNR {fig.colour_psnr_db:.2f} dB; ground-truth Gaussian plane render PSNR {fig.render_psnr_db:.2f} dB"
    )
    assert fig.covisible_fraction > 0.2
    assert fig.depth_within_2pct >= 0.95
    assert fig.colour_psnr_db >= 25.0
    assert fig.render_psnr_db >= 30.0
