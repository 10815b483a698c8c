"""The geometry check of the pipeline without training (torch; frames come from the caller).

On a frame set with ground truth (the simulator's), with the oracle backbone in metric scale and
the affine transform bypassed, it measures:
- depth: the initial depth splatted into a target camera against its ground-truth depth (the
  fraction within 2 %), on the pixels both sources see;
- colour: the sources' colours warped into the target with that depth against the target image
  (PSNR), on the same pixels;
- renderer: a Gaussian plane built on the target's ground-truth depth and colours at the fine size,
  rendered at the output size, against the target image at the output size (PSNR).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from calibration.camera import CameraModel
from inference.config import ModelConfig, Sizes
from inference.metrics import covisibility, depth_agreement, psnr
from inference.model.geometry import relative_pose
from inference.model.pipeline import build_model
from inference.model.splat import PlaneSplatter, plane_from_depth
from inference.model.stage2 import RefinedDepth
from inference.runtime.preprocess import InputPreparer, intrinsics, pinhole


@dataclass
class View:
    camera: CameraModel
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres


@dataclass
class GeometryFigures:
    depth_within_2pct: float  # fraction of covisible target pixels
    colour_psnr_db: float  # warped colour vs target image, covisible pixels
    render_psnr_db: float  # Gaussian plane of ground truth vs target image at the output size
    covisible_fraction: float  # fraction of target pixels both sources see
    depth_median_rel_error: float

    def to_dict(self) -> dict:
        return asdict(self)


def evaluate_geometry(sizes: Sizes, left: View, right: View, target_fine: View, target_output: View, overrides: dict | None = None) -> GeometryFigures:
    """`target_fine` and `target_output` are pinhole views of one target camera at the fine and
    output sizes (render them with `inference.runtime.preprocess.pinhole(camera, size)`). `overrides`
    ("section.field": value) change the pipeline's configuration, e.g. {"depth_init.radius": 1}."""
    cfg = ModelConfig.for_backbone("oracle", sizes, **(overrides or {}))
    cfg.backbone.oracle_scale = "metric"
    cfg.stage1.affine = "bypass"
    model = build_model(cfg)
    prepare = InputPreparer(sizes, needs_depth=True)
    feeds = prepare(left.rgb, right.rgb, left.camera, right.camera, target_output.camera, left.depth, right.depth)
    inputs = [torch.from_numpy(feeds[n]) for n in model.input_names]
    with torch.no_grad():
        out = model.run(*inputs)
        init = out["initial_depth"].depth
        refined = out["refined"]
        # Colour warped with the initial depth itself (the refinement is untrained here).
        at_init = RefinedDepth(init, refined.probabilities, refined.phi, refined.features_left, refined.features_right)
        s = sizes.fine
        target_K_fine = torch.from_numpy(intrinsics(target_fine.camera, s))
        colours = model.colour_init(inputs[0], inputs[1], inputs[2], inputs[3], *_target_to_sources(inputs), target_K_fine, at_init)
    depth = init[0, 0].numpy()
    colour = colours.colour[0].permute(1, 2, 0).numpy()

    gt_depth = target_fine.depth
    mask = covisibility(target_fine.camera, gt_depth, [(left.camera, left.depth), (right.camera, right.depth)])
    rel = np.abs(depth[mask] - gt_depth[mask]) / gt_depth[mask]

    # Renderer: ground-truth Gaussian plane at the fine size, rendered at the output size.
    K_fine = torch.from_numpy(intrinsics(target_fine.camera, s))
    plane = plane_from_depth(
        torch.from_numpy(gt_depth)[None, None], torch.from_numpy(target_fine.rgb.astype(np.float32) / 255.0).permute(2, 0, 1)[None], K_fine
    )
    splatter = PlaneSplatter(cfg.splat, s, sizes.output)
    with torch.no_grad():
        rendered = splatter(plane, torch.from_numpy(intrinsics(target_output.camera, sizes.output)))
    image = rendered.image[0].permute(1, 2, 0).numpy()
    truth_out = target_output.rgb.astype(np.float32) / 255.0
    return GeometryFigures(
        depth_within_2pct=depth_agreement(depth, gt_depth, mask, 0.02),
        colour_psnr_db=psnr(colour, target_fine.rgb.astype(np.float32) / 255.0, mask),
        render_psnr_db=psnr(image, truth_out, target_output.depth > 0),
        covisible_fraction=float(mask.mean()),
        depth_median_rel_error=float(np.median(rel)) if rel.size else float("nan"),
    )


def _target_to_sources(inputs: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    left_pose, right_pose, target_pose = inputs[4], inputs[5], inputs[7]
    return relative_pose(left_pose, target_pose), relative_pose(right_pose, target_pose)


def target_views(camera: CameraModel, sizes: Sizes) -> tuple[CameraModel, CameraModel]:
    """The pinhole cameras whose renders `evaluate_geometry` compares with (fine, output)."""
    return pinhole(camera, sizes.fine), pinhole(camera, sizes.output)
