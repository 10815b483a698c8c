"""The MASt3R backbone: our implementation of the public checkpoint
"MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric" (naver/mast3r, AsymmetricMASt3R), so that its
weights, given by the user (`--weights PATH`), load with strict key matching.

Architecture (fixed by the checkpoint; only the depths are configurable, for tests and experiments):
- a ViT-Large encoder shared by both views: 16x16 patches to 1024-d tokens, 24 blocks of 16 heads,
  2-D rotary positions (RoPE, frequency 100), final LayerNorm;
- a linear map to 768-d and two ViT-Base decoders (`dec_blocks` for the first view, `dec_blocks2`
  for the second), 12 blocks of 12 heads each; every block cross-attends to the other view's tokens
  of the previous block; final LayerNorm;
- per view a 'catmlp+dpt' head (inference.model.mast3r_heads): DPT on the encoder output and decoder
  blocks 6, 9, 12 -> points ('exp' depth mode) and confidence (1 + exp), and an MLP on the
  concatenated encoder and last decoder tokens -> 24-d local descriptors and their confidence.

Both point maps are in the first view's camera frame, metric for this checkpoint: the first view's
`pts3d` and the second view's `pts3d_in_other_view`. Images enter normalised as MASt3R expects:
(x - 0.5) / 0.5. The coarse size must be a multiple of 16 (inference.config.Sizes checks it).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn

from inference.config import BackboneConfig
from inference.model.backbone import Backbone, PointMaps
from inference.model.mast3r_heads import PointsAndFeaturesHead
from inference.model.mast3r_vit import LAYER_NORM_EPS, DecoderBlock, EncoderBlock, PatchEmbed, rope_tables

CHECKPOINT_NAME = "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric"


@dataclass(frozen=True)
class MASt3RArch:
    """The public checkpoint's architecture (its `args.model` string; see mast3r_weights.ARCH_ARGS)."""

    encoder_blocks: int = 24
    decoder_blocks: int = 12
    enc_dim: int = 1024
    enc_heads: int = 16
    dec_dim: int = 768
    dec_heads: int = 12
    patch: int = 16
    rope_freq: float = 100.0
    desc_dim: int = 24
    desc_conf: bool = True  # two_confs=True: a separate descriptor confidence channel

    def __post_init__(self) -> None:
        if self.encoder_blocks < 1 or self.decoder_blocks < 2:  # the DPT reads decoder blocks L/2, 3L/4, L
            raise ValueError(f"MASt3R needs at least 1 encoder and 2 decoder blocks, got {self.encoder_blocks}, {self.decoder_blocks}")

    @classmethod
    def from_config(cls, cfg: BackboneConfig) -> "MASt3RArch":
        return cls(encoder_blocks=cfg.mast3r_encoder_blocks, decoder_blocks=cfg.mast3r_decoder_blocks)


class MASt3RNet(nn.Module):
    """AsymmetricMASt3R's inference network. Our state dict holds the official names, less the
    entries the official one carries but never uses (see mast3r_weights.KEY_MAP)."""

    def __init__(self, arch: MASt3RArch = MASt3RArch()):
        super().__init__()
        a = arch
        self.arch = arch
        self.patch_embed = PatchEmbed(a.enc_dim, a.patch)
        self.enc_blocks = nn.ModuleList([EncoderBlock(a.enc_dim, a.enc_heads) for _ in range(a.encoder_blocks)])
        self.enc_norm = nn.LayerNorm(a.enc_dim, eps=LAYER_NORM_EPS)
        self.decoder_embed = nn.Linear(a.enc_dim, a.dec_dim)
        self.dec_blocks = nn.ModuleList([DecoderBlock(a.dec_dim, a.dec_heads) for _ in range(a.decoder_blocks)])
        self.dec_blocks2 = nn.ModuleList([DecoderBlock(a.dec_dim, a.dec_heads) for _ in range(a.decoder_blocks)])
        self.dec_norm = nn.LayerNorm(a.dec_dim, eps=LAYER_NORM_EPS)
        head = lambda: PointsAndFeaturesHead(a.enc_dim, a.dec_dim, a.decoder_blocks, a.patch, a.desc_dim, a.desc_conf)  # noqa: E731
        self.downstream_head1 = head()
        self.downstream_head2 = head()
        self._init_weights()

    def _init_weights(self) -> None:
        """Untrained weights (random-weight benchmarks and exports): xavier-uniform linear layers,
        zero biases, unit LayerNorms, as CroCo initialises; convolutions keep torch's default."""
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.LayerNorm):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        w = self.patch_embed.proj.weight
        nn.init.xavier_uniform_(w.view(w.shape[0], -1))

    def forward(self, img1: torch.Tensor, img2: torch.Tensor, descriptors: bool = True) -> tuple[dict, dict]:
        """Images (B, 3, H, W) already normalised to [-1, 1]. Returns (res1, res2) as the official
        model does: res1 pts3d, conf[, desc, desc_conf]; res2 pts3d_in_other_view, conf[, desc,
        desc_conf]; each (B, C, H, W), plus `tokens`: the normalised last decoder tokens (B, h*w, 768)."""
        b, _, hh, ww = img1.shape
        p = self.arch.patch
        grid = (hh // p, ww // p)
        # Both views through the shared encoder in one batch, as the official model encodes a pair.
        x = self.patch_embed(torch.cat([img1, img2], dim=0))
        cos, sin = rope_tables(grid[0], grid[1], self.arch.enc_dim // self.arch.enc_heads, self.arch.rope_freq, x.device, x.dtype)
        for blk in self.enc_blocks:
            x = blk(x, cos, sin)
        x = self.enc_norm(x)
        enc1, enc2 = x[:b], x[b:]
        cos, sin = rope_tables(grid[0], grid[1], self.arch.dec_dim // self.arch.dec_heads, self.arch.rope_freq, x.device, x.dtype)
        f1, f2 = self.decoder_embed(enc1), self.decoder_embed(enc2)
        out1, out2 = [enc1], [enc2]
        for blk1, blk2 in zip(self.dec_blocks, self.dec_blocks2):
            # Each view's block reads the other view's tokens of the previous block.
            f1, f2 = blk1(f1, f2, cos, sin), blk2(f2, f1, cos, sin)
            out1.append(f1)
            out2.append(f2)
        out1[-1] = self.dec_norm(out1[-1])
        out2[-1] = self.dec_norm(out2[-1])
        res1 = self.downstream_head1(out1, grid, descriptors)
        res2 = self.downstream_head2(out2, grid, descriptors)
        res2["pts3d_in_other_view"] = res2.pop("pts3d")
        res1["tokens"] = out1[-1]
        res2["tokens"] = out2[-1]
        return res1, res2


class MASt3RBackbone(Backbone):
    """PointMaps from MASt3R: points of both views in the left camera's frame (metric for the
    metric checkpoint), confidences 1 + exp, the last decoder tokens (768-d) for stage 1's scaling
    head and, when `descriptors` is set, the 24-d local descriptors. The calibration is not read.

    The pipeline does not use the descriptors, so it leaves `descriptors` off (their MLP is about
    a tenth of the network's arithmetic); the weights are there either way."""

    def __init__(self, cfg: BackboneConfig, coarse_size: tuple[int, int], descriptors: bool = False):
        super().__init__()
        self.cfg = cfg
        self.arch = MASt3RArch.from_config(cfg)
        w, h = coarse_size
        self.grid = (h // self.arch.patch, w // self.arch.patch)
        self.token_dim = self.arch.dec_dim
        self.descriptors = descriptors
        self.net = MASt3RNet(self.arch)

    def forward(self, left, right, left_K=None, right_K=None, right_to_left=None, left_depth=None, right_depth=None) -> PointMaps:
        res1, res2 = self.net((left - 0.5) / 0.5, (right - 0.5) / 0.5, descriptors=self.descriptors)
        return PointMaps(
            res1["pts3d"], res2["pts3d_in_other_view"], res1["conf"], res2["conf"], res1["tokens"], res2["tokens"], self.grid,
            descriptors_left=res1.get("desc"), descriptors_right=res2.get("desc"),
        )
