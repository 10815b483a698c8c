"""GoPros that record the take to their cards (`gopro://SERIAL@HOST:PORT?record=card`): a take of two
hardware-triggered sim sources and two GoPro emulators filming the simulated scene (the board's LED in
view), recorded with `rig record`; the first GoPro's download is cut short on purpose and `rig record
fetch` completes it; `rig record align` places each video's frames on the pulses.

The truth: the emulator records frame k of a video from the simulated instant t0 + k / fps
(simulator.gopro.scene: `recordings` keep t0 and fps); a hardware camera's device time is its
pulse's simulated time (plus the sim sensor's trigger latency), so the left camera's frames give
the pulses' simulated times.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import socket
from pathlib import Path

import numpy as np
import pytest

from rig.cameras.gopro import card_client
from rig.sim.clock import SIM_EPOCH_NS
from rig.sim.rig_config import sim_rig_config
from rig.cli import main
from rig.config import dump_config, load_config, parse_config
from rig.storage.layout import INDEX
from rig.storage.media import MANIFEST
from simulator.gopro.scene import scene_emulators

pytestmark = pytest.mark.slow

GOPRO_FPS = (24.0, 30.0)
CUT_AFTER = 200_000  # bytes of the first GoPro's download before the emulator drops the connection


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One loop cache for the module's takes (the scene is rendered once per camera size)."""
    mp = pytest.MonkeyPatch()
    mp.setenv("RIG_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))
    yield
    mp.undo()


def _card_rig(tmp: Path, fps_list) -> tuple:
    """Two sim sources and a card-recording GoPro per rate in `fps_list` (1080p), the LED in view."""
    data = sim_rig_config(n_cameras=2 + len(fps_list), width=640, height=360)
    data["sim"].update(led=True, loop_frames=6)
    gopros = [c for c in data["cameras"] if c["role"] == "supervision"]
    for i, (cam, fps) in enumerate(zip(gopros, fps_list)):
        cam.update(uri=f"gopro://C35013246455{60 + i}@127.0.0.1:{_free_port()}?record=card", width=1920, height=1080,
                   trigger="free", fps=fps)
        for key in ("sim", "exposure_us", "gain", "pixel_format"):
            cam.pop(key, None)
    rig_file = tmp / "rig.toml"
    rig_file.write_text(dump_config(parse_config(data)))
    return load_config(rig_file, check_calibration=False), [c["name"] for c in gopros], rig_file


def _pulse_axis(root: Path, cfg) -> tuple[float, float]:
    """(ns per pulse, simulated ns of pulse 0) from the hardware-triggered left camera's frames."""
    rows = [json.loads(line) for line in (root / INDEX).read_text().splitlines()]
    hw = np.array([(r["trigger"], r["frames"]["left"]["device_ts_ns"]) for r in rows if r["frames"]["left"]], np.float64)
    latency_ns = cfg.camera("left").sim.get("latency_us", 0) * 1e3
    ns_per_pulse, at_zero = np.polyfit(hw[:, 0], hw[:, 1] - latency_ns, 1)
    return ns_per_pulse, at_zero


@pytest.fixture(scope="module")
def take(tmp_path_factory, cache):
    """Records the take (the first GoPro's download cut), says what the take held then, fetches the
    rest with the emulators still up, and keeps the emulators' truth."""
    tmp = tmp_path_factory.mktemp("card")
    cfg, names, rig_file = _card_rig(tmp, GOPRO_FPS)
    emulators = scene_emulators(cfg, SIM_EPOCH_NS)
    out = {"cfg": cfg, "names": names, "root": tmp / "take", "rig": rig_file}
    try:
        emulators[0].cut_next_download(CUT_AFTER)
        out["record"] = _capture(lambda: main(["record", "-c", str(rig_file), "-o", str(tmp / "take"), "--seconds", "5",
                                               "--json"]))
        out["manifest_after_record"] = json.loads((tmp / "take" / MANIFEST).read_text())
        out["parts"] = {p.name: p.stat().st_size for p in (tmp / "take" / "media").rglob("*.part")}
        out["fetch"] = _capture(lambda: main(["record", "fetch", str(tmp / "take"), "--json"]))
        out["card"] = {n: [(m.name, m.size, _sha(e.media_dir / "DCIM" / m.directory / m.name)) for m in e.media.files()]
                       for n, e in zip(names, emulators)}
        out["recordings"] = {n: list(e.recordings) for n, e in zip(names, emulators)}
        out["download_requests"] = {n: [r.range for r in e.requests if r.path.startswith("/videos/")]
                                    for n, e in zip(names, emulators)}
    finally:
        for e in emulators:
            e.stop()
    return out


def _capture(fn) -> tuple[int, str, str]:
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = fn()
    return code, out.getvalue(), err.getvalue()


def test_the_videos_come_into_the_take_and_a_cut_download_is_resumed_by_fetch(take):
    root, names = take["root"], take["names"]
    code, out, err = take["record"]
    rec = json.loads(out)
    # the take itself: the sources' sets, no set waiting for the card cameras, two flashes
    assert rec["sets"] > 100 and rec["complete_sets"] == rec["sets"], rec
    assert set(rec["frames"]) == {"left", "right"}, rec["frames"]
    assert rec["flashes"] == 2
    rows = [json.loads(line) for line in (root / INDEX).read_text().splitlines()]
    assert all(set(r["frames"]) == {"left", "right"} for r in rows)
    # the cut download: exit 1, one error naming the camera and the way out; its .part kept
    assert code == 1
    errors = [line for line in err.strip().splitlines()]
    assert len(errors) == 1 and names[0] in errors[0] and "rig record fetch" in errors[0], err
    print(errors[0])
    before = take["manifest_after_record"]["cameras"]
    assert before[names[0]]["state"] == "pending" and [f["state"] for f in before[names[0]]["files"]] == ["pending"]
    assert before[names[1]]["state"] == "done"
    (kept,) = take["parts"].values()  # what arrived in whole chunks before the cut
    assert 0 < kept <= CUT_AFTER, take["parts"]
    for cam in before.values():  # the shutter's times, in host order
        assert cam["pressed_host_ns"] <= cam["encoding_host_ns"] < cam["released_host_ns"]

    # fetch: the rest of the file by a Range request, the same bytes as on the card
    code, out, err = take["fetch"]
    assert code == 0, err
    fetched = json.loads(out)
    assert fetched["complete"] and all(c["state"] == "done" and c["problem"] is None for c in fetched["cameras"].values())
    assert take["download_requests"][names[0]] == [None, f"bytes={kept}-"]
    assert take["download_requests"][names[1]] == [None]
    manifest = json.loads((root / MANIFEST).read_text())["cameras"]
    for name in names:
        card = take["card"][name]
        assert len(card) == 1  # one video per camera on its card: the take's
        files = manifest[name]["files"]
        assert [(Path(f["file"]).name, f["size"], f["state"]) for f in files] == [(card[0][0], card[0][1], "done")]
        path = root / files[0]["file"]
        assert path.stat().st_size == card[0][1] and _sha(path) == card[0][2]
        assert not list((root / "media" / name).glob("*.part"))
        print(f"{name}: {files[0]['file']} {files[0]['size'] / 1e6:.2f} MB, last download {files[0]['seconds']:.3f} s")

    # fetching again has nothing to do
    again = _capture(lambda: main(["record", "fetch", str(root)]))
    assert again[0] == 0 and "done: 1 of 1 files" in again[1], again


def test_align_places_each_video_on_the_pulses(take, capsys):
    root, names = take["root"], take["names"]
    code, out, err = _run(capsys, "record", "align", root, "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["cameras"] == {} and report["backup"] is None  # the sources were triggered: the index is as it was
    ns_per_pulse, at_zero = _pulse_axis(root, take["cfg"])
    videos = {v["camera"]: v for v in report["videos"]}
    assert set(videos) == set(names)
    for name in names:
        v = videos[name]
        assert v["problem"] is None, v
        truth = take["recordings"][name][0]
        assert v["frames"] == truth.frames and v["fps"] == pytest.approx(truth.fps)
        true_frame0 = (truth.t0 * 1e9 - at_zero) / ns_per_pulse
        true_per_frame = 1e9 / truth.fps / ns_per_pulse
        err0 = (v["trigger_at_frame0"] - true_frame0) / true_per_frame  # in frame periods
        last = truth.frames - 1
        err_last = (v["trigger_at_frame0"] + last * v["pulses_per_frame"] - (true_frame0 + last * true_per_frame)) / true_per_frame
        print(f"{name} at {truth.fps:g} fps: frame 0 at trigger {v['trigger_at_frame0']:.4f} (truth {true_frame0:.4f}): "
              f"error {err0:+.4f} frames; frame {last}: {err_last:+.4f} frames; rate {v['rate_ppm']} ppm; "
              f"stated uncertainty {v['error_frames']} frames")
        assert abs(err0) < 0.1 and abs(err_last) < 0.1, (name, err0, err_last)
        assert len([f for f in v["flashes"] if "onset_s" in f]) == 2
    saved = json.loads((root / "alignment.json").read_text())
    assert saved["videos"] == report["videos"]


def test_an_interrupted_take_keeps_the_card_video_for_fetch(tmp_path, cache, capsys):
    """`rig record` stopped (SIGTERM, as Ctrl-C) soon after the first flash: the shutter is released,
    nothing is downloaded, and `rig record fetch` finds the take's video by what the card gained since
    the press; align places it by the one flash (nominal rate)."""
    import os
    import signal
    import threading
    import time

    cfg, names, rig_file = _card_rig(tmp_path, (GOPRO_FPS[1],))
    root = tmp_path / "take"
    emulators = scene_emulators(cfg, SIM_EPOCH_NS)
    previous = signal.getsignal(signal.SIGTERM)

    def stop_after_first_flash():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            flashes = root / "flashes.jsonl"
            if flashes.is_file() and flashes.read_text().strip():
                time.sleep(0.5)  # the flash's last frames
                os.kill(os.getpid(), signal.SIGTERM)
                return
            time.sleep(0.05)

    try:
        older = card_client(cfg.camera(names[0]).uri).connect()  # a clip on the card from before: not the take's
        older.shutter_start()
        time.sleep(0.3)
        older.shutter_stop()
        older.wait_ready()
        older.close()
        watcher = threading.Thread(target=stop_after_first_flash, daemon=True)
        watcher.start()
        code, out, err = _run(capsys, "record", "-c", rig_file, "-o", root, "--seconds", "60", "--json")
        watcher.join()
        rec = json.loads(out)
        assert code == 1 and rec["stopped_by"] == "interrupt" and rec["flashes"] == 1, (rec, err)
        assert len(err.strip().splitlines()) == 1 and "rig record fetch" in err, err
        manifest = json.loads((root / MANIFEST).read_text())["cameras"][names[0]]
        assert manifest["files"] is None and manifest["released_host_ns"] is not None, manifest
        assert len(manifest["card_before"]) == 1
        assert not emulators[0].state.encoding  # the take released the shutter
        code, out, err = _run(capsys, "record", "fetch", root)
        assert code == 0, err
        card = {m.name: m.size for m in emulators[0].media.files()}
        truth = emulators[0].recordings[-1]
    finally:
        signal.signal(signal.SIGTERM, previous)
        for e in emulators:
            e.stop()
    files = json.loads((root / MANIFEST).read_text())["cameras"][names[0]]["files"]
    assert [(Path(f["file"]).name, f["size"], f["state"]) for f in files] == [(truth.file.name, card[truth.file.name], "done")]
    code, out, err = _run(capsys, "record", "align", root, "--json")
    assert code == 0, err
    (v,) = json.loads(out)["videos"]
    ns_per_pulse, at_zero = _pulse_axis(root, cfg)
    err0 = (v["trigger_at_frame0"] - (truth.t0 * 1e9 - at_zero) / ns_per_pulse) * ns_per_pulse * truth.fps / 1e9
    print(f"interrupted take: {truth.frames} frames; frame 0 off by {err0:+.4f} frames (one flash, nominal rate)")
    assert v["rate_ppm"] is None and abs(err0) < 0.1, v


def test_fetch_and_align_bad_input_say_one_line(take, tmp_path, capsys):
    root, names = take["root"], take["names"]
    for argv, code, words in [
        (["record", "fetch", tmp_path / "nothing"], 2, "no such sequence folder"),
        (["record", "fetch", tmp_path], 2, "not a sequence"),
        (["record", "fetch", root, "--camera", "left"], 2, "did not record to its card"),
        (["record", "align", root, "--camera", "nosuch"], 2, "no camera nosuch"),
    ]:
        got, out, err = _run(capsys, *argv)
        assert got == code and len(err.strip().splitlines()) == 1 and words in err, (argv, got, err)
    # a take without card cameras
    plain = tmp_path / "plain"
    plain.mkdir()
    shutil.copy(root / "sequence.json", plain)
    got, out, err = _run(capsys, "record", "fetch", plain)
    assert got == 2 and len(err.strip().splitlines()) == 1 and f"no {MANIFEST}" in err, err

    # the cameras are gone (the emulators stopped) and a file is missing: exit 1, one line, nothing lost
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    manifest = json.loads((copy / MANIFEST).read_text())
    f = manifest["cameras"][names[1]]["files"][0]
    f["state"] = "pending"
    (copy / MANIFEST).write_text(json.dumps(manifest))
    kept = sorted(p.relative_to(copy) for p in copy.rglob("*") if p.is_file() and p.name != MANIFEST)
    got, out, err = _run(capsys, "record", "fetch", copy)
    print(out + err)
    assert got == 1 and len(err.strip().splitlines()) == 1 and names[1] in err and "no answer" in err, err
    assert sorted(p.relative_to(copy) for p in copy.rglob("*") if p.is_file() and p.name != MANIFEST) == kept
    after = json.loads((copy / MANIFEST).read_text())["cameras"][names[1]]
    assert after["files"][0]["state"] == "pending" and "no answer" in after["problem"]
    # align says the video is not downloaded yet, aligns the other and exits 1
    got, out, err = _run(capsys, "record", "align", copy)
    print(out + err)
    assert got == 1 and len(err.strip().splitlines()) == 1 and "not downloaded yet" in err, err
    # validate: a video still to fetch is a warning; a downloaded one cut short is an error
    got, out, err = _run(capsys, "record", "validate", copy)
    assert got == 0 and f"{names[1]}: 1 video(s) not downloaded yet" in out, (out, err)
    done = copy / manifest["cameras"][names[0]]["files"][0]["file"]
    done.write_bytes(done.read_bytes()[:-1000])
    got, out, err = _run(capsys, "record", "validate", copy)
    assert got == 1 and f"{done.relative_to(copy)}: " in out and "media.json says" in out, (out, err)


def test_config_check_says_what_is_wrong_with_a_card_camera(tmp_path, capsys):
    data = sim_rig_config(n_cameras=3, width=640, height=360)
    gopro = next(c for c in data["cameras"] if c["role"] == "supervision")
    for key in ("sim", "exposure_us", "gain"):
        gopro.pop(key, None)
    uri = "gopro://C3501324645570@127.0.0.1:8080?record=card"
    gopro.update(uri=uri, trigger="free", width=1920, height=1080, fps=25.0)
    good = dump_config(parse_config(data))
    path = tmp_path / "rig.toml"
    path.write_text(good)
    got, out, err = _run(capsys, "config", "check", path)
    assert got == 0, (out, err)
    for old, new, words in [
        ("fps = 25.0", "fps = 15.0", "records at 24, 25, 30"),
        ("width = 1920", "width = 640", "records 3840x2160"),
        (uri, uri.replace("card", "disk"), "record must be webcam or card"),
        (uri, uri + "&port=9000", "drop port="),
        ('fps = 25.0\ntrigger = "free"', 'fps = 25.0\ntrigger = "hardware"', "cannot be triggered"),
    ]:
        assert old in good, old
        path.write_text(good.replace(old, new))
        got, out, err = _run(capsys, "config", "check", path)
        assert got == 2 and words in out + err, (new, got, out, err)
