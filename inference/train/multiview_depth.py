"""Multi-view stereo depth of a source camera from its neighbouring supervision cameras (training only).

The paper's backbone, MASt3R, comes pretrained: its two views already agree on a plausible metric
geometry before stage 1 starts. A backbone trained from scratch (`stereo`, `tiny`) has no such
start, and the rendering loss alone teaches it slowly: on the simulator's rig, whose sources stand
about as far apart as they stand from the people, matching the two sources directly is hard (a
classical plane sweep between them alone is 36-43 % AbsRel). The supervision cameras between the
sources are close to each source (about a fifth of the baseline on the simulator's rig): a plane
sweep between a source and its two nearest supervision cameras is a narrow-baseline problem, and
where its cost has a clear, agreed peak its depth is accurate (about 1 % median error there).

`multiview_depth` computes that depth and a mask of the pixels it trusts, from the images and the
calibration alone (no ground truth): zero-mean normalised cross-correlation (ZNCC) over a window,
D fronto-parallel planes uniform in inverse depth, the cost averaged over the neighbours, winner
takes all with a parabola through the peak. A pixel is trusted where the mean ZNCC peak clears
`min_score` and stands `min_margin` above every plane more than `margin_planes` from it (no second
match), every neighbour on its own puts the peak within `agree_planes` planes of the others, and
the window has texture. On simulator frame sets that keeps about 30 % of each view, at 3-6 % mean
and 1.5 % median error. Stage 1 then pulls the backbone's depth towards it on those pixels
(`TrainConfig.mvs_depth`), as self-supervised MVS trainers pull towards their own pseudo-labels.

Plain torch on whole planes at a time (4-D grid_sample, pooling); it runs once per frame set and
source and the trainer caches it, so it is written for clarity, not for export.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from inference.model.geometry import inverse_3x3, invert_pose


@dataclass(frozen=True)
class MultiViewDepthConfig:
    planes: int = 96
    window: int = 7  # ZNCC window side (pixels of the size it runs at)
    min_score: float = 0.6  # mean ZNCC at the peak
    min_margin: float = 0.15  # the peak above the best score more than `margin_planes` planes from it
    margin_planes: int = 3
    agree_planes: int = 1  # each neighbour's own peak within this many planes of the others'
    min_texture: float = 1e-4  # variance of the reference window (grey levels in [0, 1])
    single_score: float = 0.7  # the peak a pixel needs when only one neighbour sees the scene
    chunk: int = 16  # planes sampled at once
    near: float = 0.2  # the depth range swept, in units of the distance between the two sources
    far: float = 6.0

    def check(self) -> None:
        if not (isinstance(self.planes, int) and self.planes >= 2):
            raise ValueError(f"mvs.planes must be an integer >= 2, got {self.planes!r}")
        if not (isinstance(self.window, int) and self.window >= 3 and self.window % 2 == 1):
            raise ValueError(f"mvs.window must be an odd integer >= 3, got {self.window!r}")
        if not 0 < self.near < self.far:
            raise ValueError(f"mvs: the depth range must satisfy 0 < near < far, got {self.near}, {self.far}")


def _grey(images: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) in [0, 1] -> (N, 1, H, W)."""
    return (0.299 * images[:, 0:1] + 0.587 * images[:, 1:2] + 0.114 * images[:, 2:3])


def _box(x: torch.Tensor, window: int) -> torch.Tensor:
    return F.avg_pool2d(x, window, 1, window // 2, count_include_pad=False)


def _zncc(a: torch.Tensor, b: torch.Tensor, window: int) -> torch.Tensor:
    """ZNCC of windows of a (1, 1, H, W) against each of b (N, 1, H, W)."""
    mu_a, mu_b = _box(a, window), _box(b, window)
    cov = _box(a * b, window) - mu_a * mu_b
    var_a = (_box(a * a, window) - mu_a * mu_a).clamp(min=1e-6)
    var_b = (_box(b * b, window) - mu_b * mu_b).clamp(min=1e-6)
    return cov / torch.sqrt(var_a * var_b)


def sweep_costs(ref_image, ref_K, ref_pose, images, Ks, poses, inverse_depths, cfg: MultiViewDepthConfig) -> torch.Tensor:
    """ZNCC (M, D, H, W) of the reference view (3, H, W) against each of M neighbours (M, 3, H, W),
    at D planes of the reference camera (inverse depths in the poses' units). -1 where a plane's
    point falls outside a neighbour's image or behind it."""
    m, _, h, w = images.shape
    d = inverse_depths.shape[0]
    ys, xs = torch.meshgrid(torch.arange(h, dtype=ref_K.dtype, device=ref_K.device), torch.arange(w, dtype=ref_K.dtype, device=ref_K.device), indexing="ij")
    pix = torch.stack([xs, ys, torch.ones_like(xs)]).reshape(3, -1)
    rays = inverse_3x3(ref_K) @ pix  # (3, HW), z = 1
    rel = poses @ invert_pose(ref_pose)  # (M, 4, 4) reference camera -> neighbour
    a = _grey(ref_image[None])
    b_all = _grey(images)
    out = torch.empty(m, d, h, w, dtype=ref_image.dtype, device=ref_image.device)
    for start in range(0, d, cfg.chunk):
        inv = inverse_depths[start : start + cfg.chunk]
        k = inv.shape[0]
        pts = rays[None] / inv.reshape(k, 1, 1)  # (k, 3, HW)
        cam = rel[:, None, :3, :3] @ pts[None] + rel[:, None, :3, 3:]  # (M, k, 3, HW)
        uvw = Ks[:, None] @ cam
        z = uvw[:, :, 2]
        u = uvw[:, :, 0] / z.clamp(min=1e-6)
        v = uvw[:, :, 1] / z.clamp(min=1e-6)
        grid = torch.stack([(u + 0.5) / w * 2 - 1, (v + 0.5) / h * 2 - 1], dim=-1).reshape(m * k, h, w, 2)
        src = b_all[:, None].expand(m, k, 1, h, w).reshape(m * k, 1, h, w)
        warped = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        score = _zncc(a, warped, cfg.window).reshape(m, k, h, w)
        inside = ((u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1) & (z > 1e-6)).reshape(m, k, h, w)
        out[:, start : start + k] = torch.where(inside, score, torch.full_like(score, -1.0))
    return out


def _peak(cost: torch.Tensor, inverse_depths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Winner takes all over (D, H, W) with a parabola through the peak: depth, peak score, plane index."""
    d = cost.shape[0]
    best = cost.argmax(0)
    c0 = cost.gather(0, best[None])[0]
    lo = cost.gather(0, (best - 1).clamp(min=0)[None])[0]
    hi = cost.gather(0, (best + 1).clamp(max=d - 1)[None])[0]
    curv = lo - 2 * c0 + hi
    off = torch.where(curv < -1e-6, 0.5 * (lo - hi) / curv.clamp(max=-1e-6), torch.zeros_like(curv)).clamp(-0.5, 0.5)
    pos = best.to(cost.dtype) + off
    step = (inverse_depths[-1] - inverse_depths[0]) / max(1, d - 1)
    inv = inverse_depths[0] + step * pos
    return 1.0 / inv.clamp(min=1e-9), c0, best


@torch.no_grad()
def multiview_depth(ref_image, ref_K, ref_pose, images, Ks, poses, near: float, far: float,
                    cfg: MultiViewDepthConfig = MultiViewDepthConfig()) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth (H, W) of the reference camera (z, in the poses' units) and the mask (H, W, bool) of
    the pixels it is trusted on. `images` (M, 3, H, W) are M >= 1 neighbouring cameras at the
    reference's size, with intrinsics `Ks` (M, 3, 3) and world-to-camera `poses` (M, 4, 4)."""
    if images.shape[0] < 1:
        raise ValueError("multi-view depth needs at least one neighbouring camera")
    if not 0 < near < far:
        raise ValueError(f"depth range must satisfy 0 < near < far, got {near}, {far}")
    inverse_depths = torch.linspace(1.0 / near, 1.0 / far, cfg.planes, dtype=ref_image.dtype, device=ref_image.device)
    costs = sweep_costs(ref_image, ref_K, ref_pose, images, Ks, poses, inverse_depths, cfg)
    mean = costs.mean(0)
    depth, score, best = _peak(mean, inverse_depths)
    a = _grey(ref_image[None])
    texture = (_box(a * a, cfg.window) - _box(a, cfg.window) ** 2)[0, 0]
    away = (torch.arange(cfg.planes, device=best.device)[:, None, None] - best[None]).abs() > cfg.margin_planes
    runner_up = torch.where(away, mean, torch.full_like(mean, -2.0)).max(0).values
    mask = (texture > cfg.min_texture) & torch.isfinite(depth) & (score - runner_up > cfg.min_margin)
    if costs.shape[0] == 1:
        mask &= score > cfg.single_score
    else:
        mask &= score > cfg.min_score
        own = torch.stack([_peak(c, inverse_depths)[2] for c in costs])  # (M, H, W)
        mask &= (own.max(0).values - own.min(0).values) <= cfg.agree_planes
    return depth, mask


def nearest_cameras(poses: torch.Tensor, ref: int, candidates: list[int], count: int = 2) -> list[int]:
    """The `count` candidates whose centres lie nearest the reference camera's (poses (N, 4, 4))."""
    centres = -poses[:, :3, :3].transpose(1, 2) @ poses[:, :3, 3:]
    dist = [(float(torch.linalg.norm(centres[j] - centres[ref])), j) for j in candidates if j != ref]
    return [j for _, j in sorted(dist)[:count]]


def source_depths(views, supervision: list[int], neighbours: int, cfg: MultiViewDepthConfig) -> list[torch.Tensor]:
    """[depth, mask, depth, mask] of the two sources, views 0 (left) and 1 (right) of `views`
    (images (N, 3, H, W), K, poses), each from its `neighbours` nearest supervision views; the depth
    range is cfg.near..cfg.far times the distance between the sources."""
    centres = invert_pose(views.poses)[:, :3, 3]
    baseline = float(torch.linalg.norm(centres[0] - centres[1]))
    out: list[torch.Tensor] = []
    for ref in (0, 1):
        nb = nearest_cameras(views.poses, ref, supervision, neighbours)
        out += multiview_depth(views.images[ref], views.K[ref], views.poses[ref], views.images[nb], views.K[nb], views.poses[nb],
                               cfg.near * baseline, cfg.far * baseline, cfg)
    return out
