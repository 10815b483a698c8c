"""Typed configuration of the Splat-SAP pipeline.

Plain dataclasses (no torch), so the runtime and the command line can read a model's configuration
from the ONNX file's metadata without importing torch. Sizes are (width, height) in pixels.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import Any

from inference.errors import InferenceError

STAGES = (
    "point_init",
    "affine_transform",
    "depth_init",
    "depth_refine",
    "colour_init",
    "gaussian_plane",
    "splatting",
)
"""The paper's per-module timing breakdown (its Table 'Time cost of our pipeline'), in run order."""

SIZE_PRESETS: dict[str, dict[str, tuple[int, int]]] = {
    # The paper's sizes: stage 1 at 512x288, stage 2 at 1024x576, rendered at 1280x720.
    "paper": {"coarse": (512, 288), "fine": (1024, 576), "output": (1280, 720)},
    # Half the paper's sizes: what a CPU runs in reasonable time.
    "preview": {"coarse": (256, 144), "fine": (512, 288), "output": (640, 360)},
    # Small enough for unit tests and quick exports.
    "test": {"coarse": (128, 64), "fine": (256, 144), "output": (320, 180)},
}


@dataclass
class Sizes:
    coarse: tuple[int, int] = (512, 288)
    fine: tuple[int, int] = (1024, 576)
    output: tuple[int, int] = (1280, 720)

    def __post_init__(self) -> None:
        self.coarse = tuple(int(v) for v in self.coarse)
        self.fine = tuple(int(v) for v in self.fine)
        self.output = tuple(int(v) for v in self.output)
        for name in ("coarse", "fine", "output"):
            w, h = getattr(self, name)
            if w <= 0 or h <= 0:
                raise InferenceError(f"size {name}: width and height must be positive, got {w}x{h}")
        # Stage 2 builds its cost volume at a quarter of the fine size; the backbone works on patches of 16.
        if self.fine[0] % 4 or self.fine[1] % 4:
            raise InferenceError(f"size fine: {self.fine[0]}x{self.fine[1]} must be a multiple of 4 in both axes")
        if self.coarse[0] % 16 or self.coarse[1] % 16:
            raise InferenceError(f"size coarse: {self.coarse[0]}x{self.coarse[1]} must be a multiple of 16 in both axes")

    @classmethod
    def preset(cls, name: str) -> "Sizes":
        if name not in SIZE_PRESETS:
            raise InferenceError(f"unknown size preset '{name}' (allowed: {', '.join(SIZE_PRESETS)})")
        return cls(**SIZE_PRESETS[name])

    def describe(self) -> dict[str, str]:
        return {k: f"{w}x{h}" for k, (w, h) in asdict(self).items()}


BACKBONE_KINDS = ("tiny", "stereo", "oracle", "mast3r")
# Backbones whose point maps are metric out of the box: stage 1's scaling S starts at 1 for them
# (Stage1Config.scale_reference = "one") instead of at the baseline.
METRIC_BACKBONES = ("mast3r",)


@dataclass
class BackboneConfig:
    kind: str = "tiny"  # tiny | stereo | oracle | mast3r
    # oracle: "metric" keeps ground-truth metres; "canonical" divides both point maps by their mean
    # distance to the left camera, as DUSt3R/MASt3R normalise theirs.
    oracle_scale: str = "metric"
    patch: int = 16
    dim: int = 192
    heads: int = 4
    encoder_blocks: int = 4
    decoder_blocks: int = 4
    # stereo: plane sweep between the calibrated views (inference.model.stereo_backbone)
    stereo_features: int = 32
    stereo_groups: int = 8
    stereo_depths: int = 48
    stereo_near: float = 0.5  # nearest plane, in baselines (the mean of the planes' inverse depths, an untrained
    # model's depth, is then about one baseline: the centre of an arc rig)
    stereo_far: float = 10.0  # farthest plane, in baselines
    # A second, local sweep at the coarse size around the volume's depth (CasMVSNet's cascade): this
    # many depth hypotheses (0: none, as in models saved before it), spread over +-stereo_cascade_range
    # in log depth. The volume is matched at 1/4 of the coarse size, where a person is a few cells wide.
    stereo_cascade: int = 0
    stereo_cascade_range: float = 0.35
    # The sweep reads the source images at this multiple of the coarse size (2: the fine images at
    # every preset), so its volume's cells are 4 / stereo_input_scale coarse pixels wide; the point
    # maps stay at the coarse size. No weight depends on it (the networks are convolutions).
    stereo_input_scale: int = 1
    # mast3r: the public MASt3R checkpoint's network (inference.model.mast3r); every width is the
    # checkpoint's, only the depths may be reduced (tests, quick CPU runs). The weights' file says
    # its own depths (its recorded architecture), and loading it sets these.
    mast3r_encoder_blocks: int = 24
    mast3r_decoder_blocks: int = 12

    def __post_init__(self) -> None:
        if self.kind not in BACKBONE_KINDS:
            raise InferenceError(f"backbone: unknown kind '{self.kind}' (allowed: {', '.join(BACKBONE_KINDS)})")
        if self.kind == "mast3r":
            # The DPT reads decoder blocks L/2, 3L/4 and L: at least 2 of them.
            for name, least in (("mast3r_encoder_blocks", 1), ("mast3r_decoder_blocks", 2)):
                v = getattr(self, name)
                if not isinstance(v, int) or isinstance(v, bool) or v < least:
                    raise InferenceError(f"backbone: {name} must be an integer >= {least}, got {v!r}")
            if self.patch != 16:
                raise InferenceError(f"backbone: mast3r works on 16x16 patches, got patch {self.patch}")
        if self.kind == "stereo":
            if self.stereo_features % self.stereo_groups:
                raise InferenceError(f"backbone: stereo_features ({self.stereo_features}) must be a multiple of stereo_groups ({self.stereo_groups})")
            if not 0 < self.stereo_near < self.stereo_far:
                raise InferenceError(f"backbone: need 0 < stereo_near < stereo_far, got {self.stereo_near}, {self.stereo_far}")
            if self.stereo_depths < 2 or self.patch % 4:
                raise InferenceError("backbone: stereo needs at least 2 depths and a patch that is a multiple of 4")
            s = self.stereo_input_scale
            if not isinstance(s, int) or isinstance(s, bool) or not 1 <= s <= 4:
                raise InferenceError(f"backbone: stereo_input_scale must be an integer from 1 to 4, got {s!r}")
            if not isinstance(self.stereo_cascade, int) or isinstance(self.stereo_cascade, bool) or self.stereo_cascade < 0 or self.stereo_cascade == 1:
                raise InferenceError(f"backbone: stereo_cascade must be 0 (off) or an integer >= 2, got {self.stereo_cascade!r}")
            if not 0 < self.stereo_cascade_range < 2:
                raise InferenceError(f"backbone: stereo_cascade_range must lie in (0, 2), got {self.stereo_cascade_range!r}")
        if self.oracle_scale not in ("metric", "canonical"):
            raise InferenceError(f"backbone: oracle_scale must be metric or canonical, got '{self.oracle_scale}'")


@dataclass
class Stage1Config:
    # "learned": S and T from the networks; "bypass": S = 1, T = 0 (metric point maps, e.g. the oracle).
    affine: str = "learned"
    attention_dim: int = 128
    attention_heads: int = 4
    pe_frequencies: int = 6
    mlp_hidden: int = 128
    feature_dim: int = 64  # channels of the convolutional encoder E_c
    hidden_dim: int = 64  # ConvGRU state
    iterations: int = 4
    stride: int = 4  # the ConvGRU runs at 1/stride of the coarse size
    # Bounds that keep training stable (an unbounded update once sent T to tens of metres, every point
    # behind the cameras, and no gradient came back): each ConvGRU iteration moves T by at most
    # translation_step baselines per axis (tanh), and log(S / baseline) stays within +-scale_log_range.
    translation_step: float = 0.05
    scale_log_range: float = 2.0
    # What S multiplies exp(r tanh(MLP / r)) by, i.e. S of an untrained model: "baseline" for a
    # canonical point map (mean distance 1), "one" for metric point maps (the MASt3R metric checkpoint).
    scale_reference: str = "baseline"
    # After S and T: both point maps scaled by the factor (within 1 +- scale_search_range, from
    # scale_search candidates) at which the two sources re-project best onto each other
    # (inference/model/scale_search.py; no weights). 0: off (the shipped model has it on: 21);
    # training stage 1 with it on is untried.
    scale_search: int = 0
    scale_search_range: float = 0.2
    scale_search_floor: float = 0.0  # the softmin's temperature floor, a part of the mean error (ScaleSearch)
    # T scaled by each point's opacity (1 - 1/confidence) to this power; 0: T as learned.
    translation_gate: float = 0.0
    # T keeps only its part along each point's ray from its own camera: T moves a point nearer or
    # farther, never off the pixel it came from (a calibrated backbone's points lie on their rays).
    translation_along_rays: bool = False
    # S as one factor for all three axes, its depth axis' (the one depth supervision trains): a
    # calibrated backbone's points stay on their rays. Three factors (the paper's S) scale x and y
    # apart from depth and move every point off its pixel in proportion to its distance from the
    # optical axis (people41-f: x 4.08, y 2.83, z 3.69 baselines; heads and outstretched arms landed
    # on the wall in the novel view, docs/model.md).
    isotropic_scale: bool = False

    def __post_init__(self) -> None:
        if self.affine not in ("learned", "bypass"):
            raise InferenceError(f"stage1: affine must be learned or bypass, got '{self.affine}'")
        if self.scale_reference not in ("baseline", "one"):
            raise InferenceError(f"stage1: scale_reference must be baseline or one, got '{self.scale_reference}'")
        if not isinstance(self.scale_search, int) or isinstance(self.scale_search, bool) or self.scale_search < 0 or self.scale_search == 1:
            raise InferenceError(f"stage1: scale_search must be 0 (off) or an integer >= 2, got {self.scale_search!r}")
        if not 0 < self.scale_search_range < 1:
            raise InferenceError(f"stage1: scale_search_range must be between 0 and 1, got {self.scale_search_range!r}")
        if not (isinstance(self.scale_search_floor, (int, float)) and 0 <= self.scale_search_floor < 1):
            raise InferenceError(f"stage1: scale_search_floor must be in [0, 1), got {self.scale_search_floor!r}")
        if not (isinstance(self.translation_gate, (int, float)) and self.translation_gate >= 0):
            raise InferenceError(f"stage1: translation_gate must be >= 0, got {self.translation_gate!r}")
        if not isinstance(self.translation_along_rays, bool):
            raise InferenceError(f"stage1: translation_along_rays must be true or false, got {self.translation_along_rays!r}")
        if not isinstance(self.isotropic_scale, bool):
            raise InferenceError(f"stage1: isotropic_scale must be true or false, got {self.isotropic_scale!r}")


ZBUFFERS = ("occlusion", "reference")


@dataclass
class DepthInitConfig:
    # Splat window half-size in fine target pixels: (2r+1)^2 pixels per point. Stage 1's points are
    # about 2 target pixels apart (the coarse size is half the fine one): radius 2 covers the gaps.
    radius: int = 2
    # How the splats at a target pixel blend (see depth_init): "occlusion", coverage nearer than the
    # margin hides a splat; "reference", the soft z-buffer of models saved before "occlusion" existed.
    zbuffer: str = "occlusion"
    occlusion_gain: float = 5.0  # a splat behind coverage c keeps exp(-gain c) of its weight
    occlusion_margin: float = 0.3  # log depth (35 %): only coverage nearer than this occludes
    depth_bin: float = 0.15  # log-depth bin of the coverage histogram (the margin spans >= 2 bins)
    depth_span: float = 3.0  # the bins cover the view's mean log depth +- this (20x nearer or farther)
    front_tolerance: float = 0.02  # "reference" only: softness of its z-buffer, relative depth
    fill_levels: int = 6  # push-pull levels that fill pixels no point reached
    # A point's coverage is its stage-1 opacity raised to this power (0: every point covers fully).
    opacity_power: float = 1.0
    # Splat at 1/scale of the fine size (radius in those pixels), then resize the filled depth to
    # the fine size (`upsample`: "nearest" keeps a person's edge against the wall behind as one
    # depth or the other; "bilinear" blends them). scale 2 with radius 2 covers what radius 4 covers
    # at the fine size with a ninth of the histogram and a third of the splats (docs/model.md).
    scale: int = 1
    upsample: str = "nearest"

    def __post_init__(self) -> None:
        if self.zbuffer not in ZBUFFERS:
            raise InferenceError(f"depth_init: zbuffer must be one of {', '.join(ZBUFFERS)}, got '{self.zbuffer}'")
        if not (isinstance(self.radius, int) and 0 <= self.radius <= 4):
            raise InferenceError(f"depth_init: radius must be an integer from 0 to 4, got {self.radius!r}")
        if not (self.depth_bin > 0 and self.depth_span >= 2 * self.depth_bin and self.occlusion_margin >= 2 * self.depth_bin):
            raise InferenceError("depth_init: depth_bin must be positive, and depth_span and occlusion_margin at least two bins")
        if self.occlusion_gain < 0:
            raise InferenceError(f"depth_init: occlusion_gain must be >= 0, got {self.occlusion_gain}")
        if not (isinstance(self.opacity_power, (int, float)) and self.opacity_power >= 0):
            raise InferenceError(f"depth_init: opacity_power must be >= 0, got {self.opacity_power!r}")
        if self.scale not in (1, 2, 4):
            raise InferenceError(f"depth_init: scale must be 1, 2 or 4, got {self.scale!r}")
        if self.upsample not in ("nearest", "bilinear"):
            raise InferenceError(f"depth_init: upsample must be nearest or bilinear, got {self.upsample!r}")


@dataclass
class Stage2Config:
    feature_dim: int = 16  # channels of the fine encoder E_f (at 1/4 of the fine size)
    candidates: int = 8  # depth candidates per target ray
    search_range: float = 0.06  # candidates span the initial depth times (1 +- search_range)
    groups: int = 4  # group-wise correlation channels of the cost volume
    volume_dim: int = 8  # channels of the 3D regularisation (the feature volume Phi)
    head_dim: int = 32  # channels of the Gaussian plane heads
    colour_alpha: float = 0.8  # P_c = alpha C + (1 - alpha) dC (the paper's alpha = 0.8)
    gaussian_sigma: float = 0.6  # initial in-plane Gaussian size, in fine pixels
    # Pixels over which a source's visibility fades at its image border: colour init blends the
    # sources by it (a point one source cannot see takes the other's colour), and a narrow ramp
    # makes the blend swing with float rounding of the projection (docs/model.md: on rig model
    # check's synthetic inputs, 8 px came to 9.5e-4 of ONNX Runtime against torch, 16 px to 7.1e-4).
    visibility_ramp: float = 16.0

    def __post_init__(self) -> None:
        if not self.visibility_ramp > 0:
            raise InferenceError(f"stage2: visibility_ramp must be > 0, got {self.visibility_ramp}")


@dataclass
class SplatConfig:
    window: int = 1  # candidate Gaussians per output pixel: (2w+1)^2 fine anchors around it
    max_alpha: float = 0.99
    # Depth order is softened over this relative depth difference: Gaussians of one surface blend
    # by alpha, Gaussians further apart composite in strict 3DGS order (0 = strict order everywhere).
    depth_tolerance: float = 0.02
    blur: float = 0.3  # screen-space low-pass added to each 2D covariance (px^2), as 3DGS does
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        self.background = tuple(float(v) for v in self.background)


@dataclass
class ModelConfig:
    sizes: Sizes = field(default_factory=Sizes)
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    stage1: Stage1Config = field(default_factory=Stage1Config)
    depth_init: DepthInitConfig = field(default_factory=DepthInitConfig)
    stage2: Stage2Config = field(default_factory=Stage2Config)
    splat: SplatConfig = field(default_factory=SplatConfig)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any], saved: bool = False) -> "ModelConfig":
        """`saved`: `d` is a whole configuration a checkpoint or an export recorded; a key it lacks was
        added later and takes the value that reproduces what that model computed (SAVED_BEFORE)."""
        if saved and isinstance(d, dict):
            d = {k: dict(v) if isinstance(v, dict) else v for k, v in d.items()}
            for (section, key), value in SAVED_BEFORE.items():
                if isinstance(d.get(section), dict):
                    d[section].setdefault(key, value)
        return _build(cls, d, "model")

    @classmethod
    def from_json(cls, text: str, saved: bool = False) -> "ModelConfig":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InferenceError(f"model configuration is not valid JSON ({exc.msg})") from None
        return cls.from_dict(d, saved=saved)

    @classmethod
    def for_backbone(cls, kind: str, sizes: Sizes | None = None, **overrides: Any) -> "ModelConfig":
        """The default configuration of a backbone: the oracle gives metric points, so it bypasses the
        affine transform; MASt3R's metric points start the learned scaling at S = 1."""
        cfg = cls(sizes=sizes or Sizes(), backbone=BackboneConfig(kind=kind))
        if kind == "oracle":
            cfg.stage1.affine = "bypass"
        if kind in METRIC_BACKBONES:
            cfg.stage1.scale_reference = "one"
        for key, value in overrides.items():
            section, _, name = key.partition(".")
            setattr(getattr(cfg, section), name, value)
        return cfg


# Keys added after models were first saved, with the value that makes a model saved before them
# compute what it computed then (its weights were trained with it).
SAVED_BEFORE: dict[tuple[str, str], Any] = {
    ("depth_init", "zbuffer"): "reference",
    ("stage2", "visibility_ramp"): 1.0,
}


# Settings that no weight's shape depends on: the sizes (every weight is a convolution, a per-token
# layer or an attention over averaged tokens: a model trained at one size runs and trains at another,
# as the live model is exported at the test size from preview-size weights), how depth init splats and blends, how the Gaussian
# plane is rendered, how colour init fades a source at its border, how far and in how many
# candidates depth refinement searches (its 3-D convolutions slide along the candidates), and stage
# 1's scale search, and the stereo backbone's nearest and farthest planes (the planes' count shapes its
# refinement and tokens; their depths shape nothing, but its logits mean them, so a run that moves them
# retrains the backbone). A run may start from weights trained with other values of these (fine-tuning to them).
WEIGHT_FREE: dict[str, Any] = {"sizes": "*", "depth_init": "*", "splat": "*", "stage2": {"visibility_ramp", "search_range", "candidates"},
                               "stage1": {"scale_search", "scale_search_range", "scale_search_floor", "translation_gate", "translation_along_rays",
                                          "isotropic_scale"},
                               "backbone": {"stereo_cascade_range", "stereo_input_scale", "stereo_near", "stereo_far"}}

# Weight-shaping keys a run may turn on over weights trained without them: the modules they add
# start at zero and compute nothing until trained (section.key -> their parameters' prefix).
GROWN_FROM_ZERO: dict[str, str] = {"backbone.stereo_cascade": "point_init.cascade."}


def weight_differences(a: "ModelConfig", b: "ModelConfig") -> list[str]:
    """The keys ("section.key") in which two configurations differ where weights depend on them."""
    out = []
    da, db = a.to_dict(), b.to_dict()
    for section in sorted(set(da) | set(db)):
        va, vb = da.get(section), db.get(section)
        free = WEIGHT_FREE.get(section, ())
        if free == "*":
            continue
        if isinstance(va, dict) and isinstance(vb, dict):
            out += [f"{section}.{k}" for k in sorted(set(va) | set(vb)) if k not in free and va.get(k) != vb.get(k)]
        elif va != vb:
            out.append(section)
    return out


def _build(cls, d: Any, where: str):
    if not isinstance(d, dict):
        raise InferenceError(f"{where}: expected an object")
    known = {f.name: f for f in fields(cls)}
    unknown = set(d) - set(known)
    if unknown:
        raise InferenceError(f"{where}: unknown keys {sorted(unknown)} (allowed: {', '.join(known)})")
    kwargs = {}
    defaults = cls()
    for name, value in d.items():
        current = getattr(defaults, name)
        if is_dataclass(current):
            kwargs[name] = _build(type(current), value, f"{where}.{name}")
        elif isinstance(current, tuple):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)
