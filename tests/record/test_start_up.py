"""A sim command says what its start-up is doing, and its status line shows no nonsense rates (issue 11
point 8: seconds of silence before the first set, then "124008 sets/s" on the first status line)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading

from rig.progress import MIN_RATE_S, rate, rate_text
from rig.config import dump_config, parse_config
from rig.sim.rig_config import sim_rig_config
from tests.record.test_record import rig_file
from tests.rig.cli_helpers import REPO, run_rig

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
RATE = re.compile(r"(\S+)\s+(sets/s|MB/s)")


def run_on_a_terminal(*args) -> tuple[int, str, str]:
    """`rig ...` with stderr on a pty (so the live status line draws): (exit status, stdout, what the
    terminal showed, escape codes removed)."""
    master, slave = os.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "rig", *map(str, args)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=slave, text=True, env=dict(os.environ, COLUMNS="200"))
    os.close(slave)
    chunks = []

    def read():
        while True:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # EIO: the command ended and closed the terminal
                return
            if not chunk:
                return
            chunks.append(chunk)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    stdout, _ = proc.communicate(timeout=120)
    reader.join(10)
    os.close(master)
    return proc.returncode, stdout, ANSI.sub("", b"".join(chunks).decode(errors="replace"))


def test_no_status_text_shows_a_rate_before_there_is_one(tmp_path):
    rc, stdout, shown = run_on_a_terminal("record", "-c", rig_file(tmp_path), "-o", tmp_path / "take", "--sets", 75)
    assert rc == 0, shown
    texts = [t for t in re.split(r"[\r\n]+", shown) if "sets/s" in t]
    assert texts, shown
    first = RATE.findall(texts[0])
    assert first == [("--", "sets/s"), ("--", "MB/s")], texts[0]  # the first set: no time has passed, no rate
    rates = {"sets/s": [], "MB/s": []}
    for t in texts:
        for value, unit in RATE.findall(t):
            if value != "--":
                rates[unit].append(float(value))
    # the rig runs at 30 sets/s of two 160x90 RGB frames (2.6 MB/s): nothing near 124008 sets/s
    assert all(0 < r <= 45 for r in rates["sets/s"]), rates
    assert all(0 < r <= 5 for r in rates["MB/s"]), rates
    assert rates["sets/s"], "2.5 s of recording shows a rate once it has one"


def test_rate_waits_for_enough_time_and_counts():
    assert rate(1, 1e-6) is None and rate(3, 5.0) is None and rate(30, MIN_RATE_S / 2) is None
    assert rate(30, 1.0) == 30.0
    assert rate_text(None) == "   --" and rate_text(29.96) == " 30.0"


def start_up_notes(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if not line.startswith("rig: error:")]


def test_sim_record_says_what_its_start_up_is_doing_on_stderr_in_order(tmp_path):
    proc = run_rig("record", "-c", rig_file(tmp_path), "-o", tmp_path / "take", "--sets", 3)
    assert proc.returncode == 0, proc.stderr
    notes = start_up_notes(proc.stderr)
    assert notes[0] == "rig: opened 2 cameras (left, right) and the trigger board sim://trigger"
    assert notes[1].startswith("rig: preparing the simulated scene for left, right")
    # the board clock's warm-up is said when any of its 3 s is left after the pre-rendering
    assert all(n.startswith("rig: warming up the trigger board clock (") for n in notes[2:]) and len(notes) <= 3, notes
    assert proc.stdout.startswith("recorded 3 sets")  # stdout: the result only

    # no pre-rendered loop: the warm-up is then nearly all of the start, and is said
    data = sim_rig_config(n_cameras=2, width=160, height=90, fps=30.0)
    data["sim"]["loop_frames"] = 0
    cfg = tmp_path / "live.toml"
    cfg.write_text(dump_config(parse_config(data)))
    proc = run_rig("grab", "-c", cfg, "-n", 2, "-o", tmp_path / "grab")
    assert proc.returncode == 0, proc.stderr
    notes = start_up_notes(proc.stderr)
    assert len(notes) == 2 and notes[0].startswith("rig: opened 2 cameras")
    assert re.fullmatch(r"rig: warming up the trigger board clock \(\d\.\d s\)", notes[1]), notes


def test_json_mode_keeps_stderr_for_errors_only(tmp_path):
    cfg = rig_file(tmp_path)
    for argv in (["record", "-c", cfg, "-o", tmp_path / "take", "--sets", 3, "--json"],
                 ["grab", "-c", cfg, "-n", 1, "-o", tmp_path / "grab", "--json"],
                 ["sim", "snapshot", "-c", cfg, "-t", 0, "-o", tmp_path / "snap", "--json"]):
        proc = run_rig(*argv)
        assert proc.returncode == 0 and proc.stderr == "", (argv, proc.stderr)
        json.loads(proc.stdout)


def test_sim_snapshot_says_what_it_renders(tmp_path):
    proc = run_rig("sim", "snapshot", "-c", rig_file(tmp_path), "-t", 0.5, "-o", tmp_path / "snap")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.splitlines() == ["rig: building the simulated scene and rendering 2 cameras at t = 0.5 s",
                                        "rig: rendering left (1/2)", "rig: rendering right (2/2)"]
