"""Camera daemons under `rig up` on the simulated rig: sessions read them, a killed or hung daemon is
restarted, the control API refuses bad input, a session on another "host" reads them over TCP."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from rig.sim.rig_config import sim_rig_config
from rig.config import dump_config, parse_config
from rig.storage.layout import INDEX
from rig.storage.validate import validate
from tests.rig.cli_helpers import REPO


def rig_file(folder: Path, n: int = 6, width: int = 160, height: int = 90, trigger: str = "hardware",
             camera_sim: dict | None = None) -> Path:
    data = sim_rig_config(n_cameras=n, width=width, height=height, fps=30.0, trigger=trigger)
    for cam in data["cameras"]:
        cam["sim"].update(camera_sim or {})
    data["sim"]["loop_frames"] = 6  # a short pre-rendered loop keeps the tests quick
    path = folder / "rig.toml"
    path.write_text(dump_config(parse_config(data)))
    return path


def env_for(root: Path) -> dict:
    return dict(os.environ, RIG_SHM_ROOT=str(root))


def rig(*args, env, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rig", *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=REPO, env=env)


def communicate(proc: subprocess.Popen, timeout: float) -> tuple[str, str]:
    """The process's output once it ends; killed if it does not end in time (a failing test leaves no
    process behind)."""
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise


def state(root: Path, rig_name: str) -> dict | None:
    try:
        return json.loads((root / rig_name / "supervisor.json").read_text())
    except (OSError, ValueError):
        return None


def wait_running(root: Path, rig_name: str, cameras: int, timeout: float = 60.0) -> dict:
    """Until every daemon of the rig runs: its cameras' and, when it has one, its trigger board's."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        s = state(root, rig_name)
        if s and len([n for n in s["cameras"] if n != "@board"]) == cameras and all(c["state"] == "running" for c in s["cameras"].values()):
            return s
        time.sleep(0.1)
    raise AssertionError(f"daemons not up within {timeout} s: {state(root, rig_name)}")


class Up:
    """`rig up` in a subprocess, with its own shared-memory root."""

    def __init__(self, config: Path, root: Path, *extra, env: dict | None = None):
        self.root, self.env = root, dict(env_for(root), **(env or {}))
        self.proc = subprocess.Popen([sys.executable, "-m", "rig", "up", "-c", str(config), "--no-advertise", *extra],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO, env=self.env)

    def stop(self) -> str:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        out, _ = self.proc.communicate(timeout=30)
        return out


@pytest.fixture
def six(tmp_path):
    config = rig_file(tmp_path)
    up = Up(config, tmp_path / "shm")
    try:
        wait_running(up.root, "sim-6cam", 6)
        yield config, up
    finally:
        out = up.stop()
        print(out)
    assert not any((up.root / "sim-6cam").glob("*")), "rig up left files behind"  # rings, info and state files are gone


def start_take(config: Path, up: Up, seq: Path, seconds: float) -> subprocess.Popen:
    """`rig record --seconds` on `rig up`'s daemons, returned once its sets are being written."""
    rec = subprocess.Popen([sys.executable, "-m", "rig", "record", "-c", str(config), "-o", str(seq), "--seconds", str(seconds), "--json"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=up.env)
    deadline = time.monotonic() + 60
    while not (seq / INDEX).exists() or (seq / INDEX).stat().st_size < 2000:
        assert rec.poll() is None and time.monotonic() < deadline, rec.communicate()
        time.sleep(0.05)
    return rec


def _record_while(config: Path, up: Up, seq: Path, seconds: float, fault, at: float = 3.0):
    """`rig record` for `seconds` while `fault(daemon pid)` hits the daemon of sup2 `at` seconds in."""
    rec = start_take(config, up, seq, seconds)
    time.sleep(at)
    victim = state(up.root, "sim-6cam")["cameras"]["sup2"]["pid"]
    hit = time.monotonic()
    fault(victim)
    back = None
    while back is None and time.monotonic() - hit < 15:
        s = state(up.root, "sim-6cam")["cameras"]["sup2"]
        if s["pid"] not in (None, victim):
            back = time.monotonic() - hit  # a new daemon process runs
        time.sleep(0.02)
    out, err = communicate(rec, 120)
    return rec.returncode, out, err, back, victim


def _check_take(seq: Path, out: str):
    rows = [json.loads(line) for line in (seq / INDEX).read_text().splitlines() if line.endswith("}")]
    summary = json.loads(out)
    v = validate(seq)
    assert v.readable and v.errors == [], v.errors
    others = [c for c in rows[0]["frames"] if c != "sup2"]
    lost = {c: [r["set"] for r in rows if r["frames"][c] is None] for c in others}
    assert not any(lost.values()), f"a camera other than sup2 lost frames: {lost}; {out}"
    gap = [i for i, r in enumerate(rows) if r["frames"]["sup2"] is None]
    assert gap and gap[-1] < len(rows) - 10, "sup2 never came back"  # missing for the gap, then there again
    mismatched = 0
    for r in rows:
        times = {round(f["sim_time_s"], 4) for f in r["frames"].values() if f is not None}
        mismatched += len(times) > 1
    assert mismatched == 0
    assert summary["frames"]["left"] == summary["sets"]
    return len(gap), len(rows)


def test_kill_9_of_a_daemon_during_a_take_is_a_gap_in_that_camera_only(six, tmp_path):
    config, up = six
    code, out, err, back, victim = _record_while(config, up, tmp_path / "seq", 9.0, lambda pid: os.kill(pid, signal.SIGKILL))
    assert back is not None and back < 2.0, back  # measured 0.2-0.4 s (the first back-off)
    gap, sets = _check_take(tmp_path / "seq", out)
    print(f"kill -9: new daemon after {back:.2f} s, sup2 missing in {gap} of {sets} sets")
    assert "sup2" in err
    s = state(up.root, "sim-6cam")
    assert s["cameras"]["sup2"]["restarts"] == 1 and all(c["restarts"] == 0 for n, c in s["cameras"].items() if n != "sup2")
    assert any(e["kind"] == "restart" and "SIGKILL" in e["detail"] for e in s["events"])


def test_a_hung_daemon_is_killed_and_restarted(six, tmp_path):
    config, up = six
    code, out, err, back, victim = _record_while(config, up, tmp_path / "seq", 9.0, lambda pid: os.kill(pid, signal.SIGSTOP))
    assert back is not None and back < 2.0, back  # 1 s without a heartbeat, then the first back-off
    print(f"hung daemon: a new one runs {back:.2f} s after the hang")
    _check_take(tmp_path / "seq", out)
    assert any(e["kind"] == "restart" and "heartbeat stopped" in e["detail"] for e in state(up.root, "sim-6cam")["events"])


def test_slow_work_in_a_daemon_is_not_taken_for_a_hang(tmp_path):
    """A camera that vanished and comes back is opened again, which takes a GigE camera seconds (here
    an emulated 1.5 s) inside the acquisition loop: longer than the supervisor's stale time, and the
    daemon must not be killed for it."""
    config = rig_file(tmp_path, n=1, trigger="free", camera_sim={"open_s": 1.5, "disconnect_after_s": 1.0, "reconnect_after_s": 0.3})
    up = Up(config, tmp_path / "shm", "--stale", "0.5")
    try:
        wait_running(up.root, "sim-1cam", 1, timeout=120)
        api = json.loads((up.root / "sim-1cam" / "left.json").read_text())["api"]
        deadline = time.monotonic() + 30
        while not any(e["kind"] == "camera_back" for e in json.loads(_api(api + "/status")[1]).get("events", [])):
            assert time.monotonic() < deadline, json.loads(_api(api + "/status")[1])
            time.sleep(0.1)
        s = state(up.root, "sim-1cam")
        assert s["cameras"]["left"]["restarts"] == 0, s["events"]
        frames = json.loads(_api(api + "/status")[1])["frames"]
        time.sleep(0.5)
        assert json.loads(_api(api + "/status")[1])["frames"] > frames  # acquiring again, same process
    finally:
        print(up.stop())


def _api(url: str, method: str = "GET", body: bytes | None = None, headers: dict | None = None):
    req = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def test_the_control_api_refuses_bad_input_and_a_flood_without_hurting_capture(tmp_path):
    config = rig_file(tmp_path, n=1, trigger="free")
    up = Up(config, tmp_path / "shm")
    try:
        wait_running(up.root, "sim-1cam", 1)
        info = json.loads((up.root / "sim-1cam" / "left.json").read_text())
        api = info["api"]
        status, body = _api(api + "/status")
        assert status == 200 and json.loads(body)["state"] == "running"
        cases = [("PUT", "/settings", b"{not json", 400), ("PUT", "/settings", b"[1, 2]", 400),
                 ("PUT", "/settings", b'{"exposure_us": -5}', 422), ("PUT", "/settings", b'{"gain": 1e308}', 422),
                 ("PUT", "/settings", b'{"width": 4000}', 422), ("PUT", "/settings", b'{"colour": 3}', 422),
                 ("PUT", "/settings", b'{"trigger": "psychic"}', 422), ("PUT", "/settings", b"x" * 10000, 413),
                 ("POST", "/trigger", b"", 409), ("GET", "/frames/next?after=0&timeout=99", None, 400),
                 ("GET", "/frames/next?after=abc", None, 400), ("GET", "/cameras/unknown", None, 404)]
        for method, path, body, want in cases:
            got, text = _api(api + path, method, body)
            assert got == want, (method, path, got, text)
            assert "error" in json.loads(text) or want == 404
        frames_before = json.loads(_api(api + "/status")[1])["frames"]
        t0 = time.monotonic()
        with ThreadPoolExecutor(16) as pool:
            codes = list(pool.map(lambda i: _api(api + ("/status" if i % 2 else "/settings"), "PUT" if i % 3 == 0 else "GET",
                                                 b'{"gain": "loud"}' if i % 3 == 0 else None)[0], range(600)))
        spent = time.monotonic() - t0
        assert set(codes) <= {200, 405, 422, 503}, set(codes)
        after = json.loads(_api(api + "/status")[1])
        # capture went on at its rate through the flood (30 fps)
        assert after["frames"] - frames_before >= 0.8 * 30 * spent, (after["frames"], frames_before, spent)
        status, body = _api(api + "/settings", "PUT", b'{"exposure_us": 8000, "gain": 3}')
        assert status == 200 and json.loads(body)["exposure_us"] == 8000
        time.sleep(0.5)
        assert json.loads(_api(api + "/status")[1])["state"] == "running"
    finally:
        up.stop()


def test_a_daemon_on_another_address_needs_its_token(tmp_path):
    config = rig_file(tmp_path, n=1, trigger="free")
    env = env_for(tmp_path / "shm")
    proc = subprocess.Popen([sys.executable, "-m", "rig", "daemon", "left", "-c", str(config), "--host", "0.0.0.0", "--no-advertise"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
    try:
        line = proc.stderr.readline()
        assert "API token" in line, line
        token = line.split()[-1]
        info_file = tmp_path / "shm" / "sim-1cam" / "left.json"
        deadline = time.monotonic() + 60
        while not info_file.exists():
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.05)
        api = json.loads(info_file.read_text())["api"]
        assert _api(api + "/status")[0] == 401
        assert _api(api + "/status", headers={"Authorization": "Bearer wrong"})[0] == 401
        assert _api(api + "/status", headers={"Authorization": f"Bearer {token}"})[0] == 200
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)
    assert proc.returncode == 0 and not info_file.exists()


def test_a_session_on_another_host_reads_the_daemons_over_tcp(tmp_path):
    """Host A runs the daemons (its own shm root); host B's config names them daemon://HOST:PORT and
    B's session (another shm root: no ring to map) records them through their APIs."""
    a = tmp_path / "a"
    a.mkdir()
    config = rig_file(a, n=2)
    up = Up(config, tmp_path / "shm-a")
    try:
        wait_running(up.root, "sim-2cam", 2)
        data = sim_rig_config(n_cameras=2, width=160, height=90, fps=30.0)
        for cam in data["cameras"]:
            info = json.loads((up.root / "sim-2cam" / f"{cam['name']}.json").read_text())
            cam["uri"] = "daemon://" + info["api"].split("//", 1)[1]
            cam.pop("sim")
        b = tmp_path / "b"
        b.mkdir()
        (b / "rig.toml").write_text(dump_config(parse_config(data)))
        proc = rig("record", "-c", b / "rig.toml", "-o", b / "seq", "--sets", 60, "--json", env=env_for(tmp_path / "shm-b"))
        assert proc.returncode == 0, proc.stderr
        out = json.loads(proc.stdout)
        assert out["sets"] == 60 and out["complete_sets"] == 60, out
        v = validate(b / "seq")
        assert v.readable and v.errors == [] and v.missing == {"left": 0, "right": 0}
        assert not (tmp_path / "shm-b").exists() or not any((tmp_path / "shm-b").rglob("*"))
    finally:
        up.stop()


def test_bad_daemon_commands_say_what_is_wrong_in_one_line(tmp_path):
    from tests.rig.cli_helpers import assert_one_line_error

    config = rig_file(tmp_path, n=2)
    env = env_for(tmp_path / "shm")
    assert_one_line_error(rig("daemon", "middle", "-c", config, env=env), "no camera named 'middle'", "left, right")
    assert_one_line_error(rig("daemon", "left", "-c", config, "--slots", 0, env=env), "--slots")
    assert_one_line_error(rig("daemon", "left", "-c", tmp_path / "missing.toml", env=env), "missing.toml")
    assert_one_line_error(rig("up", "-c", config, "--status", env=env), "no supervisor runs", code=1)
    assert_one_line_error(rig("up", "-c", config, "--stale", -1, env=env), "--stale")
    down = rig("down", "-c", config, env=env)
    assert down.returncode == 0 and "no supervisor was running" in down.stdout


def test_the_trigger_board_daemon_drives_takes_and_a_killed_one_comes_back(tmp_path):
    """`rig up` owns the board too (`@board`): a take of 45 sets is the board's train of 45 pulses, as
    without daemons; a board daemon killed during a take is restarted and the take goes on with a new
    train (the session's resume, as for a board plugged back in)."""
    config = rig_file(tmp_path, n=2)
    up = Up(config, tmp_path / "shm")
    try:
        s = wait_running(up.root, "sim-2cam", 2)
        assert "@board" in s["cameras"] and (up.root / "sim-2cam" / "@board.json").exists()
        proc = rig("record", "-c", config, "-o", tmp_path / "seq", "--sets", 45, "--json", env=up.env)
        assert proc.returncode == 0, proc.stderr
        out = json.loads(proc.stdout)
        assert out["sets"] == 45 and out["complete_sets"] == 45 and out["frames_lost"] == {"left": 0, "right": 0}
        rows = [json.loads(line) for line in (tmp_path / "seq" / INDEX).read_text().splitlines() if line.endswith("}")]
        assert [r["trigger"] for r in rows] == list(range(45))

        rec = start_take(config, up, tmp_path / "seq2", 9)
        index = tmp_path / "seq2" / INDEX
        time.sleep(2.0)
        os.kill(state(up.root, "sim-2cam")["cameras"]["@board"]["pid"], signal.SIGKILL)
        out2, err2 = communicate(rec, 120)
        rows2 = [json.loads(line) for line in index.read_text().splitlines() if line.endswith("}")]
        ts = [r["host_ts_ns"] for r in rows2]
        gaps = [i for i, (a, b) in enumerate(zip(ts, ts[1:])) if b - a > 0.5e9]
        # one pause while no board pulsed (measured 2.8 s), then a new train: a second of sets at least
        assert len(gaps) == 1 and len(rows2) - gaps[0] > 30, (gaps, len(rows2))
        assert all(all(f is not None for f in r["frames"].values()) for r in rows2)  # no set lost a camera
        v = validate(tmp_path / "seq2")
        assert v.readable and v.errors == [], v.errors
        assert state(up.root, "sim-2cam")["cameras"]["@board"]["restarts"] == 1
        assert "trigger board" in err2
    finally:
        print(up.stop())


def test_a_take_of_known_length_ends_on_time_when_the_board_never_comes_back(tmp_path):
    """The board's daemon killed while its supervisor is stopped, so no board ever pulses again: a
    `--seconds 5` take still ends at 5 s, with what it had and the board's loss said (it waited for
    a set that never came, for ever, before)."""
    config = rig_file(tmp_path, n=2)
    up = Up(config, tmp_path / "shm")
    try:
        wait_running(up.root, "sim-2cam", 2)
        rec = start_take(config, up, tmp_path / "seq", 5)
        t_first = time.monotonic()
        up.proc.send_signal(signal.SIGSTOP)  # no supervisor: nothing restarts the board
        os.kill(state(up.root, "sim-2cam")["cameras"]["@board"]["pid"], signal.SIGKILL)
        out, err = communicate(rec, 30)
        took = time.monotonic() - t_first
        assert took < 5 + 6, took  # the take's 5 s from its first set, the stop's settling, the process's exit
        result = json.loads(out)
        assert result["stopped_by"] == "done" and 0 < result["sets"] == result["complete_sets"], result
        assert "trigger board" in err and ("is gone" in err or "stopped answering" in err), err
        v = validate(tmp_path / "seq")
        assert v.readable and v.errors == [], v.errors
    finally:
        up.proc.send_signal(signal.SIGCONT)
        up.stop()


def test_rig_up_daemons_are_found_by_discover_network_within_3_s(tmp_path):
    config = rig_file(tmp_path, n=2, trigger="free")
    root = tmp_path / "shm"
    proc = subprocess.Popen([sys.executable, "-m", "rig", "up", "-c", str(config), "--interface", "127.0.0.1"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO, env=env_for(root))
    try:
        wait_running(root, "sim-2cam", 2)
        t0 = time.monotonic()
        found = rig("discover", "--network", "--json", "--interface", "127.0.0.1", "--rig", "sim-2cam", env=env_for(root))
        spent = time.monotonic() - t0  # the whole command, Python's start included
        assert found.returncode == 0, found.stderr
        daemons = json.loads(found.stdout)["daemons"]
        assert sorted(d["camera"] for d in daemons) == ["left", "right"], daemons
        for d in daemons:
            info = json.loads((root / "sim-2cam" / f"{d['camera']}.json").read_text())
            assert d["api_url"] == info["api"] and d["shm"] == info["ring"] and d["pid"] == info["pid"] and d["uri"] == f"sim://{d['camera']}"
        assert spent < 3.0, spent
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
