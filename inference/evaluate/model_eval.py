"""The model's figures on sequences with supervision cameras (`rig model eval`, benchmarks/model_eval.py).

For every (or every k-th) frame set, the model renders every supervision camera from the two
sources; against the camera's real image (undistorted, at the output size):
- PSNR and SSIM over the full image and over the person mask (where the sequence carries one:
  simulator takes do);
- stage 1's depth against ground truth (where it exists): AbsRel = mean |d - d*| / d* over the
  pixels of each source that the other source also sees (from the ground-truth depths), and that
  error split into scale (the median of d / d* per source and set) and shape (AbsRel after dividing
  by it);
- the frame-to-frame jitter of stage 1's scaling S: |S_t - S_{t-1}| / S_{t-1} on consecutive sets
  of a sequence (mean and max over the pairs, the three components averaged).
The same figures for two references in the same run: the oracle pipeline (ground-truth depth
through the oracle backbone, the same stage-2 weights) and the nearer source's image as it is
(what a viewer sees without a model). LPIPS is left out: it needs pretrained network weights.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from inference.config import ModelConfig
from inference.metrics import covisibility, psnr
from inference.model.geometry import relative_pose, transform_points
from inference.model.pipeline import SplatSAP, build_model
from inference.runtime.preprocess import pinhole
from inference.train.data import FrameSource, Preprocessor
from inference.train.losses import ssim_map
from inference.train.stages import stage1_forward

STAGE2_PARTS = ("depth_init.", "depth_refine.", "colour_init.", "gaussian_plane.", "splatting.")


def oracle_twin(model: SplatSAP) -> SplatSAP:
    """The oracle pipeline with `model`'s stage-2 weights (metric ground-truth depth, S = 1, T = 0)."""
    cfg = ModelConfig.from_dict(model.cfg.to_dict())
    cfg.backbone.kind = "oracle"
    cfg.backbone.oracle_scale = "metric"
    cfg.stage1.affine = "bypass"
    twin = build_model(cfg, seed=0)
    state = {k: v for k, v in model.state_dict().items() if k.startswith(STAGE2_PARTS)}
    missing = [k for k in twin.state_dict() if k.startswith(STAGE2_PARTS) and k not in state]
    if missing:
        raise ValueError(f"stage-2 weights missing: {missing[:3]}")
    twin.load_state_dict(state, strict=False)
    return twin.eval()


def stage1_depths(affine, L, R, source: FrameSource) -> dict:
    """Stage 1's depth (coarse) in each source's own camera."""
    # The poses follow the point maps (the views may have stayed on the CPU while the model runs on a GPU).
    dev = affine.points_right.device
    to_right = relative_pose(R.poses.to(dev), L.poses.to(dev))
    return {source.left: affine.points_left[0, 2].detach().float().cpu().numpy(),
            source.right: transform_points(to_right, affine.points_right)[0, 2].detach().float().cpu().numpy()}


def _depth_ratios(affine, L, R, fs, source: FrameSource, gt_coarse: dict, coarse: tuple[int, int], masks: Optional[dict] = None,
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


def view_depth_errors(depth: torch.Tensor, alpha: torch.Tensor, truth: np.ndarray, mask: Optional[np.ndarray] = None) -> np.ndarray:
    """|rendered depth / truth - 1| of one rendered view (1, 1, H, W) on the pixels the truth has and
    the render covers (accumulated opacity over one half), optionally within a mask."""
    d = depth[0, 0].detach().float().cpu().numpy()
    keep = (truth > 0) & (alpha[0, 0].detach().float().cpu().numpy() > 0.5) & (d > 0)
    if mask is not None:
        keep &= mask
    return np.abs(d[keep] / truth[keep] - 1.0)


def stage1_absrel(affine, L, R, fs, source: FrameSource, gt_coarse: dict, coarse: tuple[int, int], masks: Optional[dict] = None,
                  single: bool = False) -> list[float]:
    """AbsRel of stage 1's depth in each source against ground truth (see _depth_ratios for the pixels)."""
    return [float(np.mean(np.abs(r - 1.0))) for r in _depth_ratios(affine, L, R, fs, source, gt_coarse, coarse, masks, single)]


def stage1_scale_split(affine, L, R, fs, source: FrameSource, gt_coarse: dict, coarse: tuple[int, int]) -> list[tuple[float, float]]:
    """Stage 1's depth error split into its scale and its shape, per source: the median of depth over
    ground truth (1: the metric scale is right) and the AbsRel left once the depth is divided by it."""
    out = []
    for r in _depth_ratios(affine, L, R, fs, source, gt_coarse, coarse):
        med = float(np.median(r))
        out.append((med, float(np.mean(np.abs(r / med - 1.0)))))
    return out


@dataclass
class _Scores:
    psnr: list
    ssim: list
    psnr_mask: list
    ssim_mask: list

    @classmethod
    def new(cls) -> "_Scores":
        return cls([], [], [], [])

    def add(self, pred: torch.Tensor, truth: torch.Tensor, mask: Optional[np.ndarray]) -> None:
        p = pred[0].permute(1, 2, 0).float().cpu().numpy()
        t = truth[0].permute(1, 2, 0).float().cpu().numpy()
        smap = ssim_map(pred.float(), truth.float())[0].mean(0).cpu().numpy()
        self.psnr.append(psnr(p, t))
        self.ssim.append(float(smap.mean()))
        if mask is not None and mask.any():
            self.psnr_mask.append(psnr(p, t, mask))
            self.ssim_mask.append(float(smap[mask].mean()))

    def summary(self) -> dict:
        def mean(x):
            return round(float(np.mean(x)), 4) if x else None

        return {"psnr": mean(self.psnr), "ssim": mean(self.ssim), "psnr_mask": mean(self.psnr_mask),
                "ssim_mask": mean(self.ssim_mask), "views": len(self.psnr)}


@torch.no_grad()
def evaluate(model: SplatSAP, source: FrameSource, every: int = 1, max_sets: Optional[int] = None,
             references: bool = True, progress: Optional[Callable[[int, int], None]] = None,
             device: Optional[torch.device] = None) -> dict:
    """`device`: where the model runs (None: where its parameters are). Frames are read and
    resampled on the CPU, then moved there; the figures are computed on the CPU (in fp32)."""
    if device is not None:
        model = model.to(device)
    device = next(model.parameters()).device
    model = model.eval()
    sizes = model.cfg.sizes
    pre = Preprocessor()
    twin = oracle_twin(model).to(device) if references else None
    picks = list(range(0, len(source), every))[: max_sets or None]
    per_cam: dict[str, dict[str, _Scores]] = defaultdict(lambda: defaultdict(_Scores.new))
    absrel: list[float] = []
    absrel_person: list[float] = []
    absrel_single: list[float] = []
    view_absrel: list[float] = []
    view_absrel_person: list[float] = []
    split: list[tuple[float, float]] = []
    scales: dict[str, list[tuple[int, np.ndarray]]] = defaultdict(list)
    for n, index in enumerate(picks):
        fs = source.frame_set(index, with_truth=True)
        L = pre.views(fs, [source.left], sizes.fine).to(device)
        R = pre.views(fs, [source.right], sizes.fine).to(device)
        *_, affine = stage1_forward(model, L, R)
        seq, _, set_no = fs.key.rpartition("#")
        scales[seq].append((int(set_no) if set_no.isdigit() else index, affine.scale[0].float().cpu().numpy().astype(np.float64)))
        have_depth = all(fs.depth.get(c) is not None for c in (source.left, source.right))
        gt_coarse = {}
        if have_depth:
            gt_coarse = {c: pre.depth(fs.depth[c], fs.cameras[c], sizes.coarse) for c in (source.left, source.right)}
            absrel += stage1_absrel(affine, L, R, fs, source, gt_coarse, sizes.coarse)
            absrel_single += stage1_absrel(affine, L, R, fs, source, gt_coarse, sizes.coarse, single=True)
            split += stage1_scale_split(affine, L, R, fs, source, gt_coarse, sizes.coarse)
            if all(fs.masks.get(c) is not None for c in (source.left, source.right)):
                masks = {c: pre.depth(fs.masks[c].astype(np.float32), fs.cameras[c], sizes.coarse) > 0.5 for c in (source.left, source.right)}
                absrel_person += stage1_absrel(affine, L, R, fs, source, gt_coarse, sizes.coarse, masks)
        for sup in source.supervision:
            T = pre.views(fs, [sup], sizes.output).to(device)
            mask = None
            if fs.masks.get(sup) is not None:
                mask = pre.depth(fs.masks[sup].astype(np.float32), fs.cameras[sup], sizes.output) > 0.5
            args = (L.images, R.images, L.K, R.K, L.poses, R.poses, T.K, T.poses)
            out = model.run(*args)
            per_cam["model"][sup].add(out["image"], T.images, mask)
            if fs.depth.get(sup) is not None:
                gt_view = pre.depth(fs.depth[sup], fs.cameras[sup], sizes.output)
                view_err = view_depth_errors(out["depth"], out["alpha"], gt_view)
                view_absrel.append(float(view_err.mean()) if view_err.size else float("nan"))
                if mask is not None:
                    person_err = view_depth_errors(out["depth"], out["alpha"], gt_view, mask)
                    if person_err.size:
                        view_absrel_person.append(float(person_err.mean()))
            if references:
                if have_depth:
                    depth_in = [torch.from_numpy(gt_coarse[c])[None, None].to(device) for c in (source.left, source.right)]
                    per_cam["oracle"][sup].add(twin.run(*args, *depth_in)["image"], T.images, mask)
                nearer = min((source.left, source.right), key=lambda c: np.linalg.norm(fs.cameras[c].center - fs.cameras[sup].center))
                per_cam["nearest_source"][sup].add(pre.views(fs, [nearer], sizes.output).images.to(device), T.images, mask)
        if progress is not None:
            progress(n + 1, len(picks))
    jitter = []
    for seq, rows in scales.items():
        rows.sort()
        for (a, sa), (b, sb) in zip(rows, rows[1:]):
            jitter.append(float(np.mean(np.abs(sb - sa) / np.abs(sa))))
    out = {}
    for name, cams in per_cam.items():
        all_scores = _Scores.new()
        for s in cams.values():
            for f in ("psnr", "ssim", "psnr_mask", "ssim_mask"):
                getattr(all_scores, f).extend(getattr(s, f))
        out[name] = {"overall": all_scores.summary(), "cameras": {c: s.summary() for c, s in sorted(cams.items())}}
    model_figures = out.pop("model", {})
    return {
        "sets": len(picks), "every": every, "supervision": list(source.supervision),
        **model_figures,
        "depth_absrel": round(float(np.mean(absrel)), 5) if absrel else None,
        "depth_absrel_person": round(float(np.mean(absrel_person)), 5) if absrel_person else None,
        "depth_absrel_single": round(float(np.mean(absrel_single)), 5) if absrel_single else None,
        # The depth the model renders in each supervision camera against that camera's truth: what
        # the image is drawn at, after depth init, refinement and splatting (stage 1's AbsRel above
        # is on the sources' pixels both see; it misses what only one sees and what the target adds).
        "view_depth_absrel": round(float(np.nanmean(view_absrel)), 5) if view_absrel else None,
        "view_depth_absrel_person": round(float(np.mean(view_absrel_person)), 5) if view_absrel_person else None,
        # Where stage 1's depth error lies: its scale per source and frame set (median depth over
        # truth) and its shape (AbsRel once each is divided by that median).
        "depth_scale": {"median_ratio_min": round(min(m for m, _ in split), 4), "median_ratio_max": round(max(m for m, _ in split), 4),
                        "absrel_scale_free": round(float(np.mean([a for _, a in split])), 5)} if split else None,
        "scale_jitter": {"mean": round(float(np.mean(jitter)), 6), "max": round(float(np.max(jitter)), 6), "pairs": len(jitter)} if jitter else None,
        "references": out,
    }


def depth_lines(result: dict) -> list[str]:
    """The depth and scale figures of an `evaluate` result as text lines (rig model eval and
    benchmarks/model_eval.py print them)."""
    lines = []
    if result.get("depth_absrel") is not None:
        lines.append(f"stage-1 depth AbsRel (pixels both sources see): {100 * result['depth_absrel']:.2f} %")
    if result.get("depth_absrel_person") is not None:
        lines.append(f"  on the person masks: {100 * result['depth_absrel_person']:.2f} %")
    if result.get("depth_absrel_single") is not None:
        lines.append(f"  on the pixels only one source sees: {100 * result['depth_absrel_single']:.2f} %")
    if result.get("depth_scale") is not None:
        d = result["depth_scale"]
        lines.append(f"  scale (median depth / truth per source and set): {d['median_ratio_min']:.3f} to {d['median_ratio_max']:.3f}; "
                     f"AbsRel once divided by it: {100 * d['absrel_scale_free']:.2f} %")
    if result.get("view_depth_absrel") is not None:
        person = f" (person masks {100 * result['view_depth_absrel_person']:.2f} %)" if result.get("view_depth_absrel_person") is not None else ""
        lines.append(f"rendered depth AbsRel in the supervision cameras: {100 * result['view_depth_absrel']:.2f} %{person}")
    if result.get("scale_jitter") is not None:
        j = result["scale_jitter"]
        lines.append(f"scale jitter between consecutive sets: mean {100 * j['mean']:.3f} %, max {100 * j['max']:.3f} % ({j['pairs']} pairs)")
    return lines
