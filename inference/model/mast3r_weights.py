"""Loading the public MASt3R checkpoint (a file the user gives: it is never downloaded nor shipped).

The official file (MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth) is a torch pickle
{"model": state dict, "args": argparse.Namespace(model="AsymmetricMASt3R(...)"), ...}. It is read
with torch.load(weights_only=True) (argparse.Namespace allowed, nothing else executed), memory-mapped.

Strict matching: every key of the official layout (for the depths the file records) must be there
with its shape, and no other key; the first difference is named in a one-line InferenceError. Our
module (inference.model.mast3r.MASt3RNet) uses the official parameter names; KEY_MAP lists where
the official state dict differs from ours:

| official key | ours |
|---|---|
| `mask_token` (1, 1, 768) | none: CroCo's pre-training mask token, unused by MASt3R (shape checked, dropped) |
| `downstream_headN.dpt.scratch.layer_rn.K.weight` | `downstream_headN.dpt.scratch.layer{K+1}_rn.weight`: the official head registers each projection twice (one tensor under two names); the two must be equal |

The architecture string the file records (`args.model`) gives the depths (enc_depth, dec_depth;
reduced-depth files in the same layout are accepted, e.g. for tests) and must name the equations
this module implements: 'exp' depth mode, confidence 1 + exp, descriptor confidence exp, RoPE100,
'catmlp+dpt' with 24-d descriptors and two confidences. A file without it (a bare state dict) is
taken as the full-depth model. The weights are licensed CC BY-NC-SA 4.0 (LICENCE).
"""
from __future__ import annotations

import argparse
import ast
import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn as nn

from inference.errors import InferenceError
from inference.model.mast3r import CHECKPOINT_NAME, MASt3RArch, MASt3RNet

LICENCE = ("the MASt3R weights (naver/mast3r) are licensed CC BY-NC-SA 4.0: non-commercial use only, share-alike; "
           "rig does not ship them, and a model exported or trained from them carries their licence")

# Keywords of the recorded architecture string that the state dict's shapes cannot show, and the
# values this implementation computes (official defaults apply to keywords the string leaves out).
ARCH_ARGS = {
    "pos_embed": "RoPE100",
    "head_type": "catmlp+dpt",
    "output_mode": "pts3d+desc24",
    "depth_mode": ("exp", float("-inf"), float("inf")),
    "conf_mode": ("exp", 1, float("inf")),
    "desc_conf_mode": ("exp", 0, float("inf")),
    "desc_mode": "norm",
    "two_confs": True,
    "patch_size": 16,
}
# AsymmetricMASt3R's (CroCo's) defaults for keywords a recorded string may omit.
ARCH_DEFAULTS = {"enc_depth": 12, "dec_depth": 8, "pos_embed": "cosine", "head_type": "linear", "output_mode": "pts3d",
                 "depth_mode": ("exp", float("-inf"), float("inf")), "conf_mode": ("exp", 1, float("inf")),
                 "desc_conf_mode": None, "desc_mode": "norm", "two_confs": False, "patch_size": 16}
ARCH_CLASSES = ("AsymmetricMASt3R",)

_ALIAS = re.compile(r"^(downstream_head[12]\.dpt\.scratch\.)layer_rn\.([0-3])\.weight$")
DROPPED = {"mask_token"}


def official_to_ours(key: str) -> str | None:
    """Our key for an official one (KEY_MAP): None for a dropped entry."""
    if key in DROPPED:
        return None
    m = _ALIAS.match(key)
    if m:
        return f"{m.group(1)}layer{int(m.group(2)) + 1}_rn.weight"
    return key


def official_layout(arch: MASt3RArch) -> dict[str, tuple[int, ...]]:
    """Every key and shape of the official state dict for `arch` (ours, plus KEY_MAP's extra entries)."""
    with torch.device("meta"):
        net = MASt3RNet(arch)
    ours = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    layout = {"mask_token": (1, 1, arch.dec_dim)}
    layout.update(ours)
    for head in ("downstream_head1", "downstream_head2"):
        for k in range(4):
            layout[f"{head}.dpt.scratch.layer_rn.{k}.weight"] = ours[f"{head}.dpt.scratch.layer{k + 1}_rn.weight"]
    return layout


@dataclass
class MASt3RWeights:
    path: Path
    state_dict: dict[str, torch.Tensor]  # official keys
    arch: MASt3RArch
    recorded: str | None  # the architecture string the file records, if any


def _fmt(shape) -> str:
    return "(" + ", ".join(str(int(s)) for s in shape) + ")"


def _literal(node: ast.AST):
    """A keyword value of the recorded string: literals, tuples, inf and -inf (no evaluation)."""
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.Tuple):
        return tuple(_literal(e) for e in node.elts)
    if isinstance(node, ast.Name) and node.id == "inf":
        return float("inf")
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        return -_literal(node.operand)
    raise ValueError(ast.dump(node))


def parse_arch_string(text: str, source: str) -> dict:
    """The class name and keywords of a recorded "AsymmetricMASt3R(k=v, ...)" string."""
    try:
        call = ast.parse(text.strip(), mode="eval").body
        if not isinstance(call, ast.Call) or not isinstance(call.func, ast.Name) or call.args:
            raise ValueError("not a call with keywords")
        kw = {k.arg: _literal(k.value) for k in call.keywords}
    except (SyntaxError, ValueError) as exc:
        raise InferenceError(f"{source}: its recorded architecture {text[:80]!r} cannot be read ({exc})") from None
    return {"class": call.func.id, **kw}


def _recorded_arch(data: dict) -> str | None:
    args = data.get("args")
    if isinstance(args, argparse.Namespace):
        args = vars(args)
    if isinstance(args, dict) and isinstance(args.get("model"), str):
        return args["model"]
    return None


def arch_from_record(recorded: str | None, source: str) -> tuple[MASt3RArch, dict]:
    if recorded is None:
        return MASt3RArch(), {}
    kw = parse_arch_string(recorded, source)
    if kw["class"] not in ARCH_CLASSES:
        raise InferenceError(f"{source}: a {kw['class']} checkpoint, not {CHECKPOINT_NAME} (an AsymmetricMASt3R)")
    depths = {k: kw.get(k, ARCH_DEFAULTS[k]) for k in ("enc_depth", "dec_depth")}
    for k, v in depths.items():
        if not isinstance(v, int) or isinstance(v, bool) or v < (2 if k == "dec_depth" else 1):
            raise InferenceError(f"{source}: its recorded architecture has {k}={v!r} (this backbone needs enc_depth >= 1, dec_depth >= 2)")
    return MASt3RArch(encoder_blocks=depths["enc_depth"], decoder_blocks=depths["dec_depth"]), kw


def check_recorded_equations(kw: dict, source: str) -> None:
    """The recorded keywords the shapes cannot show must be the ones implemented (ARCH_ARGS)."""
    for key, want in ARCH_ARGS.items():
        have = kw.get(key, ARCH_DEFAULTS.get(key))
        if key == "desc_conf_mode" and have is None:
            have = kw.get("conf_mode", ARCH_DEFAULTS["conf_mode"])  # the official default: the points' confidence mode
        if have != want:
            raise InferenceError(f"{source}: recorded architecture has {key}={have!r}; this MASt3R backbone implements {key}={want!r} "
                                 f"({CHECKPOINT_NAME})")


def check_layout(state: dict, arch: MASt3RArch, source: str) -> None:
    """Strict key and shape matching against the official layout; the first difference (in the
    file's order) is named in one line."""
    expected = official_layout(arch)
    where = f"{source}: not the {CHECKPOINT_NAME} layout"
    depth = f" ({arch.encoder_blocks} encoder, {arch.decoder_blocks} decoder blocks)"
    missing = [k for k in expected if k not in state]
    for key, value in state.items():
        if not isinstance(value, torch.Tensor):
            raise InferenceError(f"{where}: entry {key} is a {type(value).__name__}, not a tensor")
        if key not in expected:
            hint = f"; missing {missing[0]} {_fmt(expected[missing[0]])}" if missing else ""
            raise InferenceError(f"{where}{depth}: unexpected key {key} {_fmt(value.shape)}{hint}")
        if tuple(value.shape) != expected[key]:
            raise InferenceError(f"{where}{depth}: {key} has shape {_fmt(value.shape)}, expected {_fmt(expected[key])}")
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise InferenceError(f"{where}{depth}: missing key {missing[0]} {_fmt(expected[missing[0]])}{more}")


def to_our_state_dict(state: dict, source: str) -> dict[str, torch.Tensor]:
    """The official state dict under our names (KEY_MAP); call check_layout first."""
    ours: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        if value.is_meta:
            raise InferenceError(f"{source}: entry {key} holds no data (a meta tensor)")
        mine = official_to_ours(key)
        if mine is None:
            continue
        if mine != key:  # a second name of one of our tensors
            if not torch.equal(state[mine], value):
                raise InferenceError(f"{source}: {key} and {mine} differ; in the official model they are one tensor")
            continue
        ours[key] = value
    return ours


def read_weights(path: str | os.PathLike) -> MASt3RWeights:
    """Read and check a MASt3R checkpoint file. One-line InferenceError for a missing, unreadable
    (truncated, corrupt) or foreign file, or one of another layout."""
    path = Path(path)
    if not path.is_file():
        raise InferenceError(f"{path}: no such MASt3R weights file")
    data = None
    error: Exception | None = None
    for mmap in (True, False):  # memory-mapped where the file's format allows it
        try:
            with torch.serialization.safe_globals([argparse.Namespace]):
                data = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
            break
        except Exception as exc:  # truncated zip, foreign pickle, not a torch file at all ...
            error = exc
    if data is None:
        text = str(error).strip().splitlines()[0].split(". ")[0] if str(error).strip() else ""
        if "Unsupported global" in str(error) or "weights_only" in str(error):
            found = re.search(r"GLOBAL ([\w.]+)", str(error))
            what = found.group(1) if found else type(error).__name__
            raise InferenceError(f"{path}: holds a Python object ({what}) besides tensors and the recorded arguments; "
                                 f"not loaded (only argparse.Namespace is accepted)") from None
        raise InferenceError(f"{path}: not a readable torch checkpoint (truncated or corrupt? {type(error).__name__}: {text[:120]})") from None
    if isinstance(data, dict) and data.get("format") == "splat-sap":
        raise InferenceError(f"{path}: a Splat-SAP checkpoint (give it as --checkpoint), not MASt3R weights")
    recorded = _recorded_arch(data) if isinstance(data, dict) else None
    state = data.get("model") if isinstance(data, dict) and "model" in data else data
    if not isinstance(state, dict) or not state:
        raise InferenceError(f"{path}: not a MASt3R checkpoint (no state dict under 'model')")
    arch, kw = arch_from_record(recorded, str(path))
    check_layout(state, arch, str(path))
    if kw:
        check_recorded_equations(kw, str(path))
    return MASt3RWeights(path, state, arch, recorded)


def load_into(net: MASt3RNet, weights: MASt3RWeights | dict, source: str = "weights", assign: bool = False) -> None:
    """Strictly load official-layout weights into `net` (checked first: one-line errors)."""
    if isinstance(weights, MASt3RWeights):
        state, source = weights.state_dict, str(weights.path)
        if weights.arch != net.arch:
            raise InferenceError(f"{source}: has {weights.arch.encoder_blocks} encoder and {weights.arch.decoder_blocks} decoder blocks; "
                                 f"the model is configured for {net.arch.encoder_blocks} and {net.arch.decoder_blocks}")
    else:
        state = weights
        check_layout(state, net.arch, source)
    net.load_state_dict(to_our_state_dict(state, source), strict=True, assign=assign)


def backbone_net(model: nn.Module) -> MASt3RNet:
    """The MASt3R network of a Splat-SAP model (InferenceError if its backbone is another)."""
    net = getattr(getattr(model, "point_init", None), "net", None)
    if not isinstance(net, MASt3RNet):
        kind = getattr(getattr(getattr(model, "cfg", None), "backbone", None), "kind", "?")
        raise InferenceError(f"--weights loads MASt3R weights, but the model's backbone is {kind}")
    return net
