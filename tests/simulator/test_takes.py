"""Simulator takes for training: rendered offline, read back by the rig's sequence reader exactly like
a recorded take, with ground-truth depth on demand and variety drawn from the seed."""
from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.camera import CameraModel
from rig.storage.dataset import Sequence
from rig.storage.validate import validate
from simulator.errors import SimulatorError
from simulator.render import render
from simulator.scene import Scene
from simulator.takes import TAKES_PER_SEED, take_seed, write_dataset, write_take
from simulator.variety import Lighting, draw_variety

SIZE = (96, 54)
FPS = 10.0
SECONDS = 0.2  # two sets


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    out = tmp_path_factory.mktemp("takes") / "a"
    summary = write_take(out, seed=4242, seconds=SECONDS, fps=FPS, size=SIZE)
    return out, summary


def _images(root) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted((root / "frames").rglob("*.ppm"))}


def test_a_take_reads_back_like_a_recording(take):
    root, summary = take
    seq = Sequence(root)
    assert summary["sets"] == 2 and len(seq) == 2
    assert seq.camera_names == ["left", "sup1", "sup2", "sup3", "sup4", "right"]
    assert [c.role for c in seq.meta.cameras] == ["left"] + ["supervision"] * 4 + ["right"]
    assert seq.meta.rate_hz == FPS
    assert seq.has_ground_truth()
    v = validate(root, check_pixels=True)
    assert v.readable and v.complete_sets == 2 and v.gaps == 0, v.to_dict()

    sim = seq.meta.extra["simulator"]
    scene = Scene.from_options(sim["scene"])
    Lighting.from_dict(sim["take"]["lighting"]).apply(scene)
    samples = list(seq.samples())
    assert [s.set for s in samples] == [0, 1]
    rows = seq.rows
    for sample, row in zip(samples, rows):
        for name in ("left", "sup2", "right"):
            t = row["frames"][name]["sim_time_s"]
            cam = CameraModel.from_dict(next(c for c in sim["cameras"] if c["name"] == name))
            direct = render(scene, cam, t)
            # the stored image is exactly the render the metadata describes
            np.testing.assert_array_equal(sample.images[name], direct.rgb)
            # ground-truth depth comes from the scene options and the exact cameras alone
            depth = sample.depth[name]
            assert depth is not None and depth.shape == (SIZE[1], SIZE[0])
            assert (depth > 0).mean() > 0.99  # the room surrounds the rig
            np.testing.assert_array_equal(depth, direct.depth)
            assert direct.mask.any(), "people are in view"
    # scene time advances by one frame between sets
    t0 = rows[0]["frames"]["left"]["sim_time_s"]
    t1 = rows[1]["frames"]["left"]["sim_time_s"]
    assert t1 - t0 == pytest.approx(1.0 / FPS)
    assert not np.array_equal(samples[0].images["left"], samples[1].images["left"])


def test_depth_at_the_training_size(take):
    root, _ = take
    seq = Sequence(root)
    s = next(seq.samples(cameras=["left", "sup1"], size=(48, 27)))
    assert s.images["sup1"].shape == (27, 48, 3)
    assert s.depth["sup1"].shape == (27, 48)
    assert s.cameras["sup1"].width == 48


def test_the_same_seed_gives_the_same_take_and_another_seed_another(take, tmp_path):
    root, summary = take
    again = write_take(tmp_path / "again", seed=4242, seconds=SECONDS, fps=FPS, size=SIZE)
    other = write_take(tmp_path / "other", seed=4243, seconds=SECONDS, fps=FPS, size=SIZE)
    assert _images(root) == _images(tmp_path / "again")
    assert (root / "index.jsonl").read_bytes() == (tmp_path / "again" / "index.jsonl").read_bytes()
    meta_a = json.loads((root / "sequence.json").read_text())
    meta_b = json.loads((tmp_path / "again" / "sequence.json").read_text())
    meta_a.pop("created"), meta_b.pop("created")
    assert meta_a == meta_b and again["variety"] == summary["variety"]

    imgs_o = _images(tmp_path / "other")
    assert imgs_o.keys() == _images(root).keys()
    assert all(imgs_o[k] != v for k, v in _images(root).items())
    cams_a = json.loads((root / "sequence.json").read_text())["simulator"]["cameras"]
    cams_o = json.loads((tmp_path / "other" / "sequence.json").read_text())["simulator"]["cameras"]
    assert all(not np.allclose(a["t"], o["t"]) for a, o in zip(cams_a, cams_o)), "camera placement is jittered per seed"
    assert other["variety"] != summary["variety"]


def test_variety_covers_what_the_issue_asks_for():
    varieties = [draw_variety(take_seed(0, i)) for i in range(40)]
    assert {v.scene["people"] for v in varieties} == {1, 2, 3}
    assert len({v.scene["motion"] for v in varieties}) >= 4
    assert {v.scene["scene"] for v in varieties} == {"studio", "empty"}
    ambients = [v.lighting.ambient for v in varieties]
    assert max(ambients) - min(ambients) > 0.15
    spans = [v.placement.span_deg for v in varieties]
    assert max(spans) - min(spans) > 6.0
    # the cameras stay in arc order, left to right, a small jitter off the arc
    rig = varieties[0].placement.cameras(64, 36, 6, varieties[0].seed)
    xs = [float(c.center[0]) for c in rig.cameras]
    assert xs == sorted(xs)


def test_dataset_seeds_are_disjoint_between_data_sets(tmp_path):
    summary = write_dataset(tmp_path / "ds", takes=2, seconds=0.1, seed=7, fps=FPS, size=(32, 18), cameras=3)
    assert summary["take_seeds"] == [7 * TAKES_PER_SEED, 7 * TAKES_PER_SEED + 1]
    manifest = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert manifest["takes"] == ["take-000", "take-001"]
    seq = Sequence(tmp_path / "ds" / "take-001")
    assert seq.meta.extra["simulator"]["scene"]["seed"] == 7 * TAKES_PER_SEED + 1
    assert seq.camera_names == ["left", "sup1", "right"]
    training = {take_seed(0, i) for i in range(TAKES_PER_SEED)}
    held_out = {take_seed(1, i) for i in range(TAKES_PER_SEED)}
    assert not training & held_out


def test_noise_is_optional_and_seeded(tmp_path):
    clean = write_take(tmp_path / "clean", seed=5, seconds=0.1, fps=FPS, size=(32, 18), cameras=2)
    noisy = write_take(tmp_path / "noisy", seed=5, seconds=0.1, fps=FPS, size=(32, 18), cameras=2, noise=True)
    a = next(Sequence(clean["out"]).samples(with_depth=False)).images["left"].astype(int)
    b = next(Sequence(noisy["out"]).samples(with_depth=False)).images["left"].astype(int)
    diff = b - a
    assert 0.5 < diff.std() < 10 and abs(diff.mean()) < 1.5


def test_bad_input_is_one_clear_error(take, tmp_path):
    root, _ = take
    with pytest.raises(SimulatorError, match="already holds a sequence"):
        write_take(root, seed=1, seconds=0.1, fps=FPS, size=SIZE)
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(SimulatorError, match="not an empty folder"):
        write_dataset(tmp_path / "busy", takes=1, seconds=0.1, fps=FPS, size=SIZE)
    assert (tmp_path / "busy" / "notes.txt").read_text() == "mine"
    with pytest.raises(SimulatorError, match="seconds"):
        write_take(tmp_path / "x", seed=1, seconds=0, fps=FPS, size=SIZE)
    with pytest.raises(SimulatorError, match="takes"):
        write_dataset(tmp_path / "y", takes=0, seconds=1.0)
    with pytest.raises(SimulatorError, match="seed"):
        write_dataset(tmp_path / "y", takes=1, seconds=1.0, seed=-1)
