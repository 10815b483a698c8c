"""The MASt3R backbone loads the official checkpoint's layout strictly, and refuses anything else
in one line naming the difference (random weights: no checkpoint can be downloaded here)."""
from __future__ import annotations

import pytest
import torch
from mast3r_layout_table import official_table
from mast3r_support import ARCH, official_layout, random_state, write_checkpoint

from inference.errors import InferenceError
from inference.model.mast3r import MASt3RArch, MASt3RNet
from inference.model.mast3r_weights import arch_from_record, check_layout, check_recorded_equations, load_into, parse_arch_string, read_weights
from inference.model.mast3r_weights import official_layout as our_official_layout


def test_the_official_table_is_the_metric_checkpoint_and_our_layout_matches_it():
    table = official_table()
    assert len(table) == 1017
    assert sum(torch.Size(s).numel() for s in table.values()) == 695_274_376
    assert table["patch_embed.proj.weight"] == (1024, 3, 16, 16)
    assert table["enc_blocks.23.attn.qkv.weight"] == (3072, 1024) and "enc_blocks.24.norm1.weight" not in table
    assert table["dec_blocks2.11.cross_attn.projq.weight"] == (768, 768) and "dec_blocks.12.norm1.weight" not in table
    assert table["downstream_head1.head_local_features.fc2.weight"] == (25 * 256, 4 * 1792)  # 24-d descriptors + their confidence
    assert table["downstream_head2.dpt.head.4.weight"] == (4, 128, 1, 1)  # x, y, z, confidence
    assert our_official_layout(MASt3RArch()) == table


def test_a_full_size_state_dict_in_the_official_layout_loads_strictly():
    # 2.78 GB of random float32 in the official layout, every key of the table; assigned (strict
    # load, no copy) into our full-size module built on the meta device.
    state = random_state(official_table(), seed=1)
    with torch.device("meta"):
        net = MASt3RNet()
    load_into(net, state, "random official weights", assign=True)
    params = dict(net.named_parameters())
    assert not any(p.is_meta for p in params.values())
    assert sum(p.numel() for p in params.values()) == 695_274_376 - 768 - 2 * 256 * (96 + 192 + 384 + 768) * 9  # less mask_token and the DPT aliases
    for key in ("patch_embed.proj.weight", "enc_blocks.23.mlp.fc2.weight", "dec_blocks2.11.norm_y.bias", "downstream_head2.head_local_features.fc2.bias"):
        assert params[key] is state[key] or torch.equal(params[key], state[key])
    assert torch.equal(params["downstream_head1.dpt.scratch.layer4_rn.weight"], state["downstream_head1.dpt.scratch.layer_rn.3.weight"])


class _Pickled:
    pass


def _meta_state():
    return random_state(official_table(), device="meta")


@pytest.mark.parametrize("change, message", [
    (lambda s: s.__setitem__("enc_blocks.7.attn.qkv.weight", torch.empty(3072, 1000, device="meta")),
     "enc_blocks.7.attn.qkv.weight has shape (3072, 1000), expected (3072, 1024)"),
    (lambda s: s.__setitem__("dec_blocks.3.cross_attn.projk.bias", s.pop("dec_blocks.3.cross_attn.projk.bias").new_empty(769)),
     "dec_blocks.3.cross_attn.projk.bias has shape (769), expected (768)"),
])
def test_one_shape_changed_is_refused_naming_key_and_shapes(change, message):
    state = _meta_state()
    change(state)
    with pytest.raises(InferenceError) as err:
        check_layout(state, MASt3RArch(), "w.pth")
    text = str(err.value)
    assert message in text and "\n" not in text and text.startswith("w.pth: not the MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric layout")


def test_one_key_renamed_missing_or_unexpected_is_refused_naming_it():
    state = _meta_state()
    renamed = {("downstream_head1.dpt.head.0.wieght" if k == "downstream_head1.dpt.head.0.weight" else k): v for k, v in state.items()}
    with pytest.raises(InferenceError, match=r"unexpected key downstream_head1\.dpt\.head\.0\.wieght \(128, 256, 3, 3\); "
                                             r"missing downstream_head1\.dpt\.head\.0\.weight \(128, 256, 3, 3\)$"):
        check_layout(renamed, MASt3RArch(), "w.pth")
    missing = dict(state)
    del missing["enc_norm.bias"]
    with pytest.raises(InferenceError, match=r"missing key enc_norm\.bias \(1024\)$"):
        check_layout(missing, MASt3RArch(), "w.pth")
    extra = {**state, "enc_blocks.24.norm1.weight": torch.empty(1024, device="meta")}  # a 25th encoder block
    with pytest.raises(InferenceError, match=r"\(24 encoder, 12 decoder blocks\): unexpected key enc_blocks\.24\.norm1\.weight \(1024\)$"):
        check_layout(extra, MASt3RArch(), "w.pth")


@pytest.fixture(scope="module")
def small_state():
    return random_state(official_layout(1, 2), seed=2)


def test_files_are_read_with_their_recorded_depths_and_bad_files_refused(small_state, tmp_path):
    good = write_checkpoint(tmp_path / "mast3r.pth", small_state, enc=1, dec=2)
    w = read_weights(good)
    assert (w.arch.encoder_blocks, w.arch.decoder_blocks) == (1, 2)
    with torch.device("meta"):
        net = MASt3RNet(w.arch)
    load_into(net, w, assign=True)
    assert torch.equal(net.enc_blocks[0].attn.qkv.weight, small_state["enc_blocks.0.attn.qkv.weight"])

    # Without the recorded architecture the file is taken as the full model: its layout differs
    # (a few entries are enough to show it, and to make files that are cut or not checkpoints).
    few = {k: small_state[k] for k in list(small_state)[:5]}
    bare = write_checkpoint(tmp_path / "bare.pth", few, 1, 2, with_args=False)
    with pytest.raises(InferenceError, match=r"\(24 encoder, 12 decoder blocks\): missing key enc_blocks\.0\.attn\.qkv\.weight \(3072, 1024\) and 1011 more$"):
        read_weights(bare)
    data = bare.read_bytes()
    (tmp_path / "cut.pth").write_bytes(data[: len(data) // 2])
    with pytest.raises(InferenceError, match=r"cut\.pth: not a readable torch checkpoint \(truncated or corrupt\?"):
        read_weights(tmp_path / "cut.pth")
    with pytest.raises(InferenceError, match=r"nope\.pth: no such MASt3R weights file$"):
        read_weights(tmp_path / "nope.pth")
    (tmp_path / "text.pth").write_text("hello")
    with pytest.raises(InferenceError, match="not a readable torch checkpoint"):
        read_weights(tmp_path / "text.pth")
    torch.save({"model": few, "args": _Pickled()}, tmp_path / "code.pth")  # unpickling it would construct an arbitrary object
    with pytest.raises(InferenceError, match=r"code\.pth: holds a Python object \(test_mast3r_layout\._Pickled\) besides tensors"):
        read_weights(tmp_path / "code.pth")
    torch.save({"format": "splat-sap", "version": 1}, tmp_path / "ours.pt")
    with pytest.raises(InferenceError, match=r"a Splat-SAP checkpoint \(give it as --checkpoint\), not MASt3R weights"):
        read_weights(tmp_path / "ours.pt")
    # The equations the shapes cannot show are read from the recorded architecture.
    linear = ARCH.format(enc=1, dec=2).replace("depth_mode=('exp', -inf, inf)", "depth_mode=('linear', -inf, inf)")
    with pytest.raises(InferenceError, match=r"depth_mode=\('linear', -inf, inf\); this MASt3R backbone implements depth_mode=\('exp', -inf, inf\)"):
        check_recorded_equations(parse_arch_string(linear, "w.pth"), "w.pth")
    dust3r = "AsymmetricCroCo3DStereo(pos_embed='RoPE100', head_type='dpt', enc_depth=24, dec_depth=12)"
    with pytest.raises(InferenceError, match=r"a AsymmetricCroCo3DStereo checkpoint, not MASt3R_ViTLarge"):
        arch_from_record(dust3r, "w.pth")
    check_recorded_equations(parse_arch_string(ARCH.format(enc=1, dec=2), "w.pth"), "w.pth")  # the metric checkpoint's: accepted
    # A DPT alias that differs from the tensor it names (one tensor in the official model).
    forged = dict(small_state)
    forged["downstream_head2.dpt.scratch.layer_rn.1.weight"] = forged["downstream_head2.dpt.scratch.layer_rn.1.weight"] + 1
    with pytest.raises(InferenceError, match=r"layer_rn\.1\.weight and downstream_head2\.dpt\.scratch\.layer2_rn\.weight differ"):
        load_into(net, forged, "forged")
