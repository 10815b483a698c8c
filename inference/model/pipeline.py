"""The full Splat-SAP pipeline as one module, with per-stage timing hooks.

Inputs (batch B; fine size (Wf, Hf), coarse (Wc, Hc), output (Wo, Ho) from the config):
    left_image, right_image  (B, 3, Hf, Wf) RGB in [0, 1], undistorted (pinhole)
    left_K, right_K          (B, 3, 3) intrinsics of those images
    left_pose, right_pose    (B, 4, 4) world-to-camera
    target_K                 (B, 3, 3) intrinsics of the novel view at the output size
    target_pose              (B, 4, 4) world-to-camera of the novel view
    left_depth, right_depth  (B, 1, Hc, Wc) ground-truth depth, oracle backbone only
Outputs: image (B, 3, Ho, Wo) in [0, 1] and depth (B, 1, Ho, Wo) in metres (0 where empty).

Internally every pose is taken relative to the left camera (the backbone's frame), which keeps
float32 coordinates small whatever the world frame is.
"""
from __future__ import annotations

import contextlib
import time
from typing import Callable, ContextManager

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.config import STAGES, ModelConfig
from inference.model.backbone import Backbone, OracleBackbone, TinyBackbone, confidence_to_opacity
from inference.model.depth_init import DepthInit
from inference.model.geometry import relative_pose, resize_intrinsics
from inference.model.mast3r import MASt3RBackbone
from inference.model.splat import PlaneSplatter
from inference.model.stage1 import AffineTransform
from inference.model.stereo_backbone import StereoBackbone
from inference.model.stage2 import ColourInit, DepthRefine, GaussianPlane

INPUT_NAMES = ("left_image", "right_image", "left_K", "right_K", "left_pose", "right_pose", "target_K", "target_pose")
DEPTH_INPUT_NAMES = ("left_depth", "right_depth")
OUTPUT_NAMES = ("image", "depth")
# What the target-dependent part (depth_init onwards) reads from stage 1 (point_init +
# affine_transform): the affine-transformed point maps and their splatting opacities. The ONNX
# export cuts the graph at these tensors (inference/export.py, the stage1 and view parts).
STAGE1_OUTPUT_NAMES = ("stage1_points_left", "stage1_points_right", "stage1_opacity_left", "stage1_opacity_right")


BACKBONES = {"tiny": TinyBackbone, "oracle": OracleBackbone, "stereo": StereoBackbone, "mast3r": MASt3RBackbone}


def build_backbone(cfg, coarse_size: tuple[int, int]) -> Backbone:
    return BACKBONES[cfg.kind](cfg, coarse_size)


def stage1_inputs(model: "SplatSAP", left_image, right_image, left_K, right_K):
    """What stage 1 reads of the fine source images: the coarse images and intrinsics (the affine
    transform's), and the images and intrinsics the backbone reads (the same, or larger where the
    backbone reads them at a multiple of the coarse size)."""
    s = model.cfg.sizes
    cw, ch = s.coarse
    left_c = F.interpolate(left_image, size=(ch, cw), mode="bilinear", align_corners=False)
    right_c = F.interpolate(right_image, size=(ch, cw), mode="bilinear", align_corners=False)
    left_K_c = resize_intrinsics(left_K, s.fine, s.coarse)
    right_K_c = resize_intrinsics(right_K, s.fine, s.coarse)
    k = model.point_init.input_scale
    size = (cw * k, ch * k)
    if size == s.coarse:
        backbone = (left_c, right_c, left_K_c, right_K_c)
    elif size == s.fine:
        backbone = (left_image, right_image, left_K, right_K)
    else:
        backbone = (F.interpolate(left_image, size=size[::-1], mode="bilinear", align_corners=False),
                    F.interpolate(right_image, size=size[::-1], mode="bilinear", align_corners=False),
                    resize_intrinsics(left_K, s.fine, size), resize_intrinsics(right_K, s.fine, size))
    return (left_c, right_c, left_K_c, right_K_c), backbone


class StageTimer:
    """Wall-clock milliseconds per stage; synchronises CUDA so that GPU work is counted where it runs."""

    def __init__(self):
        self.ms: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, stage: str):
        sync = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)
        sync()
        start = time.perf_counter()
        try:
            yield
        finally:
            sync()
            self.ms[stage] = self.ms.get(stage, 0.0) + (time.perf_counter() - start) * 1000.0


class SplatSAP(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        s = cfg.sizes
        # Attribute names are the paper's timing stages (inference.config.STAGES); the ONNX export
        # keeps them as name scopes, which is how the benchmark attributes ONNX Runtime's time.
        self.point_init = build_backbone(cfg.backbone, s.coarse)
        self.affine_transform = AffineTransform(cfg.stage1, self.point_init.token_dim, s.coarse)
        self.depth_init = DepthInit(cfg.depth_init, s.fine)
        self.depth_refine = DepthRefine(cfg.stage2, s.fine)
        self.colour_init = ColourInit(cfg.stage2, s.fine)
        self.gaussian_plane = GaussianPlane(cfg.stage2, s.fine)
        self.splatting = PlaneSplatter(cfg.splat, s.fine, s.output)
        self.stage_hook: Callable[[str], ContextManager] | None = None
        self.export_stage1 = False  # set by the ONNX export: forward also returns the stage-1 tensors

    @property
    def needs_depth(self) -> bool:
        return self.point_init.needs_depth

    @property
    def input_names(self) -> tuple[str, ...]:
        return INPUT_NAMES + (DEPTH_INPUT_NAMES if self.needs_depth else ())

    def _stage(self, name: str) -> ContextManager:
        return self.stage_hook(name) if self.stage_hook is not None else contextlib.nullcontext()

    def forward(self, left_image, right_image, left_K, right_K, left_pose, right_pose, target_K, target_pose, left_depth=None, right_depth=None):
        out = self.run(left_image, right_image, left_K, right_K, left_pose, right_pose, target_K, target_pose, left_depth, right_depth)
        if self.export_stage1:
            return (out["image"], out["depth"]) + tuple(out["stage1"][n] for n in STAGE1_OUTPUT_NAMES)
        return out["image"], out["depth"]

    def run(self, left_image, right_image, left_K, right_K, left_pose, right_pose, target_K, target_pose, left_depth=None, right_depth=None) -> dict:
        """The forward pass, returning every intermediate (for tests and training)."""
        pm, affine, stage1 = self.run_stage1(left_image, right_image, left_K, right_K, left_pose, right_pose, left_depth, right_depth)
        out = self.run_view(stage1, left_image, right_image, left_K, right_K, left_pose, right_pose, target_K, target_pose)
        return {**out, "point_maps": pm, "affine": affine,
                "stage1": stage1}  # the tensors depth_init reads from stage 1 (STAGE1_OUTPUT_NAMES)

    def run_stage1(self, left_image, right_image, left_K, right_K, left_pose, right_pose, left_depth=None, right_depth=None):
        """What does not depend on the viewpoint: (point maps, affine transform, the stage-1 tensors
        depth_init reads, named STAGE1_OUTPUT_NAMES). The export's stage1 part and the GPU runtime's
        first function compute this."""
        right_to_left = relative_pose(left_pose, right_pose)
        with self._stage("point_init"):
            (left_c, right_c, left_K_c, right_K_c), backbone_inputs = stage1_inputs(self, left_image, right_image, left_K, right_K)
            pm = self.point_init(*backbone_inputs, right_to_left, left_depth, right_depth)
        with self._stage("affine_transform"):
            affine = self.affine_transform(pm, left_K_c, right_K_c, right_to_left, left_c, right_c)
        with self._stage("depth_init"):
            stage1 = dict(zip(STAGE1_OUTPUT_NAMES, (affine.points_left, affine.points_right, confidence_to_opacity(pm.conf_left), confidence_to_opacity(pm.conf_right))))
        return pm, affine, stage1

    def run_view(self, stage1: dict, left_image, right_image, left_K, right_K, left_pose, right_pose, target_K, target_pose) -> dict:
        """The view at (target_K, target_pose) from stage 1's tensors: depth_init onwards."""
        s = self.cfg.sizes
        left_to_target = relative_pose(target_pose, left_pose)
        target_to_left = relative_pose(left_pose, target_pose)
        target_to_right = relative_pose(right_pose, target_pose)
        target_K_fine = resize_intrinsics(target_K, s.output, s.fine)
        with self._stage("depth_init"):
            init = self.depth_init(*(stage1[n] for n in STAGE1_OUTPUT_NAMES), left_to_target, target_K_fine)
        with self._stage("depth_refine"):
            refined = self.depth_refine(left_image, right_image, left_K, right_K, target_to_left, target_to_right, target_K_fine, init.depth)
        with self._stage("colour_init"):
            colours = self.colour_init(left_image, right_image, left_K, right_K, target_to_left, target_to_right, target_K_fine, refined)
        with self._stage("gaussian_plane"):
            plane = self.gaussian_plane(colours, refined.depth, target_K_fine)
        with self._stage("splatting"):
            rendered = self.splatting(plane, target_K)
        return {
            "image": rendered.image.clamp(0.0, 1.0),
            "depth": rendered.depth,
            "alpha": rendered.alpha,
            "initial_depth": init,
            "refined": refined,
            "colours": colours,
            "plane": plane,
        }

    def timed(self, *inputs) -> tuple[tuple[torch.Tensor, torch.Tensor], dict[str, float]]:
        """Run once and return the outputs and milliseconds per stage (plus 'total')."""
        timer = StageTimer()
        self.stage_hook = timer
        try:
            with timer("total"):
                outputs = self(*inputs)
        finally:
            self.stage_hook = None
        ms = {k: timer.ms.get(k, 0.0) for k in STAGES}
        ms["total"] = timer.ms["total"]
        return outputs, ms


def build_model(cfg: ModelConfig, seed: int | None = 0) -> SplatSAP:
    """A model with seeded initial weights (reproducible exports of untrained models)."""
    if seed is not None:
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            model = SplatSAP(cfg)
    else:
        model = SplatSAP(cfg)
    return model.eval()
