"""The prediction heads of the MASt3R backbone ("catmlp+dpt"): a DPT head for points and confidence,
and an MLP on the concatenated encoder and decoder tokens for the local features (descriptors and
their confidence). Parameter names are the official checkpoint's (`dpt.act_postprocess.0.0`,
`dpt.scratch.refinenet4.resConfUnit1.conv1`, `head_local_features.fc1`, ...).

DPT (Ranftl et al.) as DUSt3R configures it: four token maps (the encoder output and decoder blocks
L/2, 3L/4 and L) are brought to 1/4, 1/8, 1/16 and 1/32 of the image (transposed convolutions, a
strided convolution), projected to 256 channels, fused coarse to fine by residual refinement units
with 2x bilinear upsampling (align_corners=True), and a small convolutional head returns 4 channels
at full size: x, y, z (the 'exp' depth mode: direction times expm1 of the norm) and the confidence
1 + exp(c). The local-feature MLP predicts 16x16 pixels of 24 descriptor channels (L2-normalised)
plus one descriptor confidence (exp, as the metric checkpoint's desc_conf_mode ('exp', 0, inf)).
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from inference.model.mast3r_vit import Mlp

DPT_LAYER_DIMS = (96, 192, 384, 768)
DPT_FEATURES = 256
DPT_LAST = 128


def dpt_hooks(decoder_blocks: int) -> tuple[int, int, int, int]:
    """Which token maps the DPT reads: 0 is the encoder output, k the output of decoder block k."""
    n = decoder_blocks
    return (0, n * 2 // 4, n * 3 // 4, n)


def _up2(x: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)


class ResidualUnit(nn.Module):
    """x + conv2(relu(conv1(relu(x))))."""

    def __init__(self, ch: int):
        super().__init__()
        self.conv1 = nn.Conv2d(ch, ch, 3, padding=1)
        self.conv2 = nn.Conv2d(ch, ch, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """(coarser path [+ residual unit of the skip]) -> residual unit -> 2x up -> 1x1 conv."""

    def __init__(self, ch: int):
        super().__init__()
        self.out_conv = nn.Conv2d(ch, ch, 1)
        self.resConfUnit1 = ResidualUnit(ch)
        self.resConfUnit2 = ResidualUnit(ch)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None) -> torch.Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        return self.out_conv(_up2(self.resConfUnit2(x)))


class Scratch(nn.Module):
    """The projections to 256 channels (layer1_rn..layer4_rn, 3x3, no bias) and the four fusion blocks."""

    def __init__(self, layer_dims=DPT_LAYER_DIMS, features: int = DPT_FEATURES):
        super().__init__()
        for i, d in enumerate(layer_dims, start=1):
            setattr(self, f"layer{i}_rn", nn.Conv2d(d, features, 3, padding=1, bias=False))
        for i in range(1, 5):
            setattr(self, f"refinenet{i}", FusionBlock(features))


class DPT(nn.Module):
    """The DPT adapter for patch 16, as `downstream_headN.dpt` of the checkpoint."""

    def __init__(self, token_dims: tuple[int, int, int, int], hooks: tuple[int, int, int, int], out_channels: int = 4,
                 layer_dims=DPT_LAYER_DIMS, features: int = DPT_FEATURES, last: int = DPT_LAST):
        super().__init__()
        self.hooks = hooks
        d = layer_dims
        self.act_postprocess = nn.ModuleList([
            nn.Sequential(nn.Conv2d(token_dims[0], d[0], 1), nn.ConvTranspose2d(d[0], d[0], 4, stride=4)),  # 1/4
            nn.Sequential(nn.Conv2d(token_dims[1], d[1], 1), nn.ConvTranspose2d(d[1], d[1], 2, stride=2)),  # 1/8
            nn.Sequential(nn.Conv2d(token_dims[2], d[2], 1)),  # 1/16
            nn.Sequential(nn.Conv2d(token_dims[3], d[3], 1), nn.Conv2d(d[3], d[3], 3, stride=2, padding=1)),  # 1/32
        ])
        self.scratch = Scratch(layer_dims, features)
        # Indices 0, 2, 4 hold weights (1: 2x upsampling, 3: ReLU), as in the checkpoint.
        self.head = nn.Sequential(
            nn.Conv2d(features, features // 2, 3, padding=1),
            nn.Upsample(scale_factor=2, mode="bilinear", align_corners=True),
            nn.Conv2d(features // 2, last, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(last, out_channels, 1),
        )

    def forward(self, tokens: list[torch.Tensor], grid: tuple[int, int]) -> torch.Tensor:
        h, w = grid
        maps = []
        for i, hook in enumerate(self.hooks):
            t = tokens[hook]
            # (B, h*w, C) -> (B, C, h, w) as a channels-last view, the memory layout the official
            # model's convolutions see (a contiguous copy takes another kernel: 1e-6 apart).
            x = t.reshape(t.shape[0], h, w, t.shape[2]).permute(0, 3, 1, 2)
            x = self.act_postprocess[i](x)
            maps.append(getattr(self.scratch, f"layer{i + 1}_rn")(x))
        s = self.scratch
        # The 1/32 map is twice the 1/16 one after upsampling, or one more when h or w is odd: crop.
        path = s.refinenet4(maps[3])[:, :, : maps[2].shape[2], : maps[2].shape[3]]
        path = s.refinenet3(path, maps[2])
        path = s.refinenet2(path, maps[1])
        path = s.refinenet1(path, maps[0])
        return self.head(path)


def points_from_raw(xyz: torch.Tensor) -> torch.Tensor:
    """The 'exp' depth mode on (..., 3): the direction of xyz times expm1(|xyz|)."""
    d = xyz.norm(dim=-1, keepdim=True)
    return xyz / d.clamp(min=1e-8) * torch.expm1(d)


class PointsAndFeaturesHead(nn.Module):
    """`downstream_headN`: DPT points + confidence, and the local-feature MLP on [encoder, decoder] tokens."""

    def __init__(self, enc_dim: int, dec_dim: int, decoder_blocks: int, patch: int, desc_dim: int, desc_conf: bool = True):
        super().__init__()
        self.patch = patch
        self.desc_dim = desc_dim
        self.desc_conf = desc_conf
        self.dpt = DPT((enc_dim, dec_dim, dec_dim, dec_dim), dpt_hooks(decoder_blocks))
        cat = enc_dim + dec_dim
        self.head_local_features = Mlp(cat, 4 * cat, (desc_dim + int(desc_conf)) * patch * patch)

    def forward(self, tokens: list[torch.Tensor], grid: tuple[int, int], descriptors: bool = True) -> dict[str, torch.Tensor]:
        """tokens: [encoder output, decoder block 1, ..., decoder block L (normalised)], each (B, h*w, C).
        Returns pts3d (B, 3, H, W), conf (B, 1, H, W) >= 1 and, with `descriptors`, desc (B, D, H, W)
        (unit length) and desc_conf (B, 1, H, W) > 0."""
        out = self.dpt(tokens, grid)  # (B, 4, H, W): x, y, z, confidence
        if descriptors:
            b = tokens[0].shape[0]
            h, w = grid
            feats = self.head_local_features(torch.cat([tokens[0], tokens[-1]], dim=-1))  # (B, h*w, (D+1) p^2)
            feats = F.pixel_shuffle(feats.transpose(1, 2).reshape(b, -1, h, w), self.patch)
            out = torch.cat([out, feats], dim=1)
        # Channels last, as the official post-processing reads them: the same tensors in the same
        # memory order, hence the same float rounding of the norms (expm1 magnifies a last bit).
        fmap = out.permute(0, 2, 3, 1)
        res = {"pts3d": points_from_raw(fmap[..., 0:3]).permute(0, 3, 1, 2), "conf": (1.0 + fmap[..., 3].exp())[:, None]}
        if descriptors:
            desc = fmap[..., 4 : 4 + self.desc_dim]
            res["desc"] = (desc / desc.norm(dim=-1, keepdim=True)).permute(0, 3, 1, 2)
            if self.desc_conf:
                res["desc_conf"] = fmap[..., 4 + self.desc_dim].exp()[:, None]
        return res
