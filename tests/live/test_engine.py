"""The live engine on a simulated six-camera rig with the test-size model: stage 1 once per frame set
whatever the number of viewers, newest set wins, viewpoints apply to the next render, and a slow
viewer costs the model nothing."""
from __future__ import annotations

import time

import pytest

from tests.live.conftest import wait_until

pytestmark = pytest.mark.timeout(300)


def take_frames(viewers, seconds: float) -> dict:
    """Every viewer takes (and acknowledges) each frame as soon as it is there, for `seconds`."""
    got = {v.id: [] for v in viewers}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for v in viewers:
            f = v.next_frame(0.01)
            if f is not None:
                got[v.id].append(f)
                v.acknowledge(f.set_index, f.viewpoint_id)
    return got


def test_two_viewers_share_one_stage_1_per_frame_set(sim_live):
    engine = sim_live.engine
    a = engine.add_viewer({"type": "viewpoint", "t": 0.2})
    b = engine.add_viewer({"type": "viewpoint", "preset": "sup3"})
    try:
        take_frames([a, b], 1.0)  # settle
        s0, v0 = engine.stage1_runs, engine.view_runs
        got = take_frames([a, b], 6.0)
        s1, v1 = engine.stage1_runs - s0, engine.view_runs - v0
    finally:
        engine.remove_viewer(a)
        engine.remove_viewer(b)
    assert s1 >= 3 and len(got[a.id]) >= 3 and len(got[b.id]) >= 3
    assert v1 >= 2 * s1 - 2  # both views of (nearly) every stage-1 run: stage 1 is shared
    assert v1 <= 2 * s1 + 2
    for frames in got.values():  # each viewer sees increasing frame sets: the newest, never old ones
        sets = [f.set_index for f in frames]
        assert sets == sorted(sets) and len(set(sets)) == len(sets)
        assert all(f.jpeg[:2] == b"\xff\xd8" for f in frames)
    status = engine.status()
    assert status["sets_dropped"] > 0  # the cameras (15 Hz) outrun the model: old sets are dropped, not queued
    assert status["ms"]["stage1"] > 0 and status["ms"]["view"] > 0 and status["latency_ms"]["p50"] > 0


def test_only_the_two_sources_are_captured_and_every_camera_is_a_preset(sim_live):
    """The model renders from left and right alone: the live session opens and groups only them (the
    four supervision cameras of the six-camera rig cost the model CPU for nothing before), while every
    calibrated camera stays a preset."""
    engine = sim_live.engine
    assert set(engine.source.session.cameras) == {"left", "right"}
    assert set(engine.source.session.frames_delivered) == {"left", "right"}
    assert {p["name"] for p in engine.presets()} == {"left", "sup1", "sup2", "sup3", "sup4", "right"}


def test_a_viewer_that_takes_nothing_costs_the_model_nothing(sim_live):
    engine = sim_live.engine
    lazy = engine.add_viewer()
    try:
        first = lazy.next_frame(60)
        assert first is not None
        wait_until(lazy.holding, timeout=30, what="the lazy viewer's next frame to be rendered")
        for _ in range(2):  # a stage 1 begun while that frame was being encoded ends first
            with engine.model_held():
                pass
            time.sleep(0.3)
        s0, v0 = engine.stage1_runs, engine.view_runs
        time.sleep(2.0)  # it holds a frame it never takes: nothing more is rendered
        assert engine.view_runs == v0 and engine.stage1_runs == s0
        later = lazy.next_frame(1)
        assert later is not None and later.set_index > first.set_index
    finally:
        engine.remove_viewer(lazy)


def test_a_new_viewpoint_shows_in_the_next_frames_and_a_bad_one_changes_nothing(sim_live):
    engine = sim_live.engine
    v = engine.add_viewer()
    try:
        assert v.next_frame(60) is not None
        vid = v.set_viewpoint({"type": "viewpoint", "t": 0.9, "yaw": 5})
        frames = take_frames([v], 4.0)[v.id]
        assert frames and frames[-1].viewpoint_id == vid
        for bad in ({"type": "viewpoint", "t": float("nan")}, {"type": "viewpoint", "preset": "nope"}, {"type": "viewpoint", "t": 0.5, "x": 1}):
            with pytest.raises(ValueError):
                v.set_viewpoint(bad)
        assert v.describe()["viewpoint_id"] == vid
    finally:
        engine.remove_viewer(v)


def test_a_camera_vanishing_shows_in_the_health_at_once_and_it_resumes_when_the_camera_is_back(tiny_onnx):
    from rig.sim.rig_config import sim_rig_config
    from rig.config import parse_config
    from rig.live.app import LiveApp

    data = sim_rig_config(2, 320, 180, fps=15.0)
    data["cameras"][1]["sim"].update({"disconnect_after_s": 6.0, "reconnect_after_s": 3.0})  # the right camera
    app = LiveApp.build(parse_config(data), model=tiny_onnx.path, threads=2)
    with app:
        engine = app.engine
        viewer = engine.add_viewer()
        assert viewer.next_frame(60) is not None and engine.status()["health"]["ok"]
        session = engine.source.session
        wait_until(lambda: any(e.kind == "camera_lost" for e in session.events), timeout=30, what="the camera to vanish")
        seen = time.monotonic()
        health = wait_until(lambda: (h := engine.status()["health"]) and not h["ok"] and h, timeout=2.0, what="the health to say so")
        assert time.monotonic() - seen < 2.0
        assert any("right" in m for m in health["messages"]), health
        # back 3 s later: the health clears and new views come from new frame sets again
        wait_until(lambda: any(e.kind == "camera_back" for e in session.events), timeout=15, what="the camera to come back")
        wait_until(lambda: engine.status()["health"]["ok"], timeout=5, what="the health to clear")
        last = engine.status()["last_set"]
        frame = wait_until(lambda: (f := viewer.next_frame(1.0)) is not None and f.set_index > last and f, timeout=60,
                           what="a view of a frame set after the camera came back")
        assert frame.jpeg[:2] == b"\xff\xd8"
