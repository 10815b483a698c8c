"""Stage 1 supervised by ground-truth depth (the `supervised` recipe, simulator takes only).

Stereo matching gives no depth where only one source sees, and the self-supervised losses teach a
backbone trained from scratch little about people (docs/training.md). Where a take has exact depth
(the simulator renders it from the scene), stage 1's metric point maps after the affine transform
(X_t = S X + T) are pulled towards it on every pixel the truth covers, as stereo networks are
pre-trained on synthetic depth before self-supervised fine-tuning on real footage. With
d = log z - log z* per pixel (z each source's depth in its own camera), per frame set over both
sources' pixels together:

- scale-invariant term: mean |d - median(d)| (the L1 form of Eigen et al.'s scale-invariant log
  error; MiDaS aligns scale and shift the same way before comparing): the shape of the depth,
  whatever the global scale. Both sources share one median, so their relative scale counts.
- metric term: mean |d| (L1 on log depth): the metric scale too, which S and T must get right.
  With `confidence_alpha` > 0 it is weighted by the backbone's confidence c >= 1 as DUSt3R and
  MASt3R regress their point maps: mean(c |d| - alpha log c), which also teaches the confidence
  (hence the opacity 1 - 1/c that depth initialisation splats with) to be high where the depth is
  right and low where it is not.

People are a few per cent of the pixels: with every pixel weighing the same, 25 steps from the shipped
model brought the room's depth nearer the truth (all pixels' mean |d| 0.094 -> 0.083 on four training
sets) while the people's went from 15 to 37 % off, the backbone's own depth as much as the translation
(docs/training.md). `person` adds both terms again over the person-mask pixels alone (the truth's
masks), each set's people weighing that much against the rest whatever their share of the image.

Each term is averaged per frame set, then over the batch (so that data-parallel processes, each
averaging its share, step as one process on the whole batch).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from inference.errors import InferenceError

# What each recipe needs from the takes it trains on (docs/training.md, "Recipes").
RECIPES = ("self-supervised", "supervised")


def truth_missing(take: str) -> str:
    """The one line that refuses a take without ground-truth depth under the supervised recipe."""
    return (f"{take}: has no ground-truth depth (a recorded take); the supervised recipe needs simulator takes: "
            "train on real footage with the self-supervised recipe, from a supervised run's weights (rig train ... --init CKPT)")


@dataclass
class DepthSupervision:
    """Weights of the supervised recipe's stage-1 depth terms (TrainConfig.depth_supervision)."""

    scale_invariant: float = 1.0  # weight of mean |d - median d|
    metric: float = 1.0  # weight of mean |d| (or its confidence-weighted form)
    confidence_alpha: float = 0.0  # > 0: the metric term is mean(c |d| - alpha log c) (DUSt3R); 0: plain |d|
    person: float = 1.0  # both terms again over the person-mask pixels alone, at this weight (0: every pixel alike)

    def check(self) -> None:
        for name in ("scale_invariant", "metric", "confidence_alpha", "person"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0:
                raise InferenceError(f"depth_supervision.{name} must be a number >= 0, got {v!r}")
        if self.scale_invariant == 0 and self.metric == 0:
            raise InferenceError("depth_supervision: the supervised recipe needs scale_invariant or metric above 0")


@dataclass
class TruthDepth:
    """Both sources' ground-truth depth at the coarse size (B, H, W), where it holds, and their person masks."""

    left: torch.Tensor
    left_valid: torch.Tensor
    left_person: torch.Tensor
    right: torch.Tensor
    right_valid: torch.Tensor
    right_person: torch.Tensor

    def _map(self, f) -> "TruthDepth":
        return TruthDepth(*(f(t) for t in (self.left, self.left_valid, self.left_person, self.right, self.right_valid, self.right_person)))

    def to(self, device, non_blocking: bool = False) -> "TruthDepth":
        return self._map(lambda t: t.to(device, non_blocking=non_blocking))

    def pin_memory(self) -> "TruthDepth":
        return self._map(lambda t: t.pin_memory())


@dataclass
class DepthTerms:
    scale_invariant: torch.Tensor
    metric: torch.Tensor

    def total(self, w: DepthSupervision) -> torch.Tensor:
        return w.scale_invariant * self.scale_invariant + w.metric * self.metric


def log_ratio(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """log z - log z* (depths clamped to 0.1 mm: a point behind its camera counts as very near)."""
    return torch.log(pred.clamp(min=1e-4)) - torch.log(truth.clamp(min=1e-4))


def _masked_median(d: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The median of each row of d (B, N) over its masked entries (0 where none); no gradient (the
    median only centres the errors, as MiDaS's alignment does)."""
    with torch.no_grad():
        big = torch.finfo(d.dtype).max
        filled = torch.where(mask, d, torch.full_like(d, big))
        n = mask.sum(1)
        srt = filled.sort(dim=1).values
        idx = ((n - 1).clamp(min=0) // 2)[:, None]
        med = srt.gather(1, idx)[:, 0]
        return torch.where(n > 0, med, torch.zeros_like(med))


def depth_terms(preds: list[torch.Tensor], truths: list[torch.Tensor], masks: list[torch.Tensor],
                confidences: list[torch.Tensor] | None = None, alpha: float = 0.0,
                persons: list[torch.Tensor] | None = None, person: float = 0.0) -> DepthTerms:
    """The two terms for B frame sets: per source, predicted depth (B, H, W), true depth (B, H, W),
    where the truth holds (B, H, W) bool and, with `alpha` > 0, the confidence (B, H, W) >= 1. All
    sources of a set share one median for the scale-invariant term. With `person` > 0 and the person
    masks (B, H, W) bool, each term adds `person` times its mean over the person pixels (0 for a set
    without any)."""
    b = preds[0].shape[0]
    d = torch.cat([log_ratio(p, t).reshape(b, -1) for p, t in zip(preds, truths)], dim=1)
    m = torch.cat([k.reshape(b, -1) for k in masks], dim=1) & torch.isfinite(d)
    d = torch.where(m, d, torch.zeros_like(d))
    mf = m.to(d.dtype)
    count = mf.sum(1).clamp(min=1.0)
    med = _masked_median(d, m)
    centred = (d - med[:, None]).abs()
    if alpha > 0 and confidences is not None:
        c = torch.cat([k.reshape(b, -1) for k in confidences], dim=1)
        per_pixel = c * d.abs() - alpha * torch.log(c)
    else:
        per_pixel = d.abs()
    si = ((centred * mf).sum(1) / count).mean()
    metric = ((per_pixel * mf).sum(1) / count).mean()
    if person > 0 and persons is not None:
        pf = (torch.cat([k.reshape(b, -1) for k in persons], dim=1) & m).to(d.dtype)
        pcount = pf.sum(1).clamp(min=1.0)
        si = si + person * ((centred * pf).sum(1) / pcount).mean()
        metric = metric + person * ((per_pixel * pf).sum(1) / pcount).mean()
    return DepthTerms(si, metric)
