"""The training configuration a user writes (`rig train --config FILE.json`)."""
from __future__ import annotations

import pytest

from inference.config import ModelConfig, Sizes, weight_differences
from inference.errors import InferenceError
from inference.train.config import TrainConfig


def test_a_model_section_overrides_only_its_keys_of_the_default_model():
    default = TrainConfig().model
    cfg = TrainConfig.from_dict({"model": {"stage2": {"search_range": 0.25, "candidates": 12}}})
    assert (cfg.model.stage2.search_range, cfg.model.stage2.candidates) == (0.25, 12)
    # Everything it does not name stays rig train's default (it became the paper-size tiny model).
    assert cfg.model.backbone.kind == default.backbone.kind == "stereo"
    assert cfg.model.sizes == default.sizes
    assert cfg.model.stage2.feature_dim == default.stage2.feature_dim
    assert weight_differences(cfg.model, default) == []


def test_a_model_section_naming_a_backbone_starts_from_that_backbones_defaults():
    cfg = TrainConfig.from_dict({"model": {"backbone": {"kind": "tiny"}}})
    assert cfg.model.backbone.kind == "tiny" and cfg.model.sizes == TrainConfig().model.sizes
    with pytest.raises(InferenceError, match="unknown kind"):
        TrainConfig.from_dict({"model": {"backbone": {"kind": "vit-huge"}}})
    with pytest.raises(InferenceError, match="unknown keys"):
        TrainConfig.from_dict({"model": {"stage3": {}}})
    with pytest.raises(InferenceError, match="expected an object"):
        TrainConfig.from_dict({"model": 3})


def test_depth_refinements_search_may_change_between_runs_but_not_its_networks():
    base = TrainConfig().model
    wider = ModelConfig.from_dict(base.to_dict())
    wider.stage2.search_range, wider.stage2.candidates = 0.25, 12
    assert weight_differences(base, wider) == []  # --init may fine-tune to another search
    other = ModelConfig.from_dict(base.to_dict())
    other.stage2.feature_dim = 24
    assert weight_differences(base, other) == ["stage2.feature_dim"]


def test_lr_factor_takes_the_longest_matching_prefix():
    cfg = TrainConfig(lr_factors={"point_init.": 2, "point_init.cascade.": 10})
    assert cfg.lr_factor("point_init.cascade.refine.2.weight") == 10.0
    assert cfg.lr_factor("point_init.features.0.0.weight") == 2.0
    assert cfg.lr_factor("depth_refine.head.0.weight") == 1.0
    for bad in ({"point_init.": 0}, {"": 2}, {"point_init.": True}, {"point_init.": "2"}):
        with pytest.raises(InferenceError, match="lr_factors"):
            TrainConfig(lr_factors=bad).check()


def test_init_may_change_the_sizes_and_the_stereo_planes_range():
    """A run may start from weights trained at another size (a resolution curriculum; the live model
    is exported at the test size from preview weights) or with the stereo planes elsewhere (the
    run retrains the backbone to them); the planes' count shapes weights and may not change."""
    base = ModelConfig.for_backbone("stereo", Sizes.preset("preview"))
    other = ModelConfig.from_dict(base.to_dict())
    other.sizes = Sizes.preset("test")
    other.backbone.stereo_near, other.backbone.stereo_far = 0.4, 4.0
    assert weight_differences(base, other) == []
    other.backbone.stereo_depths = 56
    assert weight_differences(base, other) == ["backbone.stereo_depths"]
