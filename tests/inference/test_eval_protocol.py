"""The evaluation protocol: the held-out sets, the per-take figures and their spread, "vanished"."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from inference.errors import InferenceError
from inference.evaluate.heldout import PREVIOUS, SETS, SPENT_SEEDS, TEST, TRAINING_SEED, VALIDATION, check_data, held_out_set
from inference.evaluate.model_eval import (TAKE_FIGURES, evaluate, oracle_twin, percentile, spread, spread_lines, take_lines,
                                           vanished_pixels)
from simulator.takes import TAKES_PER_SEED, take_seed, write_dataset


def test_the_held_out_sets_never_share_a_take_with_training_or_earlier_selection():
    assert VALIDATION.takes >= 12 and TEST.takes >= 20
    for held in (VALIDATION, TEST):
        assert held.seed not in SPENT_SEEDS and held.seed != TRAINING_SEED
        assert (held.seconds, held.fps, held.size, held.cameras) == (1.0, 5.0, (640, 360), 6)
    assert PREVIOUS.seed == 1 and PREVIOUS.seed in SPENT_SEEDS
    # Take seeds, as simulator.takes draws them: no take of one set is a take of another or of any
    # data set with a spent seed (training may render up to TAKES_PER_SEED takes of its seed).
    takes = {name: {take_seed(s.seed, i) for i in range(s.takes)} for name, s in SETS.items()}
    spent = {take_seed(k, i) for k in SPENT_SEEDS for i in range(TAKES_PER_SEED)}
    assert not takes["validation"] & takes["test"]
    assert not (takes["validation"] | takes["test"]) & spent
    assert held_out_set("test") is TEST
    with pytest.raises(InferenceError, match="validation, test"):
        held_out_set("train")


def test_a_folder_is_checked_to_be_the_set_it_is_reported_as(tmp_path):
    # The validation set's first take at a tiny size: its listing says seed 3, 5 sets per take.
    VALIDATION.render(tmp_path / "val", takes=1, size=(32, 18))
    meta = check_data(VALIDATION, tmp_path / "val")
    assert meta["take_seeds"] == [take_seed(VALIDATION.seed, 0)]
    with pytest.raises(InferenceError, match="not the test set.*--seed 4"):
        check_data(TEST, tmp_path / "val")
    write_dataset(tmp_path / "short", 1, 0.4, seed=VALIDATION.seed, fps=5, size=(32, 18))  # 2 sets per take, not 5
    with pytest.raises(InferenceError, match="not the validation set"):
        check_data(VALIDATION, tmp_path / "short")
    with pytest.raises(InferenceError, match="no readable data-set listing"):
        check_data(VALIDATION, tmp_path)
    with pytest.raises(InferenceError, match="has 12 takes"):
        VALIDATION.render(tmp_path / "more", takes=13)


def test_the_spread_over_takes_is_what_it_says():
    values = [float(v) for v in range(20, 0, -1)]  # 20 takes, 1 to 20 in any order
    s = spread(values, higher_is_better=True)
    assert (s["takes"], s["min"], s["max"], s["worst"], s["mean"], s["median"]) == (20, 1, 20, 1, 10.5, 10.5)
    # The 10th percentile by linear interpolation: rank 0.1 * (20 - 1) = 1.9 from the lowest.
    assert s["p10"] == pytest.approx(2.9) and percentile(values, 10) == pytest.approx(2.9)
    assert s["p90"] == pytest.approx(18.1)
    errors = spread(values, higher_is_better=False)
    assert errors["worst"] == 20
    assert spread([None, float("nan")]) is None
    assert spread([3.0])["p10"] == 3.0


def _view(depth: np.ndarray, alpha: float = 1.0):
    d = torch.from_numpy(depth.astype(np.float32))[None, None]
    return d, torch.full_like(d, alpha)


def test_vanished_counts_person_pixels_off_by_more_than_30_percent_or_left_empty():
    rng = np.random.default_rng(0)
    truth = rng.uniform(1.5, 6.0, (36, 64)).astype(np.float32)
    mask = np.zeros_like(truth, bool)
    mask[10:30, 20:40] = True
    n = int(mask.sum())
    assert vanished_pixels(*_view(truth), truth, mask) == (0, n)
    assert vanished_pixels(*_view(truth * 1.29), truth, mask) == (0, n)
    assert vanished_pixels(*_view(truth * 0.71), truth, mask) == (0, n)
    assert vanished_pixels(*_view(truth * 1.31), truth, mask) == (n, n)
    assert vanished_pixels(*_view(truth * 0.5), truth, mask) == (n, n)
    # The person not drawn at all: the render is empty there (or has no depth), whatever lies behind.
    assert vanished_pixels(*_view(truth, alpha=0.4), truth, mask) == (n, n)
    assert vanished_pixels(*_view(np.zeros_like(truth)), truth, mask) == (n, n)
    # The wall drawn where half the person stands: half of them vanished.
    wall = truth.copy()
    wall[10:20, 20:40] = 8.0
    assert vanished_pixels(*_view(wall), truth, mask) == (n // 2, n)


@pytest.fixture(scope="module")
def two_takes(tmp_path_factory):
    """Two takes of two frame sets each, one supervision camera, small: a validation-seeded data set."""
    root = tmp_path_factory.mktemp("heldout") / "data"
    write_dataset(root, 2, 0.4, seed=VALIDATION.seed, fps=5, size=(160, 90), cameras=3)
    from rig.storage.dataset import TrainingSet, expand_sequences

    return TrainingSet(expand_sequences([root]))


@pytest.fixture(scope="module")
def result(two_takes):
    from inference.config import ModelConfig, Sizes
    from inference.model.pipeline import build_model

    # Smaller than the `test` preset (a quarter of its output pixels): the figures' bookkeeping is
    # under test here, not the model.
    model = build_model(ModelConfig.for_backbone("stereo", Sizes((64, 32), (128, 64), (160, 90))), seed=0)
    other = oracle_twin(build_model(model.cfg, seed=1))
    return evaluate(model, two_takes, oracles={"oracle_other_stage2": other})


def test_every_take_has_its_figures_and_their_spread_is_consistent(result):
    takes = result["takes"]
    assert sorted(takes) == ["take-000", "take-001"] and result["sets"] == 4
    for t in takes.values():
        assert t["views"] == 2
        assert 0 < t["person_share"] < 1 and 0.5 < t["nearest_person_m"] < 10
        assert 0 <= t["vanished"] <= 1 and t["view_depth_absrel_person"] > 0 and t["depth_absrel"] > 0
        assert t["worst_view"]["camera"] == "sup1" and t["worst_view"]["psnr"] <= t["psnr"] + 1e-4  # the lowest view of the take
    for fig, higher in TAKE_FIGURES.items():
        s = result["spread"][fig]
        values = [t[fig] for t in takes.values()]
        assert s["takes"] == 2 and s["min"] <= s["median"] <= s["max"]
        assert s["p10"] == pytest.approx(percentile(values, 10), abs=1e-5) and s["min"] <= s["p10"] <= s["median"]
        assert s["worst"] == pytest.approx(min(values) if higher else max(values), abs=1e-5)
        assert s["mean"] == pytest.approx(np.mean(values), abs=1e-5)
    # Pooled over the person pixels of both takes, the figure lies between the takes' own.
    assert result["spread"]["vanished"]["min"] - 1e-5 <= result["vanished"] <= result["spread"]["vanished"]["max"] + 1e-5
    assert result["overall"]["views"] == 4


def test_the_references_are_measured_per_take_on_the_same_views(result):
    refs = result["references"]
    assert set(refs) == {"oracle", "oracle_other_stage2", "nearest_source"}
    for name, r in refs.items():
        assert sorted(r["takes"]) == ["take-000", "take-001"] and r["overall"]["views"] == 4
        assert r["spread"]["psnr"]["min"] <= r["spread"]["psnr"]["median"] <= r["spread"]["psnr"]["max"]
    # The oracle's depth is the sources' truth: hardly any person pixel is gone (silhouette edges),
    # far fewer than for an untrained model; the nearer source draws no depth, so it has no figure.
    assert refs["oracle"]["vanished"] < 0.05 < result["vanished"]
    assert refs["nearest_source"]["vanished"] is None and "vanished" not in refs["nearest_source"]["spread"]
    # Another stage 2 draws another image from the same depth.
    assert refs["oracle_other_stage2"]["overall"]["psnr"] != refs["oracle"]["overall"]["psnr"]


def test_the_text_tables_name_every_take_and_reference(result):
    takes = "\n".join(take_lines(result, {"take-000": 3000, "take-001": 3001}))
    assert "take-000" in takes and "3001" in takes and "nearest_source" in takes
    spread_text = "\n".join(spread_lines(result))
    assert "over 2 takes" in spread_text and "vanished %" in spread_text and "oracle_other_sta" in spread_text
    json.dumps(result)  # --json prints it whole


@pytest.mark.parametrize("argv, said", [(["--set", "test", "--takes", "21"], "the test set has 20 takes"),
                                        (["--set", "validation", "--data", "{tmp}"], "no readable data-set listing"),
                                        (["--model", "{tmp}/none.pt"], "no such model")])
def test_the_benchmark_says_what_is_wrong_in_one_line(tmp_path, argv, said):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "model_eval.py"
    r = subprocess.run([sys.executable, str(script), *[a.format(tmp=tmp_path) for a in argv], "--quiet"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and said in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr


def test_sets_per_take_picks_the_first_and_last_sets_of_every_take():
    from types import SimpleNamespace

    from inference.evaluate.model_eval import sets_per_take

    # Three takes of 5, 2 and 1 complete sets, as TrainingSet.positions lists them (take, set).
    source = SimpleNamespace(positions=[(0, p) for p in range(5)] + [(1, 0), (1, 3)] + [(2, 7)])
    assert sets_per_take(source, 2) == [0, 4, 5, 6, 7]
    assert sets_per_take(source, 3) == [0, 2, 4, 5, 6, 7]
    assert sets_per_take(source, 1) == [0, 5, 7]
    with pytest.raises(ValueError):
        sets_per_take(source, 0)


def test_the_reference_cache_key_follows_the_frame_sets_the_sizes_and_the_stage2_configuration():
    import sys
    from pathlib import Path

    from inference.config import ModelConfig, Sizes

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import model_eval as bench

    cfg = ModelConfig.for_backbone("stereo", Sizes.preset("preview"))
    key = bench.reference_key("validation", ["take-000"], [0, 4], (640, 360), cfg)
    assert key == bench.reference_key("validation", ["take-000"], [0, 4], (640, 360), ModelConfig.from_dict(cfg.to_dict()))
    other_stage1 = ModelConfig.from_dict(cfg.to_dict())
    other_stage1.stage1.scale_search = 21  # replaced by the oracle: the same references
    other_stage1.backbone.stereo_near = 0.4
    assert key == bench.reference_key("validation", ["take-000"], [0, 4], (640, 360), other_stage1)
    other_stage2 = ModelConfig.from_dict(cfg.to_dict())
    other_stage2.stage2.visibility_ramp = 8.0
    assert len({key, bench.reference_key("validation", ["take-000"], [0, 3], (640, 360), cfg),
                bench.reference_key("validation", ["take-000"], [0, 4], (320, 180), cfg),
                bench.reference_key("validation", ["take-000"], [0, 4], (640, 360), other_stage2)}) == 4
