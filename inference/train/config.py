"""Typed training configuration (saved with every checkpoint).

The paper's self-supervised schedule: stage 1 trains the backbone and the affine transform with the
rendering loss of the point maps in the supervision cameras plus gamma times the 6-D Chamfer
regulariser; stage 2 freezes them and trains depth refinement, colour blending and the Gaussian
plane with lambda_fine * L(C, I) + lambda_render * L(render, I), L = beta_l1 L1 + beta_ssim (1 - SSIM).
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import Any

from inference.config import ModelConfig, Sizes
from inference.errors import InferenceError
from inference.train.depth_supervision import RECIPES, DepthSupervision
from inference.train.multiview_depth import MultiViewDepthConfig

# Backbones that start from weights the user gives (--weights) rather than from scratch.
PRETRAINED_BACKBONES = ("mast3r",)


@dataclass
class StageSchedule:
    steps: int = 1000
    lr: float = 2e-4
    batch: int = 2  # frame sets per step (the global batch, split across processes)
    warmup: int = 50  # linear learning-rate warm-up steps, then cosine decay to lr * final_lr
    final_lr: float = 0.1
    grad_clip: float = 1.0
    views: int = 0  # supervision views rendered per frame set in a step (0: TrainConfig.supervision_per_step)

    def check(self, where: str) -> None:
        if not isinstance(self.steps, int) or self.steps < 0:
            raise InferenceError(f"{where}.steps must be an integer >= 0, got {self.steps!r}")
        if not isinstance(self.batch, int) or self.batch < 1:
            raise InferenceError(f"{where}.batch must be an integer >= 1, got {self.batch!r}")
        if not isinstance(self.views, int) or self.views < 0:
            raise InferenceError(f"{where}.views must be an integer >= 0, got {self.views!r}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise InferenceError(f"{where}.lr must be a finite number > 0, got {self.lr!r}")
        if not (self.grad_clip > 0 and math.isfinite(self.grad_clip)):
            raise InferenceError(f"{where}.grad_clip must be a finite number > 0, got {self.grad_clip!r}")
        if not (self.final_lr >= 0 and math.isfinite(self.final_lr)):
            raise InferenceError(f"{where}.final_lr must be a finite number >= 0, got {self.final_lr!r}")
        if not isinstance(self.warmup, int) or self.warmup < 0:
            raise InferenceError(f"{where}.warmup must be an integer >= 0, got {self.warmup!r}")


@dataclass
class LossWeights:
    gamma: float = 0.5  # stage 1: weight of the 6-D Chamfer regulariser
    lambda_fine: float = 0.5  # stage 2: the blended colour C at the fine size
    lambda_render: float = 0.5  # stage 2: the splatted render at the output size
    beta_l1: float = 0.8
    beta_ssim: float = 0.2


@dataclass
class TrainConfig:
    model: ModelConfig = field(default_factory=lambda: ModelConfig.for_backbone("stereo", Sizes.preset("preview")))
    stage1: StageSchedule = field(default_factory=lambda: StageSchedule(steps=2000, lr=3e-4, batch=2))
    # Stage 2 renders the whole pipeline per view (about 5 s a view at the preview size on 2 CPU cores): one view per step.
    stage2: StageSchedule = field(default_factory=lambda: StageSchedule(steps=1000, lr=2e-4, batch=1, views=1))
    loss: LossWeights = field(default_factory=LossWeights)
    supervision_per_step: int = 2  # supervision cameras rendered per frame set in a step (a stage's `views` overrides it)
    # The Chamfer regulariser's weight ramps from 0 to gamma between these fractions of stage 1. The
    # paper starts from MASt3R's pretrained point maps, whose two views already agree; from scratch,
    # the Chamfer's pull between two wrong point maps drags both towards each other (nearer, flatter:
    # AbsRel 0.38 -> 0.51 in 50 steps here) faster than the rendering loss can correct them. The
    # rendering loss shapes the geometry first; the full paper objective holds after the ramp.
    chamfer_start: float = 0.5
    chamfer_ramp: float = 0.1
    point_radius: int = 1  # stage-1 point splat window half-size (target pixels)
    # Stage 1's rendering loss is the mean over these downscales of the coarse size (1 = the coarse
    # size itself). A splatted point's gradient reaches only the pixels its kernel covers; at 1/2 and
    # 1/4 the same kernel spans 2 and 4 times the distance, so a point map that is off by more than a
    # pixel or two still learns which way to move (monodepth and self-supervised MVS use the same trick).
    render_scales: tuple[int, ...] = (1, 2, 4)
    # A plane-sweep backbone's whole depth distribution is rendered too (weight of that term; 0: off):
    # every plane of every pixel at its probability, composited in the supervision views at the
    # backbone's volume size. Its gradient reaches every plane, not only the expected depth's
    # neighbourhood: which plane re-projects the colours right is learned directly. Rendering only
    # the expected depth, people stayed doubled in the supervision views after 600 steps.
    plane_render: float = 1.0
    # Weight of stage 1's rendering loss itself (the point maps splatted into the supervision views;
    # 0: not rendered at all). With the supervised recipe, 0 (and plane_render, mvs_depth and
    # loss.gamma 0) is depth-only pre-training, as GPS-Gaussian's first stage learns disparity alone
    # before any rendering: a step is the backbone and the affine transform only, several times cheaper.
    stage1_render: float = 1.0
    # Stage 1 also pulls each source's depth towards multi-view stereo depth from its nearest
    # supervision cameras (inference/train/multiview_depth.py: images and calibration only, never
    # ground truth) on the pixels where that depth is trusted: |log z - log z_mvs|, times this weight
    # (0: off, the paper's objective alone). It stands in for the pretraining a from-scratch backbone
    # lacks (MASt3R's). Computed once per frame set and cached in the output folder (mvs-depth/).
    mvs_depth: float = 1.0
    mvs_neighbours: int = 2  # supervision cameras nearest each source that it is matched against
    mvs: MultiViewDepthConfig = field(default_factory=MultiViewDepthConfig)
    frame_stride: int = 1  # use every k-th set of each sequence for training
    eval_every: int = 200  # steps between evaluations (sample PNG, loss curve, held-out PSNR)
    eval_sets: int = 4  # held-out frame sets rendered at each evaluation
    checkpoint_every: int = 100  # steps between checkpoints (one is also written at each evaluation and at the end)
    # Every this many steps the weights alone are also kept as snapshots/step-NNNNNN.pt (0: none), for
    # a validation curve measured on held-out takes by another process (benchmarks/validation_curve.py)
    # while the run goes on: the run's own evaluations read its training takes.
    snapshot_every: int = 0
    seed: int = 0
    # A pretrained backbone (mast3r, PRETRAINED_BACKBONES) stays frozen in stage 1 unless this is set
    # (fine-tuning); backbones trained from scratch (stereo, tiny) always train.
    train_backbone: bool = False
    # Not in the paper: stage 2 also trains stage 1 (the backbone, as train_backbone allows, and the
    # affine transform) through the whole pipeline, at this fraction of stage 2's learning rate
    # (0: stage 1 frozen, the paper's schedule). Stage 1's own losses never see what its points do
    # to a rendered view: its rendering loss splats them alone, where an unsure point (low opacity)
    # costs little, while at run time depth initialisation lets the wall behind an unsure person
    # show through it. The view's photometric loss reaches the points and their opacity through
    # depth initialisation's soft z-buffer.
    stage2_trains_stage1: float = 0.0
    # Learning-rate multipliers by parameter name prefix, e.g. {"point_init.cascade.": 10}: a module
    # added to trained weights (config.GROWN_FROM_ZERO) learns from scratch at a rate the trained
    # rest would not stand. The longest matching prefix wins; the stage's own factor multiplies it.
    lr_factors: dict = field(default_factory=dict)
    # What stage 1 learns from (docs/training.md, "Recipes"). "self-supervised": images and
    # calibration only, any take. "supervised": also the take's ground-truth depth (simulator takes
    # only; a recorded take is refused): stage 1's depth after the affine transform against the
    # truth on every pixel it covers, with the weights of `depth_supervision`
    # (inference/train/depth_supervision.py), on top of the self-supervised terms; stage 2 as before
    # (and where stage2_trains_stage1 > 0, the depth terms keep holding stage 1 there too).
    recipe: str = "self-supervised"
    depth_supervision: DepthSupervision = field(default_factory=DepthSupervision)
    # The supervised recipe only: stage 2 also pulls each supervision view's refined depth (depth
    # refinement's output, the fine size) towards the view's ground truth, mean |log d - log d*| over
    # the pixels the truth covers plus the person pixels again at depth_supervision.person, times this
    # weight (0: off). Without it depth refinement learns only from the rendered colour, and it left
    # depth init's error where it was (refined = initial within 0.1 %, docs/model.md).
    view_depth: float = 0.0
    # The supervised recipe only: stage 2's rendering losses (the fine colour and the rendered image)
    # again over each supervision view's person pixels (the truth's masks), times this weight (0:
    # off). People are 2 to 15 % of the pixels: trained on the whole image, stage 2 fed the true depth
    # drew people 3.6 dB worse than the untrained stage 2 and the rest 1.1 dB better (docs/model.md).
    render_person: float = 0.0

    @property
    def supervised(self) -> bool:
        return self.recipe == "supervised"

    def check(self) -> None:
        self.stage1.check("stage1")
        self.stage2.check("stage2")
        if self.recipe not in RECIPES:
            raise InferenceError(f"recipe {self.recipe!r}: give one of {', '.join(RECIPES)}")
        self.depth_supervision.check()
        if self.model.backbone.kind == "oracle":
            raise InferenceError("the oracle backbone reads ground-truth depth: it cannot be trained self-supervised")
        if not (0 <= self.chamfer_start <= 1 and 0 <= self.chamfer_ramp <= 1):
            raise InferenceError("chamfer_start and chamfer_ramp are fractions of stage 1, from 0 to 1")
        if not self.render_scales or any(not isinstance(v, int) or v < 1 for v in self.render_scales):
            raise InferenceError(f"render_scales must be integers >= 1, got {self.render_scales!r}")
        if not isinstance(self.train_backbone, bool):
            raise InferenceError(f"train_backbone must be true or false, got {self.train_backbone!r}")
        if not (isinstance(self.stage2_trains_stage1, (int, float)) and self.stage2_trains_stage1 >= 0):
            raise InferenceError(f"stage2_trains_stage1 must be a number >= 0, got {self.stage2_trains_stage1!r}")
        if not (isinstance(self.stage1_render, (int, float)) and not isinstance(self.stage1_render, bool)
                and self.stage1_render >= 0 and math.isfinite(self.stage1_render)):
            raise InferenceError(f"stage1_render must be a number >= 0, got {self.stage1_render!r}")
        if (self.stage1.steps > 0 and self.stage1_render == 0 and not self.supervised and self.plane_render == 0
                and self.mvs_depth == 0 and self.loss.gamma == 0):
            raise InferenceError("stage 1 has nothing to learn from: stage1_render, plane_render, mvs_depth and loss.gamma are all 0 "
                                 "and the recipe is self-supervised (give the supervised recipe, or a weight above 0)")
        if not (isinstance(self.mvs_depth, (int, float)) and self.mvs_depth >= 0):
            raise InferenceError(f"mvs_depth must be a number >= 0, got {self.mvs_depth!r}")
        for name, reads in (("view_depth", "the views' ground-truth depth"), ("render_person", "the views' person masks from the truth")):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0 and math.isfinite(v)):
                raise InferenceError(f"{name} must be a number >= 0, got {v!r}")
            if v > 0 and not self.supervised:
                raise InferenceError(f"{name} reads {reads}: it needs the supervised recipe")
        try:
            self.mvs.check()
        except ValueError as exc:
            raise InferenceError(str(exc)) from None
        def factor_ok(prefix, value) -> bool:
            return isinstance(prefix, str) and bool(prefix) and isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0 and math.isfinite(value)

        if not isinstance(self.lr_factors, dict) or not all(factor_ok(k, v) for k, v in self.lr_factors.items()):
            raise InferenceError(f"lr_factors must map parameter name prefixes to numbers > 0, got {self.lr_factors!r}")
        if not isinstance(self.snapshot_every, int) or isinstance(self.snapshot_every, bool) or self.snapshot_every < 0:
            raise InferenceError(f"snapshot_every must be an integer >= 0, got {self.snapshot_every!r}")
        for name in ("mvs_neighbours", "supervision_per_step", "frame_stride", "eval_every", "checkpoint_every", "eval_sets"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise InferenceError(f"{name} must be an integer >= 1, got {v!r}")

    @property
    def backbone_trainable(self) -> bool:
        return self.model.backbone.kind not in PRETRAINED_BACKBONES or bool(self.train_backbone)

    def lr_factor(self, name: str) -> float:
        """The learning-rate multiplier of the parameter called `name` (lr_factors: the longest matching prefix, else 1)."""
        matches = [k for k in self.lr_factors if name.startswith(k)]
        return float(self.lr_factors[max(matches, key=len)]) if matches else 1.0

    def gamma_at(self, step: int) -> float:
        """The Chamfer weight at stage-1 step `step` (0-based)."""
        n = max(1, self.stage1.steps)
        start = self.chamfer_start * n
        ramp = self.chamfer_ramp * n
        if step < start:
            return 0.0
        return self.loss.gamma * (1.0 if ramp <= 0 else min(1.0, (step - start + 1) / ramp))

    @property
    def total_steps(self) -> int:
        return self.stage1.steps + self.stage2.steps

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True, indent=1)

    @classmethod
    def from_dict(cls, d: dict[str, Any], saved: bool = False) -> "TrainConfig":
        """`saved`: a whole configuration a run recorded (see ModelConfig.from_dict)."""
        if not isinstance(d, dict):
            raise InferenceError("training config: expected an object")
        d = dict(d)
        model = None
        if "model" in d:
            given = d.pop("model")
            model = ModelConfig.from_dict(given if saved else _over_default_model(given), saved=saved)
        cfg = _build(cls, d, "train")
        if model is not None:
            cfg.model = model
        cfg.check()
        return cfg


def _over_default_model(given: Any) -> Any:
    """A "model" section a user writes: its keys over rig train's default model of the backbone it
    names (stereo at the preview size unless it says otherwise), section by section, as every other
    key of a training configuration overrides its default."""
    if not isinstance(given, dict):
        return given  # ModelConfig.from_dict says what is wrong with it
    backbone = given.get("backbone")
    kind = backbone.get("kind") if isinstance(backbone, dict) else None
    default = TrainConfig().model
    base = ModelConfig.for_backbone(kind, default.sizes) if isinstance(kind, str) and kind != default.backbone.kind else default
    out = base.to_dict()
    for section, value in given.items():
        if isinstance(value, dict) and isinstance(out.get(section), dict):
            out[section] = {**out[section], **value}
        else:
            out[section] = value
    return out


def _build(cls, d: dict, where: str):
    known = {f.name for f in fields(cls)}
    unknown = set(d) - known
    if unknown:
        raise InferenceError(f"{where}: unknown keys {sorted(unknown)} (allowed: {', '.join(sorted(known))})")
    defaults = cls()
    kwargs = {}
    for name, value in d.items():
        current = getattr(defaults, name)
        if is_dataclass(current):
            if not isinstance(value, dict):
                raise InferenceError(f"{where}.{name}: expected a table")
            kwargs[name] = _build(type(current), value, f"{where}.{name}")
        elif isinstance(current, tuple):
            if not isinstance(value, (list, tuple)):
                raise InferenceError(f"{where}.{name}: expected a list, got {value!r}")
            kwargs[name] = tuple(value)
        elif isinstance(current, bool) or not isinstance(current, (int, float)):
            kwargs[name] = value
        elif isinstance(current, int) and not isinstance(value, int):
            raise InferenceError(f"{where}.{name}: expected an integer, got {value!r}")
        elif not isinstance(value, (int, float)) or isinstance(value, bool):
            raise InferenceError(f"{where}.{name}: expected a number, got {value!r}")
        elif not math.isfinite(value):  # JSON's 1e400 reads as inf; NaN and Infinity as such
            raise InferenceError(f"{where}.{name}: expected a finite number, got {value!r}")
        else:
            kwargs[name] = type(current)(value)
    return cls(**kwargs)
