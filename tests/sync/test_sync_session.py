"""A sim rig run with its emulated trigger board, measured against the simulator's truth."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest

from rig.capture.session import RigSession
from rig.capture.sync_check import sync_check
from rig.config import parse_config


def sim_rig(trigger_sim=None, cameras=None, rate_hz=30.0, trigger=True) -> dict:
    cams = cameras or [
        {"name": "left", "uri": "sim://left", "role": "left", "trigger": "hardware",
         "sim": {"drop_rate": 0.02, "jitter_us": 50.0, "drift_ppm": 100.0, "clock_offset_ns": 4_000_000_000_000, "seed": 11}},
        {"name": "right", "uri": "sim://right", "role": "right", "trigger": "hardware",
         "sim": {"drop_rate": 0.02, "jitter_us": 50.0, "drift_ppm": -100.0, "clock_offset_ns": 17, "seed": 12}},
    ]
    for c in cams:
        c.setdefault("width", 64)
        c.setdefault("height", 48)
        c.setdefault("exposure_us", 5000.0)
        c.setdefault("fps", rate_hz)
    # a pre-rendered loop of the scene: the cameras keep real time (rendering live would not)
    data = {"rig": {"name": "sync-test"}, "sim": {"loop_frames": 30, "people": 1}, "cameras": cams}
    if trigger:
        data["trigger"] = {"uri": "sim://trigger", "rate_hz": rate_hz, "sim": dict(trigger_sim or {"drift_ppm": 100.0, "seed": 3})}
    return data


def assert_truth(report: dict) -> None:
    truth = report["truth"]
    assert report["mismatched_sets"] == 0 and truth["misassigned_frames"] == 0
    for name, n in report["frames"].items():
        assert report["cameras"][name]["grouped"] == n, "every delivered frame is in a set"
        assert truth["undetected_drops"][name] == 0 and truth["false_drops"][name] == 0
        assert report["drops_detected"][name] == truth["drops_injected"][name]


@pytest.mark.slow
def test_twenty_seconds_at_30_hz_with_drops_jitter_and_drift():
    """The acceptance conditions: 2% frame drops, 50 us trigger-latency jitter, 100 ppm drift, at 30 Hz;
    20 s here (it runs in real time), the full 60 s in benchmarks/sync_check_sim.py."""
    cfg = parse_config(sim_rig({"drift_ppm": 100.0, "reply_jitter_us": 200.0, "seed": 3}))
    report = sync_check(cfg, 20.0)
    print("\nsync check, 20 s:", json.dumps({k: report[k] for k in ("pulses", "frames", "complete_sets", "mismatched_sets", "drops_detected", "skew_us", "clock_residual_us", "drift_ppm")}))
    print("truth:", json.dumps(report["truth"]))
    assert report["pulses"] == 600 and report["sets"] == 600
    assert_truth(report)
    # 2% of 1200 frames: 24 expected, binomial sd 4.8
    assert 10 < sum(report["truth"]["drops_injected"].values()) < 40
    assert report["skew_us"]["p99"] < 500  # 50 us jitter per camera, not a frame period
    assert abs(report["drift_ppm"] - 100.0) < 5.0
    assert report["clock_residual_us"] < 200.0  # measured figure is printed; the model's own bound is in test_sync_clock


def test_a_noisy_link_and_dropped_pulses_never_pair_frames_wrongly():
    # a held-back line waits three pulse periods, so later pulses overtake it however late a loaded
    # machine sends them (at 40 ms, just over one period, a busy CI machine saw no overtaking at all)
    trigger = {"drift_ppm": -200.0, "reply_jitter_us": 100.0, "corrupt_rate": 0.03, "delay_rate": 0.06, "delay_ms": 100.0,
               "drop_pulse_rate": 0.05, "seed": 8}
    cfg = parse_config(sim_rig(trigger))
    report = sync_check(cfg, 4.0)
    assert_truth(report)
    link = report["board"]
    assert link["corrupt_lines"] > 0 and link["out_of_order_lines"] > 0
    dropped = 0
    for name in report["frames"]:
        assert report["cameras"][name]["missed_triggers"] > 0  # pulses the board never delivered
        dropped = max(dropped, report["cameras"][name]["missed_triggers"])
    assert dropped > 0


def test_unplugging_the_board_mid_run_keeps_the_sets_and_resumes_on_return():
    cfg = parse_config(sim_rig({"seed": 4}))
    with RigSession(cfg, warm_up_s=1.0) as session:
        session.start()
        first = []
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            fs = session.next_set(timeout=0.1)
            if fs is not None:
                first.append(fs)
        session.emulator.unplug()
        t_unplug = time.monotonic()
        while not any(e.kind == "board_disconnected" for e in session.events):
            assert time.monotonic() - t_unplug < 3, "the unplug was not reported"
            time.sleep(0.02)
        assert "disconnected" in session.errors()[0]
        # sets of pulses fired before the unplug still come out; then nothing new
        while True:
            fs = session.next_set(timeout=1.0)
            if fs is None:
                break
            first.append(fs)
        assert len(first) > 20 and [s.index for s in first] == list(range(len(first)))
        session.emulator.replug()
        second = []
        deadline = time.monotonic() + 8
        while len(second) < 30 and time.monotonic() < deadline:
            fs = session.next_set(timeout=0.2)
            if fs is not None:
                second.append(fs)
        assert any(e.kind == "resumed" for e in session.events)
        assert len(second) == 30 and all(s.train == 1 for s in second)
        assert second[0].index == first[-1].index + 1 and second[0].trigger_index == 0
        session.stop()
        for fs in first + second:
            for f in fs:
                assert session.cameras[f.camera].truth_pulse[f.frame_id] == fs.trigger_index


def test_software_and_free_running_cameras_join_the_triggered_sets():
    cams = [
        {"name": "left", "uri": "sim://left", "role": "left", "trigger": "hardware", "sim": {"seed": 1}},
        {"name": "soft", "uri": "sim://soft", "trigger": "software", "sim": {"seed": 2}},
        {"name": "free", "uri": "sim://free", "trigger": "free", "sim": {"seed": 3}},
    ]
    cfg = parse_config(sim_rig({"seed": 5}, cameras=cams, rate_hz=20.0))
    with RigSession(cfg, warm_up_s=1.0) as session:
        sets = list(session.framesets(seconds=3.0))
        stats = session.camera_stats()
    assert len(sets) >= 50
    middle = sets[3:-3]
    assert all(s["left"] is not None for s in middle)
    assert sum(s["soft"] is not None for s in middle) >= 0.9 * len(middle)
    assert sum(s["free"] is not None for s in middle) >= 0.9 * len(middle)
    for name in ("soft", "free"):
        ids = [s[name].frame_id for s in sets if s[name] is not None]
        assert len(ids) == len(set(ids)) and ids == sorted(ids)
        assert stats[name]["grouped"] == len(ids)
    for s in sets:
        if s["left"] is not None:
            assert session.cameras["left"].truth_pulse[s["left"].frame_id] == s.trigger_index


def test_a_rig_without_a_trigger_board_groups_by_the_left_camera():
    cams = [{"name": n, "uri": f"sim://{n}", "role": n, "trigger": "free", "sim": {"seed": i}} for i, n in enumerate(["left", "right"])]
    cams.append({"name": "soft", "uri": "sim://soft", "trigger": "software", "sim": {"seed": 5}})  # fired by the session
    cfg = parse_config(sim_rig(cameras=cams, trigger=False, rate_hz=25.0))
    with RigSession(cfg) as session:
        sets = list(session.framesets(seconds=2.5))
        stats = session.grouper.stats()
    # from the first set both cameras were running in (they start one after the other) to the end
    first = next(i for i, s in enumerate(sets) if s["right"] is not None)
    steady = sets[first:-2]
    assert len(steady) >= 35
    assert [s["left"].frame_id for s in sets] == list(range(sets[0]["left"].frame_id, sets[0]["left"].frame_id + len(sets)))
    right_ids = [s["right"].frame_id for s in sets if s["right"] is not None]
    assert right_ids == sorted(set(right_ids))  # no frame in two sets, none out of order
    for s in steady:
        if s["right"] is not None:  # exposures within half a period (20 ms) of each other
            assert abs(s["right"].host_ts_ns - s["left"].host_ts_ns) <= 20_000_000 + 5_000_000
    # each camera within half a period (20 ms) of the reference, so two of them within a period
    assert stats["skew_us"]["max"] <= 40_000
    # the cameras' relative phase depends on when each started; clear of the half-period boundary
    # every set has both, but for the odd frame a loaded host stamped late (measured: 3 of 65 with
    # another test process rendering beside it)
    phase = np.median([s["right"].host_ts_ns - s["left"].host_ts_ns for s in steady if s["right"] is not None])
    if abs(phase) < 0.35 * 40e6:
        assert sum(s["right"] is not None for s in steady) >= 0.9 * len(steady)
    soft = [s for s in steady if s["soft"] is not None]
    assert len(soft) >= 0.8 * len(steady)  # software triggers at the left camera's rate
    for s in soft:
        assert abs(s["soft"].host_ts_ns - s["left"].host_ts_ns) <= 20_000_000 + 5_000_000
    report = sync_check(cfg, 1.0)
    assert report["clock_residual_us"] is None and report["mismatched_sets"] is None and report["drift_ppm"] is None
