"""The two training stages as modules whose forward returns the loss (what DDP wraps).

A `Batch` holds B frame sets: the two sources at the fine size and S supervision cameras per set
at the sizes the stage compares at. Supervision cameras are the targets; the model never sees them.

- Stage 1 (`Stage1Loss`): backbone + affine transform. The metric point maps of both sources, each
  point coloured by its source pixel and weighted by its opacity, are splatted into every
  supervision camera at the coarse size (inference.train.point_splat) and compared with its image
  (L = beta_l1 L1 + beta_ssim (1 - SSIM)); plus gamma times the symmetric 6-D Chamfer distance
  between the two views' (xyz, rgb) sets. A point counts in the Chamfer only where it projects
  inside the other source's image: parts of the scene one source cannot see have no partner.
  With `mvs_depth` > 0, plus that weight times the mean |log z - log z_mvs| of both sources' depth
  against multi-view stereo depth where it is trusted (`SourceDepth`, inference.train.multiview_depth).
  With the supervised recipe, plus the depth terms against the take's ground-truth depth on every
  pixel it covers (inference.train.depth_supervision; `Batch.truth_depth`).
- Stage 2 (`Stage2Loss`): stage 1 frozen; the whole pipeline renders each supervision camera;
  lambda_fine L(C, I_fine) + lambda_render L(render, I).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.errors import InferenceError
from inference.model.backbone import confidence_to_opacity
from inference.model.geometry import in_image, project, relative_pose, resize_intrinsics, transform_points
from inference.model.pipeline import SplatSAP, stage1_inputs
from inference.train.chamfer import chamfer_6d
from inference.train.config import LossWeights
from inference.train.data import Views
from inference.train.depth_supervision import DepthSupervision, TruthDepth, depth_terms
from inference.train.losses import masked_rendering_loss, point_colour_set, rendering_loss
from inference.train.point_splat import PointSplatConfig, splat_points


@dataclass
class SourceDepth:
    """Multi-view stereo depth of both sources at the coarse size, (B, H, W) each, and where it is trusted."""

    left: torch.Tensor
    left_mask: torch.Tensor
    right: torch.Tensor
    right_mask: torch.Tensor

    def to(self, device, non_blocking: bool = False) -> "SourceDepth":
        return SourceDepth(*(t.to(device, non_blocking=non_blocking) for t in (self.left, self.left_mask, self.right, self.right_mask)))

    def pin_memory(self) -> "SourceDepth":
        return SourceDepth(*(t.pin_memory() for t in (self.left, self.left_mask, self.right, self.right_mask)))


def log_depth_error(pred: torch.Tensor, depth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """|log pred - log depth| averaged over each item's masked pixels (0 where none is), then over the
    batch (B, H, W): per item, so that data-parallel processes, each averaging its share of the
    batch, step as one process on the whole batch."""
    m = mask.to(pred.dtype).flatten(1)
    e = (torch.log(pred.clamp(min=1e-4)) - torch.log(depth.clamp(min=1e-4))).abs().flatten(1)
    return ((e * m).sum(1) / m.sum(1).clamp(min=1.0)).mean()


def source_depths_of(points_left: torch.Tensor, points_right: torch.Tensor, left: Views, right: Views) -> tuple[torch.Tensor, torch.Tensor]:
    """Each source's stage-1 depth (B, H, W) in its own camera, from point maps in the left frame."""
    z_right = transform_points(relative_pose(right.poses, left.poses), points_right)[:, 2]
    return points_left[:, 2], z_right


def truth_depth_terms(affine, conf_left: torch.Tensor, conf_right: torch.Tensor, left: Views, right: Views,
                      truth: TruthDepth, w: DepthSupervision) -> tuple[torch.Tensor, dict[str, float]]:
    """The supervised recipe's depth loss of both sources against ground truth, and its parts."""
    z_left, z_right = source_depths_of(affine.points_left, affine.points_right, left, right)
    conf = [conf_left[:, 0], conf_right[:, 0]]
    terms = depth_terms([z_left, z_right], [truth.left, truth.right], [truth.left_valid, truth.right_valid], conf, w.confidence_alpha,
                        [truth.left_person, truth.right_person], w.person)
    return terms.total(w), {"depth_si": float(terms.scale_invariant.detach()), "depth_metric": float(terms.metric.detach())}


def source_depth_error(points_left: torch.Tensor, points_right: torch.Tensor, left: Views, right: Views, sd: SourceDepth) -> torch.Tensor:
    """Both sources' stage-1 depth (point maps in the left frame) against their multi-view stereo
    depth (log_depth_error, averaged)."""
    z_right = transform_points(relative_pose(right.poses, left.poses), points_right)[:, 2]
    return 0.5 * (log_depth_error(points_left[:, 2], sd.left, sd.left_mask)
                  + log_depth_error(z_right, sd.right, sd.right_mask))


@dataclass
class ViewTruth:
    """The supervision views' ground-truth depth at the fine size (B*S, H, W), where it holds, and their person masks."""

    depth: torch.Tensor
    valid: torch.Tensor
    person: torch.Tensor

    def to(self, device, non_blocking: bool = False) -> "ViewTruth":
        return ViewTruth(*(t.to(device, non_blocking=non_blocking) for t in (self.depth, self.valid, self.person)))


def view_depth_error(depth: torch.Tensor, truth: ViewTruth, person: float) -> torch.Tensor:
    """The refined depth (B*S, 1, H, W) against the views' truth: log_depth_error over the pixels the
    truth covers, plus `person` times the same over the person pixels (0 for a view without people)."""
    d = depth[:, 0]
    loss = log_depth_error(d, truth.depth, truth.valid)
    if person > 0:
        loss = loss + person * log_depth_error(d, truth.depth, truth.valid & truth.person)
    return loss


@dataclass
class Batch:
    left: Views  # (B, ...) at the fine size
    right: Views
    targets: Views  # (B*S, ...) at the stage's comparison size (coarse for stage 1, output for stage 2)
    targets_fine: Views | None  # (B*S, ...) at the fine size (stage 2)
    per_set: int  # S
    source_depth: SourceDepth | None = None  # stage 1: multi-view stereo depth of the sources (TrainConfig.mvs_depth)
    truth_depth: TruthDepth | None = None  # the supervised recipe: the sources' ground-truth depth at the coarse size
    view_truth: ViewTruth | None = None  # stage 2 with view_depth: the supervision views' ground-truth depth, fine size

    def __len__(self) -> int:
        return self.left.images.shape[0]

    def _map(self, f) -> "Batch":
        return Batch(f(self.left), f(self.right), f(self.targets), None if self.targets_fine is None else f(self.targets_fine),
                     self.per_set, None if self.source_depth is None else f(self.source_depth),
                     None if self.truth_depth is None else f(self.truth_depth),
                     None if self.view_truth is None else f(self.view_truth))

    def to(self, device, non_blocking: bool = False) -> "Batch":
        """The batch on the model's device (built on the CPU, by the loader or its workers)."""
        return self._map(lambda x: x.to(device, non_blocking=non_blocking))

    def pin_memory(self) -> "Batch":
        return self._map(lambda x: x.pin_memory())


def _expand(x: torch.Tensor, s: int) -> torch.Tensor:
    """(B, ...) -> (B*S, ...), each item repeated S times in place."""
    return x.repeat_interleave(s, dim=0)


def stage1_forward(model: SplatSAP, left: Views, right: Views):
    """Point maps and affine transform as the pipeline computes them (coarse images and intrinsics)."""
    (left_c, right_c, kl, kr), backbone_inputs = stage1_inputs(model, left.images, right.images, left.K, right.K)
    r2l = relative_pose(left.poses, right.poses)
    pm = model.point_init(*backbone_inputs, r2l)
    affine = model.affine_transform(pm, kl, kr, r2l, left_c, right_c)
    return left_c, right_c, kl, kr, r2l, pm, affine


def _overlap(points: torch.Tensor, to_other: torch.Tensor, K: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    uv, z = project(transform_points(to_other, points), K)
    return in_image(uv, z, size[0], size[1])


class Stage1Loss(nn.Module):
    def __init__(self, model: SplatSAP, weights: LossWeights, point_radius: int = 1, render_scales: tuple[int, ...] = (1,),
                 plane_render: float = 0.0, mvs_depth: float = 0.0, depth_supervision: DepthSupervision | None = None,
                 render: float = 1.0):
        super().__init__()
        self.depth_supervision = depth_supervision  # the supervised recipe's weights (None: self-supervised)
        self.render = render  # weight of the point maps' rendering loss (0: not rendered, depth terms alone)
        self.plane_render = plane_render
        self.mvs_depth = mvs_depth
        self.model = model
        self.w = weights
        self.splat = PointSplatConfig(radius=point_radius)
        self.scales = tuple(render_scales)
        self.gamma = weights.gamma  # the trainer sets it per step (TrainConfig.gamma_at)

    def forward(self, batch: Batch) -> tuple[torch.Tensor, dict[str, float], dict]:
        m = self.model
        cw, ch = m.cfg.sizes.coarse
        left_c, right_c, kl, kr, r2l, pm, affine = stage1_forward(m, batch.left, batch.right)
        b = left_c.shape[0]
        n = batch.per_set
        pts = torch.cat([affine.points_left.flatten(2), affine.points_right.flatten(2)], dim=2)  # (B, 3, 2HW), left frame
        cols = torch.cat([left_c.flatten(2), right_c.flatten(2)], dim=2)
        ops = torch.cat([confidence_to_opacity(pm.conf_left).flatten(2), confidence_to_opacity(pm.conf_right).flatten(2)], dim=2)
        to_target = relative_pose(batch.targets.poses, _expand(batch.left.poses, n))
        args = (_expand(pts, n), _expand(cols, n), _expand(ops, n), to_target)
        render = None
        l_render = 0.0
        for k in self.scales if self.render > 0 else ():
            size = (cw // k, ch // k)
            truth = batch.targets.images if k == 1 else F.avg_pool2d(batch.targets.images, k)
            r = splat_points(*args, resize_intrinsics(batch.targets.K, (cw, ch), size), size, self.splat)
            l_render = l_render + rendering_loss(r.image, truth, self.w.beta_l1, self.w.beta_ssim) / len(self.scales)
            if k == self.scales[0]:
                render, render_truth = r, truth
        loss = self.render * l_render
        l_planes = None
        if self.plane_render > 0 and pm.planes is not None:
            l_planes = self._planes(pm.planes, affine.scale, left_c, right_c, batch, to_target, (cw, ch))
            loss = loss + self.plane_render * l_planes
        l_mvs = None
        if self.mvs_depth > 0 and batch.source_depth is not None:
            l_mvs = source_depth_error(affine.points_left, affine.points_right, batch.left, batch.right, batch.source_depth)
            loss = loss + self.mvs_depth * l_mvs
        truth_parts = {}
        if self.depth_supervision is not None and batch.truth_depth is not None:
            l_truth, truth_parts = truth_depth_terms(affine, pm.conf_left, pm.conf_right, batch.left, batch.right,
                                                     batch.truth_depth, self.depth_supervision)
            loss = loss + l_truth
        # Chamfer on the pairs both sources can see (in the left frame; the right camera is r2l^-1).
        cd = None
        if self.gamma > 0:
            with torch.no_grad():
                l2r = relative_pose(batch.right.poses, batch.left.poses)
                w_l = _overlap(affine.points_left, l2r, kr, (cw, ch)).reshape(b, -1)
                w_r = _overlap(affine.points_right, torch.eye(4, dtype=kl.dtype, device=kl.device).expand(b, 4, 4), kl, (cw, ch)).reshape(b, -1)
                w_l = (w_l > 0.5).to(kl.dtype)
                w_r = (w_r > 0.5).to(kl.dtype)
            cd = chamfer_6d(point_colour_set(affine.points_left, left_c), point_colour_set(affine.points_right, right_c), w_l, w_r)
            loss = loss + self.gamma * cd
        with torch.no_grad():
            seen = {} if render is None else {"psnr": float(-10.0 * torch.log10(((render.image - render_truth) ** 2).mean().clamp(min=1e-10))),
                                              "coverage": float(render.alpha.mean())}
            metrics = {"loss": float(loss), "render": float(l_render), "gamma": self.gamma,
                       **({"chamfer": float(cd)} if cd is not None else {}),
                       **({"planes": float(l_planes)} if l_planes is not None else {}),
                       **({"mvs": float(l_mvs)} if l_mvs is not None else {}), **truth_parts,
                       **seen, "scale": float(affine.scale.mean())}
        check_finite(1, metrics["loss"])
        return loss, metrics, {} if render is None else {"render": render.image.detach(), "truth": render_truth}


    def _planes(self, planes, scale, left_c, right_c, batch: Batch, to_target, coarse: tuple[int, int]) -> torch.Tensor:
        """Rendering loss of the backbone's depth distribution at its volume size (see TrainConfig.plane_render)."""
        b, d, _, h, w = planes.points_left.shape
        n = batch.per_set
        s = scale.reshape(b, 1, 3, 1, 1)
        pts = torch.cat([(planes.points_left * s).permute(0, 2, 1, 3, 4).reshape(b, 3, -1),
                         (planes.points_right * s).permute(0, 2, 1, 3, 4).reshape(b, 3, -1)], dim=2)
        cols = [F.adaptive_avg_pool2d(img, (h, w))[:, :, None].expand(b, 3, d, h, w).reshape(b, 3, -1) for img in (left_c, right_c)]
        ops = torch.cat([planes.prob_left.reshape(b, -1), planes.prob_right.reshape(b, -1)], dim=1)[:, None]
        size = (w, h)
        K = resize_intrinsics(batch.targets.K, coarse, size)
        truth = F.adaptive_avg_pool2d(batch.targets.images, (h, w))
        r = splat_points(_expand(pts, n), _expand(torch.cat(cols, dim=2), n), _expand(ops, n), to_target, K, size, self.splat)
        return rendering_loss(r.image, truth, self.w.beta_l1, self.w.beta_ssim)


class Stage2Loss(nn.Module):
    def __init__(self, model: SplatSAP, weights: LossWeights, mvs_depth: float = 0.0, depth_supervision: DepthSupervision | None = None,
                 view_depth: float = 0.0, person: float = 0.0, render_person: float = 0.0):
        super().__init__()
        self.render_person = render_person  # TrainConfig.render_person: the rendering losses again on the people
        # TrainConfig.view_depth: the refined depth of the views against their truth (person: its person weight).
        self.view_depth = view_depth
        self.person = person
        # Where stage 2 trains stage 1 too, the supervised recipe's depth terms keep holding it (as the MVS term does).
        self.depth_supervision = depth_supervision
        self.model = model
        self.w = weights
        self.mvs_depth = mvs_depth  # where stage 2 trains stage 1 too: its depth stays tied to the sources' MVS depth

    def forward(self, batch: Batch) -> tuple[torch.Tensor, dict[str, float], dict]:
        m = self.model
        n = batch.per_set
        L, R, T = batch.left, batch.right, batch.targets
        out = m.run(_expand(L.images, n), _expand(R.images, n), _expand(L.K, n), _expand(R.K, n),
                    _expand(L.poses, n), _expand(R.poses, n), T.K, T.poses)
        colour = out["colours"].colour
        l_fine = rendering_loss(colour, batch.targets_fine.images, self.w.beta_l1, self.w.beta_ssim)
        l_render = rendering_loss(out["image"], T.images, self.w.beta_l1, self.w.beta_ssim)
        loss = self.w.lambda_fine * l_fine + self.w.lambda_render * l_render
        l_mvs = None
        if self.mvs_depth > 0 and batch.source_depth is not None:
            # The sets of a step repeat per view (_expand): their first copies are the batch's sets.
            a = out["affine"]
            l_mvs = source_depth_error(a.points_left[::n], a.points_right[::n], L, R, batch.source_depth)
            loss = loss + self.mvs_depth * l_mvs
        truth_parts = {}
        if self.depth_supervision is not None and batch.truth_depth is not None:
            a, p = out["affine"], out["point_maps"]
            l_truth, truth_parts = truth_depth_terms(_Firsts(a, n), p.conf_left[::n], p.conf_right[::n], L, R,
                                                     batch.truth_depth, self.depth_supervision)
            loss = loss + l_truth
        l_people = None
        if self.render_person > 0 and batch.view_truth is not None:
            fine_mask = batch.view_truth.person
            out_mask = F.interpolate(fine_mask[:, None].to(colour.dtype), size=out["image"].shape[-2:], mode="nearest")[:, 0] > 0.5
            l_people = (self.w.lambda_fine * masked_rendering_loss(colour, batch.targets_fine.images, fine_mask, self.w.beta_l1, self.w.beta_ssim)
                        + self.w.lambda_render * masked_rendering_loss(out["image"], T.images, out_mask, self.w.beta_l1, self.w.beta_ssim))
            loss = loss + self.render_person * l_people
        l_view = None
        if self.view_depth > 0 and batch.view_truth is not None:
            l_view = view_depth_error(out["refined"].depth, batch.view_truth, self.person)
            loss = loss + self.view_depth * l_view
        with torch.no_grad():
            mse = ((out["image"] - T.images) ** 2).mean()
            metrics = {"loss": float(loss), "fine": float(l_fine), "render": float(l_render),
                       **({"mvs": float(l_mvs)} if l_mvs is not None else {}), **truth_parts,
                       **({"view_depth": float(l_view)} if l_view is not None else {}),
                       **({"render_person": float(l_people)} if l_people is not None else {}),
                       "psnr": float(-10.0 * torch.log10(mse.clamp(min=1e-10)))}
        check_finite(2, metrics["loss"])
        return loss, metrics, {"render": out["image"].detach(), "truth": T.images}


class TrainingDiverged(InferenceError):
    """The loss or the weights are no longer finite numbers: a failure during the work (exit 1)."""

    exit_code = 1


def check_finite(stage: int, loss: float) -> None:
    """Before the backward pass: a loss that is not a finite number stops the run (its gradients
    would be NaN everywhere, and torch's backward of some sampling ops crashed the process on
    them, a segmentation fault that lost the step's figures)."""
    if not math.isfinite(loss):
        raise TrainingDiverged(f"training diverged: the stage-{stage} loss is {loss} (the weights are no longer finite; a learning "
                               "rate too high?); the last checkpoint is kept: lower the rate in --config and resume or start again")


class _Firsts:
    """The point maps of a stage-2 step's frame sets: their first copies (the sets repeat per view)."""

    def __init__(self, affine, n: int):
        self.points_left = affine.points_left[::n]
        self.points_right = affine.points_right[::n]
