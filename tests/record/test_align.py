"""`rig record align`: free-running cameras put on the trigger pulses by the board's LED flashes.

A simulated take: two hardware-triggered sources and two free-running cameras whose own clocks are
offset (and one drifts), at frame rates that are not the trigger's, with a 1/33 s shutter like a video
camera's; the scene has the board's LED in view. The truth is known: a sim camera's device timestamp
is its exposure start on its own clock (offset and drift from the config), and a hardware camera's is
its pulse's (plus a 20 us trigger latency) on the simulated clock.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rig.sim.rig_config import sim_rig_config
from rig.config import dump_config, load_config, parse_config
from rig.storage.layout import INDEX
from rig.storage.validate import validate
from tests.rig.cli_helpers import assert_one_line_error, run_rig

FREE = {"sup1": {"fps": 29.97, "sim": {"clock_offset_ns": 123_456_789}},
        "sup2": {"fps": 30.02, "sim": {"clock_offset_ns": -987_654_321, "drift_ppm": 40.0}}}


def _rig(folder: Path, led: bool = True) -> Path:
    data = sim_rig_config(n_cameras=4, width=320, height=180)
    data["sim"].update(led=led, loop_frames=30)
    for cam in data["cameras"]:
        if cam["name"] in FREE:
            cam.update(trigger="free", exposure_us=30000.0, fps=FREE[cam["name"]]["fps"])
            cam["sim"].update(FREE[cam["name"]]["sim"])
    path = folder / "rig.toml"
    path.write_text(dump_config(parse_config(data)))
    return path


# Periods either side of half-way between two pulses where a frame may go to either set: the
# estimated clock places frames within 0.006 periods of the truth (measured), and a free camera at
# 29.97 fps against 30 Hz pulses drifts 0.001 periods a frame, so a few frames of a take lie there.
BOUNDARY = 0.02


def _truth_errors(take: Path) -> dict[str, tuple[list, float, int]]:
    """Per free camera: the frames in the wrong set (set, periods after its pulse, offset given), the
    largest offset error of the others (pulse periods), frames checked."""
    cfg = load_config(take / "rig.toml", check_calibration=False)
    rows = [json.loads(line) for line in (take / INDEX).read_text().splitlines()]
    hw = np.array([(r["trigger"], r["frames"]["left"]["device_ts_ns"]) for r in rows if r["frames"]["left"]], dtype=np.float64)
    ns_per_pulse, at_zero = np.polyfit(hw[:, 0], hw[:, 1], 1)
    out = {}
    for c in cfg.cameras:
        if c.trigger != "free":
            continue
        offset_ns, drift = c.sim.get("clock_offset_ns", 0), c.sim.get("drift_ppm", 0.0)
        wrong, worst, n = [], 0.0, 0
        for r in rows:
            f = r["frames"][c.name]
            if f is None:
                continue
            start = (f["device_ts_ns"] - offset_ns) / (1 + drift * 1e-6)  # exposure start, simulated clock
            pos = (start - at_zero) / ns_per_pulse - r["trigger"]  # periods after the pulse of its set
            n += 1
            # Its set is the nearest pulse's; a frame exposed within BOUNDARY of half-way between two
            # pulses may go to either, and its offset then says which (free cameras drift through it).
            if abs(pos) > 0.5 + BOUNDARY:
                wrong.append((r["trigger"], round(pos, 4), f["offset"]))
            else:
                worst = max(worst, abs(pos - f["offset"]))
        out[c.name] = (wrong, worst, n)
    return out


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    folder = tmp_path_factory.mktemp("align")
    config = _rig(folder)
    rec = run_rig("record", "-c", config, "-o", folder / "take", "--seconds", 4, "--json", timeout=180)
    assert rec.returncode == 0, rec.stderr
    assert json.loads(rec.stdout)["flashes"] == 2
    return folder / "take"


def test_align_gives_free_running_frames_their_pulse_and_offset(take):
    before = (take / INDEX).read_bytes()
    proc = run_rig("record", "align", take, "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert set(report["cameras"]) == {"sup1", "sup2"}
    for name, cam in report["cameras"].items():
        assert cam["problem"] is None, cam
        assert len([f for f in cam["flashes"] if "onset_ns" in f]) == 2, cam
        assert cam["placed"] >= cam["frames"] - 3, cam  # at most the frames beyond the take's first and last pulse
        # An onset in the sensor's dead time (30 ms exposures at 30 fps) is known to half the gap, and the
        # rate carries that to the take's ends: once 0.114 stated (a flash 0.0875 loose); the frames'
        # offsets against the truth stayed under 0.05 periods in 17 runs.
        assert cam["error_periods"] < 0.25, cam
        assert 25 < cam["latency_ms"] < 40, cam  # a sim camera delivers at its exposure's end: 30 ms after its start
        assert cam["rate_ppm"] is not None and abs(cam["rate_ppm"]) < 1000, cam  # two flashes: the clock's rate too
        # and how far that rate may be off, as far as the flashes' stated onset uncertainties say: on a
        # loaded machine an onset can be off by more than stated (once -435.1 +- 282.5 ppm for a true +40),
        # so the truth is printed, not asserted; test_flash_fit checks the bound itself
        print(f"{name}: clock {cam['rate_ppm']:+.1f} ± {cam['rate_ppm_error']:.1f} ppm, true {FREE[name]['sim'].get('drift_ppm', 0.0):+.1f}")
        assert cam["rate_ppm_error"] is not None and cam["rate_ppm_error"] > 0, cam
    errors = _truth_errors(take)
    for name, (wrong, worst, n) in errors.items():
        print(f"{name}: {n} frames, {len(wrong)} in the wrong set, offset error at most {worst:.4f} frame periods "
              f"(stated {report['cameras'][name]['error_periods']})")
        assert n > 100 and not wrong, errors
        assert worst < 0.1, errors  # the stated uncertainty, up to 0.014-0.12 here, is not always above it: 0.046 once
    backup = Path(report["backup"])
    assert backup.read_bytes() == before  # the original index, byte for byte
    assert json.loads((take / "alignment.json").read_text())["cameras"]["sup1"]["placed"] == report["cameras"]["sup1"]["placed"]
    v = validate(take)
    assert v.readable and not v.errors, v.errors


def test_align_says_what_is_wrong_in_one_line(take, tmp_path):
    assert_one_line_error(run_rig("record", "align", take, "--camera", "nosuch"), "no camera nosuch")
    assert_one_line_error(run_rig("record", "align", tmp_path / "missing"), "no such sequence folder")
    # a scene without the LED: the board flashes, no camera sees it
    config = _rig(tmp_path, led=False)
    rec = run_rig("record", "-c", config, "-o", tmp_path / "dark", "--seconds", 2, "--json", timeout=180)
    assert rec.returncode == 0, rec.stderr
    assert json.loads(rec.stdout)["flashes"] == 1  # a take this short gets the first flash only
    index = (tmp_path / "dark" / INDEX).read_bytes()
    assert_one_line_error(run_rig("record", "align", tmp_path / "dark"), "could not align sup1, sup2", "not found", code=1)
    assert (tmp_path / "dark" / INDEX).read_bytes() == index  # nothing changed
    assert not list((tmp_path / "dark").glob("index.before-align-*"))
    (tmp_path / "dark" / "flashes.jsonl").unlink()  # a take recorded with --no-flash
    assert_one_line_error(run_rig("record", "align", tmp_path / "dark"), "no flashes.jsonl")


def _copy_as_recorded(take: Path, dest: Path) -> Path:
    """The take as `rig record` left it (its index before any alignment), its frames shared."""
    dest.mkdir()
    backups = sorted(take.glob("index.before-align-*"))
    (dest / INDEX).write_bytes((backups[0] if backups else take / INDEX).read_bytes())
    for name in ("flashes.jsonl", "sequence.json", "rig.toml"):
        (dest / name).write_bytes((take / name).read_bytes())
    (dest / "frames").symlink_to(take / "frames")
    return dest


def _rewrite(take: Path, camera: str, change) -> None:
    """Each row's record of `camera` through change(rec) -> rec or None (the frame never arrived)."""
    rows = [json.loads(line) for line in (take / INDEX).read_text().splitlines()]
    for r in rows:
        if r["frames"].get(camera) is not None:
            r["frames"][camera] = change(r["frames"][camera])
    (take / INDEX).write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_frames_that_reach_the_host_seconds_late_are_found_by_when_they_were_exposed(take, tmp_path):
    # A loaded host falls behind decoding one camera's stream from just before the first flash on:
    # its frames arrive as late as the second flash is after the first, and at least 2 s late (past
    # the first flash's own frames' window by arrival). By arrival, the frames around the first
    # flash are dark and those around the second are the first flash's: the first would be missed
    # and the second found where the first is, a whole flash interval off, with nothing to say so.
    copy = _copy_as_recorded(take, tmp_path / "late")
    flashes = [json.loads(line) for line in (copy / "flashes.jsonl").read_text().splitlines()]
    assert len(flashes) == 2
    behind_from = flashes[0]["host_ns"] - 200_000_000
    delay = max(flashes[1]["host_ns"] - flashes[0]["host_ns"], 2_000_000_000)
    _rewrite(copy, "sup1", lambda rec: {**rec, "host_ts_ns": rec["host_ts_ns"] + delay * (rec["host_ts_ns"] >= behind_from)})
    report = run_rig("record", "align", copy, "--json")
    assert report.returncode == 0, report.stderr
    cam = json.loads(report.stdout)["cameras"]["sup1"]
    assert cam["problem"] is None and len([f for f in cam["flashes"] if "onset_ns" in f]) == 2, cam
    wrong, worst, n = _truth_errors(copy)["sup1"]
    assert n > 100 and not wrong and worst < 0.1, (wrong[:5], worst, n)


def test_a_flash_the_frames_pin_only_loosely_leaves_the_camera_not_aligned(take, tmp_path):
    # A take that got one flash, and the host kept one frame in four of a camera (its decoder fell
    # behind): 133 ms apart, 30 ms exposures. Where both edges of the flash fall between exposures,
    # every onset over 86 ms fits its frames equally well (1.3 pulse periods either way): any frame
    # could go to the neighbouring set, and the camera must be reported not aligned, not placed.
    full = _copy_as_recorded(take, tmp_path / "full")
    report = run_rig("record", "align", full, "--json")
    assert report.returncode == 0, report.stderr
    onset = json.loads(report.stdout)["cameras"]["sup1"]["flashes"][0]["onset_ns"]
    exposure_ns = 30e6
    rows = [json.loads(line) for line in (full / sorted(full.glob("index.before-align-*"))[0].name).read_text().splitlines()]
    starts = {r["frames"]["sup1"]["frame_id"]: r["frames"]["sup1"]["device_ts_ns"] for r in rows if r["frames"]["sup1"]}

    def in_dead_time(residue: int) -> bool:  # neither edge of the first flash within 1 ms of a kept exposure
        kept = [t for i, t in starts.items() if i % 4 == residue]
        return all(not (t - 1e6 <= edge <= t + exposure_ns + 1e6) for t in kept for edge in (onset, onset + 150e6))

    residue = next(r for r in range(4) if in_dead_time(r))  # an edge lies in at most one frame's exposure
    copy = _copy_as_recorded(take, tmp_path / "thinned")
    (copy / "flashes.jsonl").write_text((copy / "flashes.jsonl").read_text().splitlines()[0] + "\n")
    _rewrite(copy, "sup1", lambda rec: rec if rec["frame_id"] % 4 == residue else None)
    index = (copy / INDEX).read_bytes()
    report = run_rig("record", "align", copy, "--json")
    assert report.returncode == 1, report.stdout  # a camera left unaligned
    cams = json.loads((copy / "alignment.json").read_text())["cameras"]
    assert cams["sup1"]["problem"] and "neighbouring set" in cams["sup1"]["problem"], cams["sup1"]
    assert cams["sup1"]["flashes"][0]["uncertainty_periods"] > 0.5 and cams["sup1"]["placed"] == 0
    assert cams["sup2"]["problem"] is None  # the other camera is aligned, the unaligned one's frames untouched
    rows = [json.loads(line) for line in (copy / INDEX).read_text().splitlines()]
    before = [json.loads(line) for line in index.decode().splitlines()]
    assert [r["frames"]["sup1"] for r in rows] == [r["frames"]["sup1"] for r in before]
