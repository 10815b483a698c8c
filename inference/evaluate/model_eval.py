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

People are the subject. Besides PSNR/SSIM on the person masks and the rendered depth's AbsRel
there, "vanished" is the share of the ground truth's person-mask pixels (in the supervision
cameras, pooled over views) where the rendered depth is more than 30 % off the truth, a pixel the
render left empty counting as off: where a person's pixels show the wall behind, or nothing.

Per take (a sequence; a data set's take), the same figures and the take's exposure to people: the
person's share of its supervision pixels and the nearest person (the smallest ground-truth depth
on any camera's person mask); then their spread over the takes (`spread`): mean, median, the 10th
and 90th percentiles and the worst take. One easy take can hide a bad one in a mean.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from inference.config import ModelConfig
from inference.metrics import psnr
from inference.model.pipeline import SplatSAP, build_model
from inference.train.data import FrameSource, Preprocessor
from inference.train.depth_figures import stage1_absrel, stage1_scale_split
from inference.train.losses import ssim_map

STAGE2_PARTS = ("depth_init.", "depth_refine.", "colour_init.", "gaussian_plane.", "splatting.")
VANISHED_TOLERANCE = 0.30  # |rendered depth / truth - 1| beyond which a person's pixel counts as gone
# Per-take figures and whether higher is better (the worst take is then the lowest).
# People first (docs/design.md, "Measuring the model"): the person-mask PSNR, vanished and the rendered
# person depth lead every table.
TAKE_FIGURES = {"psnr_mask": True, "vanished": False, "view_depth_absrel_person": False, "psnr": True, "ssim": True,
                "ssim_mask": True, "depth_absrel": False}


def sets_per_take(source: FrameSource, k: int) -> list[int]:
    """The indices of `k` frame sets of each take of `source`, spread evenly over the take (its first
    and last among them), in order: a set's figures at a fraction of the cost, every take still counted."""
    if k < 1:
        raise ValueError(f"sets per take must be at least 1, got {k}")
    by_take: dict[object, list[int]] = defaultdict(list)
    positions = getattr(source, "positions", None) or [(0, i) for i in range(len(source))]
    for index, (take, _) in enumerate(positions):
        by_take[take].append(index)
    picks = []
    for indices in by_take.values():
        n, m = len(indices), min(k, len(indices))
        picks += sorted({indices[int(round(i * (n - 1) / max(1, m - 1)))] for i in range(m)})
    return picks


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


def view_depth_errors(depth: torch.Tensor, alpha: torch.Tensor, truth: np.ndarray, mask: Optional[np.ndarray] = None) -> np.ndarray:
    """|rendered depth / truth - 1| of one rendered view (1, 1, H, W) on the pixels the truth has and
    the render covers (accumulated opacity over one half), optionally within a mask."""
    d = depth[0, 0].detach().float().cpu().numpy()
    keep = (truth > 0) & (alpha[0, 0].detach().float().cpu().numpy() > 0.5) & (d > 0)
    if mask is not None:
        keep &= mask
    return np.abs(d[keep] / truth[keep] - 1.0)


def vanished_pixels(depth: torch.Tensor, alpha: torch.Tensor, truth: np.ndarray, mask: np.ndarray,
                    tolerance: float = VANISHED_TOLERANCE) -> tuple[int, int]:
    """(pixels off, pixels counted) of one rendered view (1, 1, H, W) on the person `mask`'s pixels
    that have ground truth: off where |depth / truth - 1| > `tolerance`, or where the render left
    the pixel empty (accumulated opacity at most one half, or no depth), as a person who is not drawn
    where they stand is gone from the view however the background happens to fill it."""
    d = depth[0, 0].detach().float().cpu().numpy()
    a = alpha[0, 0].detach().float().cpu().numpy()
    keep = np.asarray(mask, bool) & (truth > 0)
    d, t, a = d[keep], truth[keep], a[keep]
    drawn = (a > 0.5) & (d > 0)
    close = np.zeros_like(drawn)
    close[drawn] = np.abs(d[drawn] / t[drawn] - 1.0) <= tolerance
    return int(keep.sum() - close.sum()), int(keep.sum())


def percentile(values, q: float) -> float:
    """The q-th percentile of `values` as numpy computes it by default (linear interpolation
    between the two nearest ranks: rank q/100 * (n - 1) from 0): with 20 takes the 10th percentile
    lies 0.9 of the way from the lowest take to the second lowest."""
    return float(np.percentile(np.asarray(values, np.float64), q))


def spread(values, higher_is_better: bool = True) -> Optional[dict]:
    """The spread over takes of one per-take figure: mean, median, 10th and 90th percentiles
    (`percentile`), min, max, and the worst take's value (the min where higher is better, else the
    max). None where no take has the figure."""
    v = [float(x) for x in values if x is not None and np.isfinite(x)]
    if not v:
        return None
    r = lambda x: round(x, 5)
    return {"takes": len(v), "mean": r(float(np.mean(v))), "median": r(float(np.median(v))), "p10": r(percentile(v, 10)),
            "p90": r(percentile(v, 90)), "min": r(min(v)), "max": r(max(v)), "worst": r(min(v) if higher_is_better else max(v))}


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

    def extend(self, other: "_Scores") -> None:
        for f in ("psnr", "ssim", "psnr_mask", "ssim_mask"):
            getattr(self, f).extend(getattr(other, f))

    def summary(self) -> dict:
        def mean(x):
            return round(float(np.mean(x)), 4) if x else None

        return {"psnr": mean(self.psnr), "ssim": mean(self.ssim), "psnr_mask": mean(self.psnr_mask),
                "ssim_mask": mean(self.ssim_mask), "views": len(self.psnr)}


@dataclass
class _Take:
    """What one take gathers for one pipeline: its views' scores, the person pixels its depth
    left behind (vanished), the rendered depth's AbsRel on people per view, stage 1's AbsRel."""

    scores: _Scores
    off: int = 0
    person: int = 0
    person_absrel: list = None
    depth_absrel: list = None

    @classmethod
    def new(cls) -> "_Take":
        return cls(_Scores.new(), 0, 0, [], [])

    def summary(self) -> dict:
        s = self.scores.summary()
        s["vanished"] = round(self.off / self.person, 5) if self.person else None
        s["view_depth_absrel_person"] = round(float(np.mean(self.person_absrel)), 5) if self.person_absrel else None
        s["depth_absrel"] = round(float(np.mean(self.depth_absrel)), 5) if self.depth_absrel else None
        return s


class _Gathered:
    """What an evaluation gathers over its frame sets, per pipeline, camera and take."""

    def __init__(self) -> None:
        self.per_cam: dict[str, dict[str, _Scores]] = defaultdict(lambda: defaultdict(_Scores.new))
        self.per_take: dict[str, dict[str, _Take]] = defaultdict(lambda: defaultdict(_Take.new))
        self.exposure: dict[str, dict] = {}  # take -> person pixels, supervision pixels, nearest person depth
        self.worst_view: dict[str, dict] = {}  # take -> the model's lowest-PSNR view in it
        self.absrel: list[float] = []
        self.absrel_person: list[float] = []
        self.absrel_single: list[float] = []
        self.view_absrel: list[float] = []
        self.view_absrel_person: list[float] = []
        self.split: list[tuple[float, float]] = []
        self.scales: dict[str, list[tuple[int, np.ndarray]]] = defaultdict(list)

    def stage1(self, affine, L, R, fs, source: FrameSource, pre: Preprocessor, sizes, take: str) -> dict:
        """Stage 1's depth figures of one frame set against the sources' truth; returns that truth
        at the coarse size (empty where a source has no depth)."""
        if not all(fs.depth.get(c) is not None for c in (source.left, source.right)):
            return {}
        gt_coarse = {c: pre.depth(fs.depth[c], fs.cameras[c], sizes.coarse) for c in (source.left, source.right)}
        set_absrel = stage1_absrel(affine, L, R, fs, source, gt_coarse, sizes.coarse)
        self.absrel += set_absrel
        self.per_take["model"][take].depth_absrel.extend(set_absrel)
        self.absrel_single += stage1_absrel(affine, L, R, fs, source, gt_coarse, sizes.coarse, single=True)
        self.split += stage1_scale_split(affine, L, R, fs, source, gt_coarse, sizes.coarse)
        if all(fs.masks.get(c) is not None for c in (source.left, source.right)):
            masks = {c: pre.depth(fs.masks[c].astype(np.float32), fs.cameras[c], sizes.coarse) > 0.5 for c in (source.left, source.right)}
            self.absrel_person += stage1_absrel(affine, L, R, fs, source, gt_coarse, sizes.coarse, masks)
        return gt_coarse

    def expose(self, take: str, fs) -> dict:
        """The take's exposure record, with this set's nearest person depth in any camera."""
        ex = self.exposure.setdefault(take, {"person_px": 0, "px": 0, "nearest": float("inf")})
        for c, m in fs.masks.items():
            if m is not None and m.any() and fs.depth.get(c) is not None:
                ex["nearest"] = min(ex["nearest"], float(fs.depth[c][m & (fs.depth[c] > 0)].min(initial=np.inf)))
        return ex

    def score(self, name: str, take: str, sup: str, out: dict, target, mask, gt_view, person_absrel: Optional[list] = None) -> None:
        """One pipeline's view in camera `sup`: image figures, and where it renders depth, the
        vanished pixels and the depth error on the person mask."""
        self.per_cam[name][sup].add(out["image"], target, mask)
        t = self.per_take[name][take]
        t.scores.add(out["image"], target, mask)
        if "depth" in out and gt_view is not None and mask is not None:
            off, counted = vanished_pixels(out["depth"], out["alpha"], gt_view, mask)
            t.off += off
            t.person += counted
            err = view_depth_errors(out["depth"], out["alpha"], gt_view, mask)
            if err.size:
                t.person_absrel.append(float(err.mean()))
                if person_absrel is not None:
                    person_absrel.append(float(err.mean()))

    def model_view(self, take: str, sup: str, index: int, fs, out: dict, target, mask, gt_view) -> None:
        """The model's own view: scored, the take's worst view kept, its depth against the truth."""
        self.score("model", take, sup, out, target, mask, gt_view, self.view_absrel_person)
        last = self.per_take["model"][take].scores.psnr[-1]
        if take not in self.worst_view or last < self.worst_view[take]["psnr"]:
            self.worst_view[take] = {"frame_set_index": index, "set": fs.set, "camera": sup, "psnr": round(last, 4)}
        if gt_view is not None:
            view_err = view_depth_errors(out["depth"], out["alpha"], gt_view)
            self.view_absrel.append(float(view_err.mean()) if view_err.size else float("nan"))

    def scale_jitter(self) -> list[float]:
        """Relative change of stage 1's scale between consecutive sets of each take."""
        jitter = []
        for rows in self.scales.values():
            rows.sort()
            for (a, sa), (b, sb) in zip(rows, rows[1:]):
                jitter.append(float(np.mean(np.abs(sb - sa) / np.abs(sa))))
        return jitter

    def pipelines(self) -> dict:
        """Per pipeline: overall and per-camera scores, vanished, per-take figures and their spread."""
        out = {}
        for name, cams in self.per_cam.items():
            all_scores = _Scores.new()
            for sc in cams.values():
                all_scores.extend(sc)
            takes = {}
            off = person = 0
            for take, t in self.per_take[name].items():
                takes[take] = t.summary()
                off, person = off + t.off, person + t.person
                if name == "model":
                    ex = self.exposure[take]
                    takes[take]["person_share"] = round(ex["person_px"] / ex["px"], 5) if ex["px"] else None
                    takes[take]["nearest_person_m"] = round(ex["nearest"], 3) if np.isfinite(ex["nearest"]) else None
                    takes[take]["worst_view"] = self.worst_view.get(take)
            figures = [f for f in TAKE_FIGURES if any(t.get(f) is not None for t in takes.values())]
            out[name] = {"overall": all_scores.summary(), "cameras": {c: sc.summary() for c, sc in sorted(cams.items())},
                         "vanished": round(off / person, 5) if person else None,
                         "takes": takes, "spread": {f: spread([t[f] for t in takes.values()], TAKE_FIGURES[f]) for f in figures}}
        return out

    def result(self, sets: int, every: int, supervision: list) -> dict:
        out = self.pipelines()
        jitter = self.scale_jitter()
        model_figures = out.pop("model", {})
        absrel, split, view_absrel = self.absrel, self.split, self.view_absrel
        return {
            "sets": sets, "every": every, "supervision": list(supervision),
            **model_figures,
            "depth_absrel": round(float(np.mean(absrel)), 5) if absrel else None,
            "depth_absrel_person": round(float(np.mean(self.absrel_person)), 5) if self.absrel_person else None,
            "depth_absrel_single": round(float(np.mean(self.absrel_single)), 5) if self.absrel_single else None,
            # The depth the model renders in each supervision camera against that camera's truth: what
            # the image is drawn at, after depth init, refinement and splatting (stage 1's AbsRel above
            # is on the sources' pixels both see; it misses what only one sees and what the target adds).
            "view_depth_absrel": round(float(np.nanmean(view_absrel)), 5) if view_absrel else None,
            "view_depth_absrel_person": round(float(np.mean(self.view_absrel_person)), 5) if self.view_absrel_person else None,
            # Where stage 1's depth error lies: its scale per source and frame set (median depth over
            # truth) and its shape (AbsRel once each is divided by that median).
            "depth_scale": {"median_ratio_min": round(min(m for m, _ in split), 4), "median_ratio_max": round(max(m for m, _ in split), 4),
                            "absrel_scale_free": round(float(np.mean([a for _, a in split])), 5)} if split else None,
            "scale_jitter": {"mean": round(float(np.mean(jitter)), 6), "max": round(float(np.max(jitter)), 6), "pairs": len(jitter)} if jitter else None,
            "references": out,
        }


@torch.no_grad()
def evaluate(model: SplatSAP, source: FrameSource, every: int = 1, max_sets: Optional[int] = None,
             references: bool = True, progress: Optional[Callable[[int, int], None]] = None,
             device: Optional[torch.device] = None, oracles: Optional[dict[str, SplatSAP]] = None,
             own_oracle: bool = True, picks: Optional[list[int]] = None) -> dict:
    """`device`: where the model runs (None: where its parameters are). Frames are read and
    resampled on the CPU, then moved there; the figures are computed on the CPU (in fp32).
    `oracles`: further oracle pipelines (e.g. `oracle_twin` of an untrained model: the oracle with
    untrained stage 2) measured as references beside `oracle` under their names; `own_oracle`
    False leaves out `oracle` itself (the oracle with this model's stage 2), a third of a long
    run's time where only the acceptance references are wanted. `picks`: the frame sets to measure
    (indices into `source`, e.g. `sets_per_take`) instead of every `every`-th one."""
    if device is not None:
        model = model.to(device)
    device = next(model.parameters()).device
    model = model.eval()
    sizes = model.cfg.sizes
    pre = Preprocessor()
    twins = {}
    if references:
        if own_oracle:
            twins["oracle"] = oracle_twin(model).to(device)
        twins.update({name: o.to(device).eval() for name, o in (oracles or {}).items()})
    picks = (list(picks) if picks is not None else list(range(0, len(source), every)))[: max_sets or None]
    g = _Gathered()
    for n, index in enumerate(picks):
        fs = source.frame_set(index, with_truth=True)
        L = pre.views(fs, [source.left], sizes.fine).to(device)
        R = pre.views(fs, [source.right], sizes.fine).to(device)
        # stage 1 once per set: it does not depend on the target (the views below reuse it)
        _, affine, stage1 = model.run_stage1(L.images, R.images, L.K, R.K, L.poses, R.poses)
        seq, _, set_no = fs.key.rpartition("#")
        take = seq or "all"
        g.scales[seq].append((int(set_no) if set_no.isdigit() else index, affine.scale[0].float().cpu().numpy().astype(np.float64)))
        ex = g.expose(take, fs)
        gt_coarse = g.stage1(affine, L, R, fs, source, pre, sizes, take)
        twin_stage1 = {}
        if references and gt_coarse:
            depth_in = [torch.from_numpy(gt_coarse[c])[None, None].to(device) for c in (source.left, source.right)]
            twin_stage1 = {name: twin.run_stage1(L.images, R.images, L.K, R.K, L.poses, R.poses, *depth_in)[2] for name, twin in twins.items()}
        for sup in source.supervision:
            T = pre.views(fs, [sup], sizes.output).to(device)
            mask = None
            if fs.masks.get(sup) is not None:
                mask = pre.depth(fs.masks[sup].astype(np.float32), fs.cameras[sup], sizes.output) > 0.5
                ex["person_px"] += int(mask.sum())
            ex["px"] += sizes.output[0] * sizes.output[1]
            gt_view = pre.depth(fs.depth[sup], fs.cameras[sup], sizes.output) if fs.depth.get(sup) is not None else None
            args = (L.images, R.images, L.K, R.K, L.poses, R.poses, T.K, T.poses)
            g.model_view(take, sup, index, fs, model.run_view(stage1, *args), T.images, mask, gt_view)
            if references:
                for name, twin in twins.items():
                    if name in twin_stage1:
                        g.score(name, take, sup, twin.run_view(twin_stage1[name], *args), T.images, mask, gt_view)
                nearer = min((source.left, source.right), key=lambda c: np.linalg.norm(fs.cameras[c].center - fs.cameras[sup].center))
                g.score("nearest_source", take, sup, {"image": pre.views(fs, [nearer], sizes.output).images.to(device)}, T.images, mask, gt_view)
        if progress is not None:
            progress(n + 1, len(picks))
    return g.result(len(picks), every, source.supervision)


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


def _f(v, fmt: str, scale: float = 1.0) -> str:
    return (fmt % (v * scale)) if v is not None else "-"


def vanished_lines(result: dict) -> list[str]:
    """The "vanished" figure of an `evaluate` result and of its oracle references, as text lines."""
    if result.get("vanished") is None:
        return []
    refs = [f"{name} {100 * r['vanished']:.2f} %" for name, r in result.get("references", {}).items() if r.get("vanished") is not None]
    return [f"vanished (person-mask pixels rendered over {100 * VANISHED_TOLERANCE:.0f} % off in depth, or left empty): "
            f"{100 * result['vanished']:.2f} %" + (f" ({', '.join(refs)})" if refs else "")]


def take_lines(result: dict, seeds: Optional[dict[str, int]] = None) -> list[str]:
    """One line per take: its exposure to people, the model's figures and the references' PSNR."""
    takes = result.get("takes") or {}
    refs = result.get("references", {})
    head = (f"{'take':10s} {'seed':>5s} {'person':>6s} {'nearest':>7s} {'PSNR p':>6s} {'vanish':>6s} {'depth p':>7s} "
            f"{'PSNR':>6s} {'SSIM':>5s} {'SSIM p':>6s}" + "".join(f" {name[:14]:>14s}" for name in refs))
    lines = [head]
    for take, t in takes.items():
        seed = (seeds or {}).get(take)
        lines.append(f"{take[:10]:10s} {seed if seed is not None else '-':>5} {_f(t.get('person_share'), '%5.1f%%', 100):>6s} "
                     f"{_f(t.get('nearest_person_m'), '%6.2fm'):>7s} {_f(t.get('psnr_mask'), '%6.2f'):>6s} "
                     f"{_f(t.get('vanished'), '%5.1f%%', 100):>6s} {_f(t.get('view_depth_absrel_person'), '%6.1f%%', 100):>7s} "
                     f"{_f(t['psnr'], '%6.2f'):>6s} {_f(t['ssim'], '%5.3f'):>5s} {_f(t.get('ssim_mask'), '%6.3f'):>6s}"
                     + "".join(f" {_f(r.get('takes', {}).get(take, {}).get('psnr_mask'), '%14.2f'):>14s}" for r in refs.values()))
    lines.append("(person: share of the supervision pixels; nearest: smallest person depth in any camera; PSNR p / SSIM p: on "
                 "the person masks; vanish: person pixels drawn over 30 % off in depth or not at all; depth p: rendered depth "
                 "AbsRel on the person masks; the references' columns: their PSNR on the person masks)")
    return lines


SPREAD_LABELS = {"psnr": ("PSNR dB", "%.2f", 1), "ssim": ("SSIM", "%.3f", 1), "psnr_mask": ("PSNR person dB", "%.2f", 1),
                 "ssim_mask": ("SSIM person", "%.3f", 1), "view_depth_absrel_person": ("depth on people %", "%.1f", 100),
                 "vanished": ("vanished %", "%.1f", 100), "depth_absrel": ("stage-1 AbsRel %", "%.2f", 100)}


def spread_lines(result: dict) -> list[str]:
    """The spread over takes of every per-take figure, for the model and each reference: mean,
    median, the 10th-percentile take counted from the bad side (the 10th percentile where higher is
    better, the 90th for errors) and the worst take."""
    rows = [("model", result)] + list(result.get("references", {}).items())
    lines = [f"{'':16s} {'figure':18s} {'mean':>7s} {'median':>7s} {'10% bad':>7s} {'worst':>7s}  (over {len((result.get('takes') or {}))} takes)"]
    for name, r in rows:
        for fig, s in (r.get("spread") or {}).items():
            if s is None:
                continue
            label, fmt, k = SPREAD_LABELS[fig]
            tail = s["p10"] if TAKE_FIGURES[fig] else s["p90"]
            lines.append(f"{name[:16]:16s} {label:18s} {fmt % (k * s['mean']):>7s} {fmt % (k * s['median']):>7s} "
                         f"{fmt % (k * tail):>7s} {fmt % (k * s['worst']):>7s}")
    return lines
