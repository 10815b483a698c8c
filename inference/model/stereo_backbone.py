"""A calibrated plane-sweep stereo backbone: point maps a CPU can learn from scratch.

The paper's backbone is MASt3R, a pretrained ViT whose weights cannot be had here (no model hub),
and a ViT trained from scratch on a two-core machine does not learn stereo in the steps available.
This backbone uses what every rig has, its calibration: it sweeps D fronto-parallel planes through
each view (MVSNet's cost volume), so depth comes from matching features, not from a learned prior.

For each view i (left and right, batched) and its partner j:
- a small CNN gives features at 1/4 of the size it reads the images at: the coarse size, or a
  multiple of it (`stereo_input_scale`; 2 reads the fine images, so a volume cell is 2 coarse pixels
  wide, not 4); point maps, confidences and tokens are at the coarse size either way;
- for D depths d_k (uniform in inverse depth between `near` and `far`, in units of the baseline),
  the pixels of i at depth d_k are projected into j and j's features sampled there (4-D
  grid_sample, the D hypotheses folded into the batch);
- group-wise correlation, a small 3-D convolution over (depth, y, x) and a 2-D refinement that
  sees i's features give D logits per pixel; the soft-argmin over inverse depth gives the depth;
- the confidence (DUSt3R convention 1 + exp(x)) comes from the peak probability and the features;
- optionally (`stereo_cascade` hypotheses) a second sweep at the coarse size itself, around the
  volume's depth (`CoarseCascade`): the volume's cells are 4 coarse pixels wide, so thin and small
  things (a person's limbs, a box) take the depth of what lies behind them, and its depth is
  bilinearly upsampled across every edge.

Point maps are returned in the left camera's frame in units of the baseline (scale-free, as
MASt3R's are): stage 1's scaling S (initialised to the baseline) makes them metric. In training the
backbone also returns its whole depth distribution (`PlaneVolume`), which stage 1 renders. Tokens for
stage 1's attention and ConvGRU are the features and the probability volume pooled to the patch
grid.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.config import BackboneConfig
from inference.model.backbone import Backbone, PlaneVolume, PointMaps
from inference.model.geometry import (
    in_image,
    invert_pose,
    normalise_pixels,
    pixel_rays,
    project,
    resize_intrinsics,
    transform_points,
)


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.GroupNorm(4, cout), nn.ReLU())


class StereoBackbone(Backbone):
    def __init__(self, cfg: BackboneConfig, coarse_size: tuple[int, int]):
        super().__init__()
        self.cfg = cfg
        w, h = coarse_size
        p = cfg.patch
        self.coarse_size = (w, h)
        self.grid = (h // p, w // p)
        self.input_scale = cfg.stereo_input_scale
        self.input_size = (w * self.input_scale, h * self.input_scale)
        self.volume_size = (self.input_size[0] // 4, self.input_size[1] // 4)
        c = cfg.stereo_features
        d = cfg.stereo_depths
        self.features = nn.Sequential(_conv(3, 32, 2), _conv(32, 32), _conv(32, 48, 2), _conv(48, 48), nn.Conv2d(48, c, 1))
        self.groups = cfg.stereo_groups
        self.regularise = nn.Sequential(
            nn.Conv3d(self.groups + 1, 8, 3, padding=1), nn.ReLU(), nn.Conv3d(8, 8, 3, padding=1), nn.ReLU(), nn.Conv3d(8, 1, 3, padding=1)
        )
        self.refine = nn.Sequential(nn.Conv2d(d + c, 64, 3, padding=1), nn.ReLU(), nn.Conv2d(64, 64, 3, padding=1), nn.ReLU(), nn.Conv2d(64, d, 3, padding=1))
        nn.init.zeros_(self.refine[-1].weight)
        nn.init.zeros_(self.refine[-1].bias)
        self.confidence = nn.Sequential(nn.Conv2d(c + 2, 32, 3, padding=1), nn.ReLU(), nn.Conv2d(32, 1, 3, padding=1))
        nn.init.zeros_(self.confidence[-1].weight)
        nn.init.constant_(self.confidence[-1].bias, 3.0)  # opacity ~0.95 before training
        inv = torch.linspace(1.0 / cfg.stereo_near, 1.0 / cfg.stereo_far, d)
        self.register_buffer("inverse_depths", inv, persistent=False)
        self.token_dim = c + d
        self.cascade = CoarseCascade(cfg.stereo_cascade, cfg.stereo_cascade_range, c) if cfg.stereo_cascade else None

    def _sweep(self, feats, other_feats, K, other_K, to_other):
        """Logits (N, D, h, w) of the D depth planes of each reference view. Depths in baseline units;
        `to_other` maps reference-camera points (baseline units) into the other camera."""
        n, c, h, w = feats.shape
        d = self.inverse_depths.shape[0]
        rays = pixel_rays(K, w, h)  # (N, 3, h, w)
        depths = (1.0 / self.inverse_depths).reshape(1, d, 1, 1, 1)
        pts = (rays[:, None] * depths).reshape(n, d * 3, h, w).reshape(n, d, 3, h * w).permute(0, 2, 1, 3)  # (N, 3, D, hw)
        uv, z = project(transform_points(to_other, pts), other_K)  # (N, 2, D, hw)
        vis = in_image(uv, z, w, h).reshape(n, 1, d, h, w)
        grid = normalise_pixels(uv.reshape(n, 2, d * h, w), w, h)  # (N, D*h, w, 2)
        # Fold the D planes into the batch: sample the other view's features D times (4-D grid_sample).
        grid = grid.reshape(n, d, h, w, 2).reshape(n * d, h, w, 2)
        src = other_feats[:, None].expand(n, d, c, h, w).reshape(n * d, c, h, w)
        warped = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        warped = warped.reshape(n, d, self.groups, c // self.groups, h, w)
        ref = feats.reshape(n, 1, self.groups, c // self.groups, h, w)
        corr = (warped * ref).mean(dim=3).permute(0, 2, 1, 3, 4)  # (N, G, D, h, w)
        logits = self.regularise(torch.cat([corr, vis], dim=1))[:, 0]  # (N, D, h, w)
        return logits + self.refine(torch.cat([logits, feats], dim=1))

    def forward(self, left, right, left_K, right_K, right_to_left, left_depth=None, right_depth=None) -> PointMaps:
        """Images and intrinsics at `input_size` (the coarse size times `stereo_input_scale`); point
        maps, confidences and tokens at the coarse size."""
        b = left.shape[0]
        cw, ch = self.coarse_size
        vw, vh = self.volume_size
        baseline = torch.sqrt((right_to_left[:, :3, 3] ** 2).sum(-1)).clamp(min=1e-6)
        # The rig in baseline units: translations divided by the baseline.
        unit = torch.cat([torch.ones(b, 3, 3, dtype=left.dtype, device=left.device), (1.0 / baseline).reshape(b, 1, 1).expand(b, 3, 1)], dim=2)
        unit = torch.cat([unit, torch.ones(b, 1, 4, dtype=left.dtype, device=left.device)], dim=1)
        r2l = right_to_left * unit
        l2r = invert_pose(r2l)
        # Each image scaled before they are stacked: read at the fine size they are the images depth
        # refinement stacks and scales too, and the ONNX exporter would merge the two subgraphs into
        # one node of this stage, which the live split's view part must not hold.
        feats = self.features(torch.cat([left * 2.0 - 1.0, right * 2.0 - 1.0], dim=0))  # (2B, C, h, w)
        other = torch.cat([feats[b:], feats[:b]], dim=0)
        k_vol = resize_intrinsics(torch.cat([left_K, right_K], dim=0), self.input_size, (vw, vh))
        k_other = torch.cat([k_vol[b:], k_vol[:b]], dim=0)
        logits = self._sweep(feats, other, k_vol, k_other, torch.cat([l2r, r2l], dim=0))
        prob = torch.softmax(logits, dim=1)
        inv = (prob * self.inverse_depths.reshape(1, -1, 1, 1)).sum(dim=1, keepdim=True)
        peak = prob.max(dim=1, keepdim=True).values
        conf_logit = self.confidence(torch.cat([feats, peak, inv], dim=1))
        inv_c = F.interpolate(inv, size=(ch, cw), mode="bilinear", align_corners=False)
        conf_logit = F.interpolate(conf_logit, size=(ch, cw), mode="bilinear", align_corners=False)
        k_coarse = resize_intrinsics(torch.cat([left_K, right_K], dim=0), self.input_size, (cw, ch))
        if self.cascade is not None:
            images = torch.cat([left, right], dim=0)
            if self.input_scale != 1:
                images = F.interpolate(images, size=(ch, cw), mode="bilinear", align_corners=False)
            inv_c, conf_logit = self.cascade(images, feats, inv_c, conf_logit, k_coarse, torch.cat([l2r, r2l], dim=0))
        conf = 1.0 + torch.exp(conf_logit.clamp(max=20.0))
        pts = pixel_rays(k_coarse, cw, ch) / inv_c.clamp(min=1e-6)
        pts_l = pts[:b]
        pts_r = transform_points(r2l, pts[b:])
        p = self.cfg.patch
        tokens = F.avg_pool2d(torch.cat([feats, prob], dim=1), p * self.input_scale // 4).flatten(2).transpose(1, 2)  # (2B, h*w, C + D)
        planes = None
        if self.training:
            d = self.inverse_depths.shape[0]
            rays = pixel_rays(k_vol, vw, vh)  # (2B, 3, h, w)
            plane_pts = rays[:, None] / self.inverse_depths.reshape(1, d, 1, 1, 1)  # (2B, D, 3, h, w)
            right_in_left = transform_points(r2l, plane_pts[b:].permute(0, 2, 1, 3, 4)).permute(0, 2, 1, 3, 4)
            planes = PlaneVolume(plane_pts[:b], right_in_left, prob[:b], prob[b:])
        return PointMaps(pts_l, pts_r, conf[:b], conf[b:], tokens[:b], tokens[b:], self.grid, planes=planes)


class CoarseCascade(nn.Module):
    """The second sweep of a cascade (CasMVSNet) at the coarse size: K hypotheses around the
    volume's depth, inverse depth times exp(-delta_k) for K offsets delta_k evenly over +-range (log
    depth). Features of the image at full coarse resolution (with the volume's features upsampled)
    of the reference view are correlated with the other view's sampled at each hypothesis (4-D
    grid_sample, the hypotheses folded into the batch), a 3-D convolution over (hypothesis, y, x)
    and a 2-D one that sees the reference features give K logits, and the depth moves by the
    softmax-weighted offset. A residual confidence logit comes from the same features and the peak.
    The last layers start at zero: uniform weights over symmetric offsets move nothing, so a model
    trained without the cascade starts from what it computed."""

    def __init__(self, hypotheses: int, log_range: float, volume_features: int, features: int = 16, groups: int = 4):
        super().__init__()
        self.groups = groups
        self.image = nn.Sequential(_conv(3, 16), _conv(16, 16))
        self.features = nn.Sequential(_conv(16 + volume_features, 32), nn.Conv2d(32, features, 1))
        self.regularise = nn.Sequential(nn.Conv3d(groups + 1, 8, 3, padding=1), nn.ReLU(), nn.Conv3d(8, 1, 3, padding=1))
        self.refine = nn.Sequential(nn.Conv2d(hypotheses + features, 32, 3, padding=1), nn.ReLU(), nn.Conv2d(32, hypotheses, 3, padding=1))
        self.confidence = nn.Sequential(nn.Conv2d(features + 2, 16, 3, padding=1), nn.ReLU(), nn.Conv2d(16, 1, 3, padding=1))
        for last in (self.regularise[-1], self.refine[-1], self.confidence[-1]):
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
        self.register_buffer("offsets", torch.linspace(-log_range, log_range, hypotheses), persistent=False)

    def forward(self, images, volume_feats, inv, conf_logit, K, to_other):
        """Both sources batched, left ones first: images (2B, 3, H, W) in [0, 1], volume_feats
        (2B, C, h, w), inv and conf_logit (2B, 1, H, W) at the coarse size, K (2B, 3, 3) coarse
        intrinsics, to_other (2B, 4, 4) each view's points into its partner (baseline units).
        Returns the refined inverse depth and confidence logit."""
        n, _, hgt, wid = images.shape
        b = n // 2
        k = self.offsets.shape[0]
        up = F.interpolate(volume_feats, size=(hgt, wid), mode="bilinear", align_corners=False)
        ref = self.features(torch.cat([self.image(images * 2.0 - 1.0), up], dim=1))
        other = torch.cat([ref[b:], ref[:b]], dim=0)
        other_K = torch.cat([K[b:], K[:b]], dim=0)
        c = ref.shape[1]
        depth = torch.exp(self.offsets).reshape(1, k, 1, 1) / inv.clamp(min=1e-6)  # (N, K, H, W)
        rays = pixel_rays(K, wid, hgt)  # (N, 3, H, W)
        pts = (rays[:, :, None] * depth[:, None]).reshape(n, 3, k, hgt * wid)
        uv, z = project(transform_points(to_other, pts), other_K)  # (N, 2, K, HW)
        vis = in_image(uv, z, wid, hgt).reshape(n, 1, k, hgt, wid)
        grid = normalise_pixels(uv.reshape(n, 2, k * hgt, wid), wid, hgt).reshape(n, k, hgt, wid, 2).reshape(n * k, hgt, wid, 2)
        src = other[:, None].expand(n, k, c, hgt, wid).reshape(n * k, c, hgt, wid)
        warped = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        warped = warped.reshape(n, k, self.groups, c // self.groups, hgt, wid)
        corr = (warped * ref.reshape(n, 1, self.groups, c // self.groups, hgt, wid)).mean(dim=3).permute(0, 2, 1, 3, 4)
        logits = self.regularise(torch.cat([corr, vis], dim=1))[:, 0]  # (N, K, H, W)
        logits = logits + self.refine(torch.cat([logits, ref], dim=1))
        prob = torch.softmax(logits, dim=1)
        shift = (prob * self.offsets.reshape(1, k, 1, 1)).sum(dim=1, keepdim=True)
        peak = prob.max(dim=1, keepdim=True).values
        conf_logit = conf_logit + self.confidence(torch.cat([ref, peak, shift], dim=1))
        return inv * torch.exp(-shift), conf_logit
