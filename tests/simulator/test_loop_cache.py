"""The loop cache: a loop from the cache is the very loop a fresh render gives, anything that shapes
the loop changes its key, a damaged file is rendered again, and the folder stays within its bound."""
from __future__ import annotations

import os
import shutil
import time
from types import SimpleNamespace

import numpy as np
import pytest

from simulator import loop_cache
from simulator.rig import virtual_rig
from simulator.scene import Scene
from simulator.sensor import SensorModel, SimRig

W, H, FRAMES = 64, 36, 3


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("RIG_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("RIG_SIM_LOOP_CACHE_MB", raising=False)
    return tmp_path / "cache" / "sim-loops"


def _config(seed=0, read_noise=1.0):
    cams = [SimpleNamespace(name=n, uri=f"sim://{n}", role=n, width=W, height=H, gain=None, sim={"seed": i, "read_noise": read_noise})
            for i, n in enumerate(("left", "right"))]
    return SimpleNamespace(sim={"seed": seed, "people": 1, "loop_frames": FRAMES, "loop_fps": 10.0}, cameras=cams)


@pytest.fixture(scope="module")
def scene():
    return Scene(seed=1, people=1, name="empty")


@pytest.fixture(scope="module")
def cam():
    return virtual_rig(2, W, H)["left"]


def _replays(sensor, n=6):
    return [sensor.expose(0.1 * i, 0.005, np.random.default_rng(i)) for i in range(n)]


def test_a_loop_from_the_cache_is_bit_identical_to_a_fresh_render(cache):
    done = []
    fresh = SimRig(_config()).sensor("left")
    fresh.prerender(0.005, progress=lambda i, n: done.append((i, n)))
    assert fresh.loop_origin == "render" and done == [(1, FRAMES), (2, FRAMES), (3, FRAMES)]
    assert len(list(cache.glob("*.npz"))) == 1

    rig = SimRig(_config())
    cached = rig.sensor("left")
    done.clear()
    cached.prerender(0.005, progress=lambda i, n: done.append((i, n)))
    assert cached.loop_origin == "cache" and done == [], "loaded, not rendered"
    assert rig._scene is None, "a start from the cache does not even build the scene"
    for name in ("_loop", "_loop_clean", "_loop_sigma16"):
        assert np.array_equal(getattr(fresh, name), getattr(cached, name)), name
    for a, b in zip(_replays(fresh), _replays(cached)):
        assert np.array_equal(a, b)
    other = SimRig(_config()).sensor("right")  # another camera: its own loop
    other.prerender(0.005)
    assert other.loop_origin == "render" and len(list(cache.glob("*.npz"))) == 2


def test_everything_that_shapes_the_loop_is_in_its_key(scene, cam):
    def key(scene=scene, cam=cam, options=None, exposure_s=0.005, **kw):
        return SensorModel(scene, cam, options or {}, **{"loop_frames": FRAMES, **kw}).loop_cache_key(exposure_s)

    base = key()
    assert key() == base
    changed = [
        key(scene=Scene(seed=2, people=1, name="empty")),
        key(cam=virtual_rig(2, W + 2, H)["left"]),
        key(cam=virtual_rig(2, W, H)["right"]),
        key(options={"read_noise": 2.0}),
        key(options={"blur_samples": 2}),
        key(gain_db=3.0),
        key(loop_frames=FRAMES + 1),
        key(loop_fps=15.0),
        key(antialias=2),
        key(exposure_s=0.004),
    ]
    assert base not in changed and len(set(changed)) == len(changed)
    assert SensorModel(object(), cam, {}, loop_frames=FRAMES).loop_cache_key(0.005) is None, "an unknown scene is not cached"

    def rig_key(**scene_opts):  # a SimRig's scene is keyed by its options (and not built for it)
        config = _config()
        config.sim.update(scene_opts)
        return SimRig(config).sensor("left").loop_cache_key(0.005)

    rig_keys = [rig_key(), rig_key(seed=1), rig_key(people=2), rig_key(motion="walk"), rig_key(scene="empty")]
    assert len(set(rig_keys)) == len(rig_keys)
    assert SimRig(_config(read_noise=2.0)).sensor("left").loop_cache_key(0.005) != rig_keys[0]


def test_a_change_of_the_simulator_code_changes_the_key(tmp_path, monkeypatch):
    root = tmp_path / "src"
    shutil.copytree(loop_cache._ROOT / "simulator", root / "simulator")
    shutil.copytree(loop_cache._ROOT / "calibration", root / "calibration")
    monkeypatch.setattr(loop_cache, "_ROOT", root)
    loop_cache.code_version.cache_clear()
    try:
        before = loop_cache.code_version()
        with open(root / "simulator" / "render.py", "a") as f:
            f.write("\n# a change\n")
        loop_cache.code_version.cache_clear()
        assert loop_cache.code_version() != before
    finally:
        loop_cache.code_version.cache_clear()


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty"])
def test_a_damaged_cache_file_is_rendered_again(cache, scene, cam, damage):
    def sensor():
        return SensorModel(scene, cam, {}, loop_frames=FRAMES, loop_fps=10.0)

    fresh = sensor()
    fresh.prerender(0.005)
    (path,) = cache.glob("*.npz")
    data = path.read_bytes()
    path.write_bytes({"truncated": data[: len(data) // 2], "garbage": b"not a loop" * 100, "empty": b""}[damage])
    again = sensor()
    again.prerender(0.005)
    assert again.loop_origin == "render"
    assert np.array_equal(again._loop_clean, fresh._loop_clean)
    third = sensor()
    third.prerender(0.005)
    assert third.loop_origin == "cache", "the damaged file was replaced"


def test_a_file_with_another_key_or_shape_is_not_used(cache):
    arrays = {name: np.zeros((2, 4, 4, 3), np.uint8) for name in loop_cache.ARRAYS}
    loop_cache.store("key a", arrays)
    assert loop_cache.load("key a", (2, 4, 4, 3)) is not None
    assert loop_cache.load("key a", (2, 4, 5, 3)) is None
    path = loop_cache._file_of("key a", cache)
    path.rename(loop_cache._file_of("key b", cache))  # as if two keys had the same hash
    assert loop_cache.load("key b", (2, 4, 4, 3)) is None


def test_the_cache_folder_stays_within_its_bound_least_recently_used_first(cache, monkeypatch):
    one = {name: np.full((1, 100, 100, 3), i, np.uint8) for i, name in enumerate(loop_cache.ARRAYS)}
    size = loop_cache.store("first", one).stat().st_size
    monkeypatch.setenv("RIG_SIM_LOOP_CACHE_MB", str(2.5 * size / 1e6))  # room for two
    loop_cache.store("second", one)
    assert loop_cache.load("first", one["clean"].shape) is not None  # used again: now the newest
    loop_cache.store("third", one)
    assert loop_cache.load("second", one["clean"].shape) is None, "the least recently used went"
    assert loop_cache.load("first", one["clean"].shape) is not None
    assert loop_cache.load("third", one["clean"].shape) is not None
    assert sum(p.stat().st_size for p in cache.glob("*.npz")) <= 2.5 * size

    stale = cache / ".left-behind.part.npz"  # a writer that died mid-file
    stale.write_bytes(b"x")
    old = 2 * loop_cache.STALE_PART_S
    os.utime(stale, (time.time() - old, time.time() - old))
    loop_cache.store("fourth", one)
    assert not stale.exists()


def test_no_cache_when_turned_off_or_unwritable(tmp_path, monkeypatch, cache, scene, cam):
    monkeypatch.setenv("RIG_SIM_LOOP_CACHE_MB", "0")
    s = SensorModel(scene, cam, {}, loop_frames=FRAMES)
    s.prerender(0.005)
    assert s.loop_origin == "render" and not cache.exists()

    monkeypatch.delenv("RIG_SIM_LOOP_CACHE_MB")
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("RIG_CACHE_DIR", str(blocker))  # the cache folder cannot be made under a file
    s = SensorModel(scene, cam, {}, loop_frames=FRAMES)
    s.prerender(0.005)
    assert s.loop_origin == "render" and s._loop_clean.shape == (FRAMES, H, W, 3)


def test_the_default_folder_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.delenv("RIG_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert loop_cache.cache_dir() == tmp_path / "rig" / "sim-loops"
    monkeypatch.setenv("RIG_CACHE_DIR", str(tmp_path / "x"))
    assert loop_cache.cache_dir() == tmp_path / "x" / "sim-loops"
