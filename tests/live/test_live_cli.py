"""`rig live` as a user runs it: a simulated rig served on loopback, its status, snapshot and MJPEG
routes, the output video, the token rule, and bad input (one line, exit 2)."""
from __future__ import annotations

import json
import re
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from rig.sim.rig_config import sim_rig_config
from rig.config import dump_config
from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]


@pytest.fixture(scope="module")
def rig_toml(tmp_path_factory) -> Path:
    from rig.config import parse_config

    path = tmp_path_factory.mktemp("live-cli") / "rig.toml"
    path.write_text(dump_config(parse_config(sim_rig_config(6, 320, 180, fps=15.0))))
    return path


def start_live(*args) -> tuple[subprocess.Popen, str]:
    """`rig live ...` in the background; returns it and the URL it printed."""
    proc = subprocess.Popen([sys.executable, "-m", "rig", "live", *map(str, args)], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    lines = []
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        m = re.search(r"serving (http://\S+)", line)
        if m:
            return proc, m.group(1)
    proc.kill()
    raise AssertionError("rig live did not say where it serves: " + "".join(lines) + proc.stderr.read())


def get(url: str, timeout: float = 30.0) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def test_live_serves_a_simulated_rig_and_records_its_output(rig_toml, tiny_onnx, tmp_path):
    video = tmp_path / "out.mp4"
    proc, url = start_live("-c", rig_toml, "--model", tiny_onnx.path, "--port", 0, "--seconds", 15, "--threads", 1,
                           "--record-output", video, "--record-view", "sup2", "--json")
    try:
        base = url.split("?")[0]
        code, png = get(base + "snapshot.png?t=0.25")
        assert code == 200 and png[:8] == b"\x89PNG\r\n\x1a\n"
        code, body = get(base + "status")
        status = json.loads(body)
        assert code == 200 and status["fps_in"] > 0 and status["health"]["ok"] and status["stage1_runs"] > 0
        code, body = get(base + "snapshot.png?preset=nope")
        assert code == 400 and b"nope" in body
    finally:
        out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["url"].startswith("http://127.0.0.1:")
    assert summary["stage1_runs"] > 0 and summary["view_runs"] >= summary["stage1_runs"]
    rec = summary["record_output"]
    assert rec["path"] == str(video) and rec["frames"] > 0
    from rig.live.video import read_frame_count

    assert read_frame_count(video) == rec["frames"]


def test_a_non_loopback_bind_always_has_a_token(rig_toml, tiny_onnx):
    proc, url = start_live("-c", rig_toml, "--model", tiny_onnx.path, "--host", "0.0.0.0", "--port", 0, "--seconds", 8)
    try:
        token = re.search(r"\?token=(\S+)", url).group(1)
        port = re.search(r":(\d+)/", url).group(1)
        assert get(f"http://127.0.0.1:{port}/status")[0] == 401
        assert get(f"http://127.0.0.1:{port}/status?token=wrong-{token}")[0] == 401
        assert get(f"http://127.0.0.1:{port}/status?token={token}")[0] == 200
    finally:
        proc.communicate(timeout=60)
    assert proc.returncode == 0


@pytest.mark.parametrize("args, fragments", [
    (["--token", "short"], ["--token", "at least 8"]),
    (["--port", "70000"], ["--port"]),
    (["--jpeg-quality", "0"], ["--jpeg-quality"]),
    (["--seconds", "-1"], ["--seconds"]),
    (["--model", "/nonexistent/model.onnx"], ["/nonexistent/model.onnx"]),
    (["--calibration", "/nonexistent/calib.json"], ["/nonexistent/calib.json"]),
    (["--replay", "/nonexistent/take"], ["--replay"]),
])
def test_bad_input_is_one_line_and_exit_2(rig_toml, tiny_onnx, args, fragments):
    base = ["live", "-c", rig_toml, "--port", 0, "--seconds", 1]
    if "--model" not in args:
        base += ["--model", tiny_onnx.path]
    assert_one_line_error(run_rig(*base, *args), *fragments)


def test_an_oracle_model_or_an_existing_output_video_is_refused(rig_toml, tiny_onnx, oracle_onnx, tmp_path):
    assert_one_line_error(run_rig("live", "-c", rig_toml, "--model", oracle_onnx.path, "--seconds", 1), "oracle")
    kept = tmp_path / "kept.mp4"
    kept.write_bytes(b"not to be lost")
    assert_one_line_error(run_rig("live", "-c", rig_toml, "--model", tiny_onnx.path, "--record-output", kept, "--seconds", 1), "exists")
    assert kept.read_bytes() == b"not to be lost"
