"""Stage 2 at the fine size: depth refinement, colour initialisation and the Gaussian plane.

- `DepthRefine` (the paper's 3D refinement): a CNN encoder E_f gives features at 1/4 of the fine
  size; N depth candidates d_n = D (1 + delta_n) around the initial depth D of each target ray;
  the source features are warped into the target per candidate with one 4-D grid_sample per
  source (candidates stacked along the image height); a group-wise correlation cost volume is
  regularised by 3D convolutions into the feature volume Phi; a softmax over candidates gives the
  depth probabilities w_n and the refined depth sum_n w_n d_n (ENeRF). Probabilities are
  upsampled to the fine size, so the refined depth keeps the initial depth's sharp edges.
- `ColourInit`: colours (and features) of both sources warped at the refined depth; an MLP of the
  warped features and phi (Phi read at the refined depth by linear interpolation along the
  candidates) gives the blending weights w_c^i; C = sum_i w_c^i C^{i->k}.
- `GaussianPlane`: convolutional heads h_r, h_s, h_o on the aggregated map M = Agg{f_l, f_r, phi}
  and the position Y; the colour head h_c (which also sees C) gives dC and P_c = alpha C +
  (1 - alpha) dC (alpha = 0.8).

Output layers start so that an untrained model is a sensible renderer: dC = C, in-plane Gaussians
about `gaussian_sigma` pixels wide facing the camera, opacity ~0.99, and a flat depth distribution.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.config import Stage2Config
from inference.model.geometry import (
    in_image,
    normalise_pixels,
    pixel_rays,
    project,
    resize_intrinsics,
    transform_points,
)


@dataclass
class RefinedDepth:
    depth: torch.Tensor  # (B, 1, H, W) refined depth at the fine size
    probabilities: torch.Tensor  # (B, N, h, w) depth probabilities at the volume size
    phi: torch.Tensor  # (B, Cv, h, w) the feature volume read at the refined depth
    features_left: torch.Tensor  # (B, C, h, w) E_f of the left image
    features_right: torch.Tensor


@dataclass
class ColourInitOutput:
    colour: torch.Tensor  # (B, 3, H, W) C, the blended warped colour
    colour_left: torch.Tensor  # (B, 3, H, W) C^{l->k}
    colour_right: torch.Tensor
    visible_left: torch.Tensor  # (B, 1, H, W) the left source sees the point (projection inside, in front)
    visible_right: torch.Tensor
    blend_left: torch.Tensor  # (B, 1, H, W) w_c^l (w_c^r = 1 - w_c^l)
    aggregate: torch.Tensor  # (B, C', H, W) [f_l, f_r, phi] at the fine size


@dataclass
class GaussianPlaneMaps:
    """One Gaussian per fine target pixel, in the target camera's frame."""

    means: torch.Tensor  # (B, 3, H, W) metres
    rotations: torch.Tensor  # (B, 4, H, W) unit quaternions (w, x, y, z)
    scales: torch.Tensor  # (B, 3, H, W) metres (standard deviations along the rotated axes)
    opacities: torch.Tensor  # (B, 1, H, W)
    colours: torch.Tensor  # (B, 3, H, W) P_c


def conv_relu(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.ReLU())


class FineEncoder(nn.Module):
    """E_f: images (B, 3, H, W) to features (B, C, H/4, W/4)."""

    def __init__(self, dim: int):
        super().__init__()
        self.net = nn.Sequential(
            conv_relu(3, 16, 2), conv_relu(16, 16), conv_relu(16, 32, 2), conv_relu(32, 32), nn.Conv2d(32, dim, 3, padding=1)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x * 2.0 - 1.0)


def warp_candidates(features, source_K, target_to_source, rays, depths):
    """Sample source features at every candidate point of every target ray.

    features (B, C, h, w) with intrinsics `source_K` for that size; rays (B, 3, h', w') unit-z target
    rays; depths (B, N, h', w'). Returns (B, C, N, h', w') and a visibility mask (B, 1, N, h', w').
    The N candidates are stacked along the height so that one 4-D grid_sample serves them all
    (ONNX Runtime and TensorRT do not run 5-D GridSample).
    """
    b, n, hh, ww = depths.shape
    _, c, fh, fw = features.shape
    pts = rays[:, :, None] * depths[:, None]  # (B, 3, N, h', w')
    uv, z = project(transform_points(target_to_source, pts.reshape(b, 3, n * hh, ww)), source_K)
    grid = normalise_pixels(uv, fw, fh)  # (B, N*h', w', 2)
    sampled = F.grid_sample(features, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    visible = in_image(uv, z, fw, fh)
    return sampled.reshape(b, c, n, hh, ww), visible.reshape(b, 1, n, hh, ww)


class DepthRefine(nn.Module):
    def __init__(self, cfg: Stage2Config, fine_size: tuple[int, int]):
        super().__init__()
        if cfg.feature_dim % cfg.groups:
            raise ValueError("stage2: feature_dim must be a multiple of groups")
        self.cfg = cfg
        self.fine_size = fine_size
        self.volume_size = (fine_size[0] // 4, fine_size[1] // 4)
        self.encoder = FineEncoder(cfg.feature_dim)
        v = cfg.volume_dim
        self.regularise = nn.Sequential(
            nn.Conv3d(cfg.groups + 1, v, 3, padding=1), nn.ReLU(), nn.Conv3d(v, v, 3, padding=1), nn.ReLU(), nn.Conv3d(v, v, 3, padding=1), nn.ReLU()
        )
        self.probability = nn.Conv3d(v, 1, 3, padding=1)
        self.register_buffer("offsets", torch.linspace(-cfg.search_range, cfg.search_range, cfg.candidates), persistent=False)

    def forward(self, left, right, left_K, right_K, target_to_left, target_to_right, target_K, initial_depth) -> RefinedDepth:
        """Images (B, 3, H, W) at the fine size with their intrinsics; target_K for the fine size."""
        b = left.shape[0]
        fw, fh = self.fine_size
        vw, vh = self.volume_size
        n = self.cfg.candidates
        feats = self.encoder(torch.cat([left, right], dim=0))
        f_l, f_r = feats[:b], feats[b:]
        # Intrinsics of the feature maps and of the volume (both 1/4 of the fine size).
        kl = resize_intrinsics(left_K, (fw, fh), (vw, vh))
        kr = resize_intrinsics(right_K, (fw, fh), (vw, vh))
        kt = resize_intrinsics(target_K, (fw, fh), (vw, vh))
        d0 = F.interpolate(initial_depth, size=(vh, vw), mode="bilinear", align_corners=False)
        candidates = d0 * (1.0 + self.offsets.reshape(1, n, 1, 1))  # (B, N, h, w)
        rays = pixel_rays(kt, vw, vh)
        w_l, vis_l = warp_candidates(f_l, kl, target_to_left, rays, candidates)
        w_r, vis_r = warp_candidates(f_r, kr, target_to_right, rays, candidates)
        g = self.cfg.groups
        c = self.cfg.feature_dim
        corr = (w_l * w_r).reshape(b, g, c // g, n, vh, vw).mean(dim=2)
        volume = self.regularise(torch.cat([corr, vis_l * vis_r], dim=1))  # Phi (B, Cv, N, h, w)
        prob = torch.softmax(self.probability(volume)[:, 0], dim=1)  # (B, N, h, w)
        # Refined depth: sum_n w_n d_n with w_n upsampled to the fine size, d_n = D (1 + delta_n).
        prob_fine = F.interpolate(prob, size=(fh, fw), mode="bilinear", align_corners=False)
        delta = (prob_fine * self.offsets.reshape(1, n, 1, 1)).sum(dim=1, keepdim=True)
        depth = initial_depth * (1.0 + delta)
        # phi: Phi read at the expected candidate index (linear interpolation along the candidates).
        index = torch.arange(n, dtype=prob.dtype, device=prob.device).reshape(1, n, 1, 1)
        expected = (prob * index).sum(dim=1, keepdim=True)
        hat = (1.0 - (index - expected).abs()).clamp(min=0.0)  # (B, N, h, w)
        phi = (volume * hat[:, None]).sum(dim=2)
        return RefinedDepth(depth, prob, phi, f_l, f_r)


class ColourInit(nn.Module):
    def __init__(self, cfg: Stage2Config, fine_size: tuple[int, int]):
        super().__init__()
        self.cfg = cfg
        self.fine_size = fine_size
        c = 2 * cfg.feature_dim + cfg.volume_dim
        self.mlp = nn.Sequential(nn.Conv2d(c + 2, 32, 1), nn.ReLU(), nn.Conv2d(32, 32, 1), nn.ReLU(), nn.Conv2d(32, 1, 1))
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, left, right, left_K, right_K, target_to_left, target_to_right, target_K, refined: RefinedDepth) -> ColourInitOutput:
        fw, fh = self.fine_size
        points = pixel_rays(target_K, fw, fh) * refined.depth
        uv_l, z_l = project(transform_points(target_to_left, points), left_K)
        uv_r, z_r = project(transform_points(target_to_right, points), right_K)
        grid_l = normalise_pixels(uv_l, fw, fh)
        grid_r = normalise_pixels(uv_r, fw, fh)
        ramp = self.cfg.visibility_ramp
        vis_l = in_image(uv_l, z_l, fw, fh, ramp)
        vis_r = in_image(uv_r, z_r, fw, fh, ramp)
        col_l = F.grid_sample(left, grid_l, mode="bilinear", padding_mode="border", align_corners=False)
        col_r = F.grid_sample(right, grid_r, mode="bilinear", padding_mode="border", align_corners=False)
        # The 1/4-size feature maps share the normalised grid (pixel-centre convention).
        f_l = F.grid_sample(refined.features_left, grid_l, mode="bilinear", padding_mode="zeros", align_corners=False)
        f_r = F.grid_sample(refined.features_right, grid_r, mode="bilinear", padding_mode="zeros", align_corners=False)
        phi = F.interpolate(refined.phi, size=(fh, fw), mode="bilinear", align_corners=False)
        aggregate = torch.cat([f_l * vis_l, f_r * vis_r, phi], dim=1)
        # Two-way softmax as a sigmoid of the logit difference; a source that cannot see the point is pushed out.
        logit = self.mlp(torch.cat([aggregate, vis_l, vis_r], dim=1)) + 20.0 * (vis_l - vis_r)
        w_l = torch.sigmoid(logit)
        colour = w_l * col_l + (1.0 - w_l) * col_r
        return ColourInitOutput(colour, col_l, col_r, vis_l, vis_r, w_l, aggregate)


class GaussianPlane(nn.Module):
    def __init__(self, cfg: Stage2Config, fine_size: tuple[int, int]):
        super().__init__()
        self.cfg = cfg
        self.fine_size = fine_size
        c = 2 * cfg.feature_dim + cfg.volume_dim
        d = cfg.head_dim
        self.aggregate = conv_relu(c, d)  # Agg{f_l, f_r, phi}
        self.trunk = conv_relu(d + 3, d)  # with Y
        # One 3x3 convolution for all heads h_r, h_s, h_o, h_c (4 + 3 + 1 + 3 channels); the colour
        # head also sees C, as dC = h_c(M, Y, C).
        self.heads = nn.Conv2d(d + 3, 11, 3, padding=1)
        nn.init.zeros_(self.heads.weight)
        with torch.no_grad():
            self.heads.bias.zero_()
            self.heads.bias[7] = 4.6  # opacity sigmoid(4.6) = 0.99
        # Gaussian extent relative to the pixel footprint: in-plane sigma pixels, thin along the ray.
        self.register_buffer("base_scale", torch.tensor([cfg.gaussian_sigma, cfg.gaussian_sigma, 0.1 * cfg.gaussian_sigma]).reshape(1, 3, 1, 1), persistent=False)
        self.register_buffer("identity", torch.tensor([1.0, 0.0, 0.0, 0.0]).reshape(1, 4, 1, 1), persistent=False)

    def forward(self, colours: ColourInitOutput, depth: torch.Tensor, target_K: torch.Tensor) -> GaussianPlaneMaps:
        fw, fh = self.fine_size
        b = depth.shape[0]
        means = pixel_rays(target_K, fw, fh) * depth
        # Y, the Gaussian position, made scale-free by the mean depth of the view.
        ref = depth.mean(dim=(1, 2, 3), keepdim=True).clamp(min=1e-6)
        m = self.aggregate(colours.aggregate)
        h = self.trunk(torch.cat([m, means / ref], dim=1))
        c = colours.colour
        out = self.heads(torch.cat([h, c], dim=1))
        q = out[:, 0:4] + self.identity
        q = q / torch.sqrt((q * q).sum(dim=1, keepdim=True)).clamp(min=1e-6)
        footprint = depth / target_K[:, 0, 0].reshape(b, 1, 1, 1)  # metres per fine pixel
        scales = self.base_scale * footprint * torch.exp(out[:, 4:7].clamp(max=5.0))
        opacity = torch.sigmoid(out[:, 7:8])
        delta_c = (c + out[:, 8:11]).clamp(0.0, 1.0)
        a = self.cfg.colour_alpha
        return GaussianPlaneMaps(means, q, scales, opacity, a * c + (1.0 - a) * delta_c)
