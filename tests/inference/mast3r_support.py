"""Random weights in the official MASt3R checkpoint layout (no checkpoint can be downloaded here),
for the mast3r tests. The layout comes from the official table (mast3r_layout_table), reduced in
depth by keeping the first blocks, not from the code under test."""
from __future__ import annotations

import argparse
import math
import re
from pathlib import Path

import torch
from mast3r_layout_table import official_table

ARCH = ("AsymmetricMASt3R(pos_embed='RoPE100', patch_embed_cls='ManyAR_PatchEmbed', img_size=(512, 512), head_type='catmlp+dpt', "
        "output_mode='pts3d+desc24', depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), enc_embed_dim=1024, enc_depth={enc}, "
        "enc_num_heads=16, dec_embed_dim=768, dec_depth={dec}, dec_num_heads=12, two_confs=True, desc_conf_mode=('exp', 0, inf))")
_BLOCK = re.compile(r"^(enc_blocks|dec_blocks2?)\.(\d+)\.")
_ALIAS = re.compile(r"^(downstream_head[12]\.dpt\.scratch\.)layer_rn\.(\d)\.weight$")


def official_layout(enc: int = 24, dec: int = 12) -> dict[str, tuple[int, ...]]:
    """The table's keys with the first `enc` encoder and `dec` decoder blocks (the heads' shapes do not depend on depth)."""
    out = {}
    for key, shape in official_table().items():
        m = _BLOCK.match(key)
        if m and int(m.group(2)) >= (enc if m.group(1) == "enc_blocks" else dec):
            continue
        out[key] = shape
    return out


def random_state(layout: dict[str, tuple[int, ...]], seed: int = 0, device=None) -> dict[str, torch.Tensor]:
    """Random tensors of the layout's shapes: weights of variance 1/fan_in, small biases, LayerNorm
    scales near 1. The DPT heads' last layer puts the points about 2 m ahead (confidence ~2.6):
    an image the rest of the pipeline can splat. The official state dict holds each DPT projection
    under two names (one tensor): so does this one."""
    g = torch.Generator().manual_seed(seed)
    state: dict[str, torch.Tensor] = {}
    for key, shape in layout.items():
        m = _ALIAS.match(key)
        if m:
            continue
        t = torch.empty(shape, device=device)
        if device == "meta":
            state[key] = t
            continue
        if "norm" in key and key.endswith(".weight"):
            t.uniform_(0.9, 1.1, generator=g)
        elif len(shape) == 1:
            t.uniform_(-0.02, 0.02, generator=g)
        else:
            fan_in = math.prod(shape[1:]) if key != "mask_token" else shape[-1]
            a = math.sqrt(3.0 / fan_in)
            t.uniform_(-a, a, generator=g)
        state[key] = t
    for head in ("downstream_head1", "downstream_head2"):
        w, b = f"{head}.dpt.head.4.weight", f"{head}.dpt.head.4.bias"
        if w in state and device != "meta":
            state[w].mul_(1e-2)
            state[b].copy_(torch.tensor([0.0, 0.0, math.log1p(2.0), 0.5]))
    ordered = {}
    for key in layout:
        m = _ALIAS.match(key)
        ordered[key] = state[f"{m.group(1)}layer{int(m.group(2)) + 1}_rn.weight"] if m else state[key]
    return ordered


def write_checkpoint(path: Path, state: dict, enc: int, dec: int, with_args: bool = True) -> Path:
    """The official file's format: {"model": state dict, "args": Namespace(model=<architecture>)}."""
    data = {"model": state, "epoch": 0}
    if with_args:
        data["args"] = argparse.Namespace(model=ARCH.format(enc=enc, dec=dec), lr=1e-4)
    torch.save(data, path)
    return path
