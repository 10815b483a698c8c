"""`rig console` on the command line: bad input is one line (exit 2) before any camera opens; a
non-loopback address gets an operator token, and a request without it is refused."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request

import pytest

from tests.rig.cli_helpers import REPO, assert_one_line_error, run_rig


@pytest.fixture
def sim_config(tmp_path):
    proc = run_rig("config", "init", "--sim", "--cameras", "2", "--width", "160", "--height", "96", "--fps", "10",
                   str(tmp_path / "rig.toml"), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    return tmp_path / "rig.toml"


@pytest.mark.parametrize("args, said", [(["--port", "70000"], "--port must be between"),
                                        (["--token", "short"], "--token must be at least 8"),
                                        (["--token", "same-token-1", "--viewer-token", "same-token-1"], "must differ"),
                                        (["--seconds", "-1"], "--seconds must be positive"),
                                        (["--board", "no-such-board.toml"], "no such board file")])
def test_bad_arguments_are_one_line(sim_config, args, said):
    assert_one_line_error(run_rig("console", "-c", sim_config, *args), said)


def test_a_missing_config_is_one_line(tmp_path):
    assert_one_line_error(run_rig("console", "-c", tmp_path / "none.toml"), "none.toml")


def test_a_non_loopback_address_gets_a_token_and_refuses_requests_without_it(sim_config):
    proc = subprocess.Popen([sys.executable, "-m", "rig", "console", "-c", str(sim_config), "--host", "0.0.0.0", "--port", "0",
                             "--seconds", "60"], stderr=subprocess.PIPE, text=True, cwd=sim_config.parent,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        lines = []
        deadline = time.monotonic() + 60
        while not any("operator token" in line for line in lines):
            assert time.monotonic() < deadline and proc.poll() is None, "".join(lines)
            lines.append(proc.stderr.readline())
        url = re.search(r"serving (http://\S+?)\?token=(\S+)", "".join(lines))
        base, token = url.group(1), url.group(2)
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(base + "api/status", timeout=10)
        assert e.value.code == 401
        with urllib.request.urlopen(base + f"api/status?token={token}", timeout=10) as r:
            assert json.load(r)["role"] == "operator"
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    assert proc.returncode == 0
