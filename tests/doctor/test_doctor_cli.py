"""`rig doctor` as a user runs it: for real on this host, then bad input."""
from __future__ import annotations

import json
import subprocess

from rig.doctor import AREAS
from tests.rig.cli_helpers import assert_one_line_error, run_rig


def sim_config(tmp_path):
    cfg = tmp_path / "rig.toml"
    assert run_rig("config", "init", "--sim", cfg).returncode == 0
    return cfg


def test_doctor_runs_for_real_on_this_host(tmp_path):
    """Every area of the simulated rig's checks on this very host, true values, exit 0 or 1 by the verdict;
    the fix script is bash that `bash -n` accepts."""
    cfg = sim_config(tmp_path)
    fix = tmp_path / "fix.sh"
    proc = run_rig("doctor", "-c", cfg, "--json", "--output", tmp_path / "takes", "--write-test-mb", "8", "--fix-script", fix)
    doc = json.loads(proc.stdout)
    assert proc.returncode == (1 if doc["verdict"] == "fail" else 0), proc.stderr
    assert {c["area"] for c in doc["checks"]} == set(AREAS)
    assert sum(doc["counts"].values()) == len(doc["checks"])
    rate = next(c for c in doc["checks"] if c["name"].startswith("write rate"))
    assert "(8.0 MiB in " in rate["measured"]
    with open("/sys/devices/system/cpu/online") as f:
        online = f.read().strip()
    cpu = next(c for c in doc["checks"] if c["name"] == "CPUs")
    n_online = sum(int(b) - int(a) + 1 if b else 1 for a, _, b in (p.partition("-") for p in online.split(",")))
    assert 1 <= int(cpu["measured"].split()[0]) <= n_online  # the CPUs online, or a container's quota below that
    assert subprocess.run(["bash", "-n", str(fix)]).returncode == 0
    assert not (tmp_path / "takes").exists()  # the doctor measures, it makes nothing
    text = run_rig("doctor", "-c", cfg, "--output", tmp_path, "--write-test-mb", "1")
    lines = text.stdout.strip().splitlines()
    # its own measurements (a loaded disk may measure slower this time): the exit status follows its verdict
    assert lines[-1].split(":")[0] in ("ok", "warn", "fail") and text.returncode == (1 if lines[-1].startswith("fail") else 0)
    assert sum(1 for line in lines[:-1] if line[:6] in ("ok    ", "warn  ", "FAIL  ")) == len(doc["checks"])
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".rig-disk-write-test")] == []


def test_bad_input_is_one_line_and_exit_2(tmp_path):
    cfg = sim_config(tmp_path)
    assert_one_line_error(run_rig("doctor", "-c", tmp_path / "nope.toml"), "no such config file")
    assert_one_line_error(run_rig("doctor", "-c", cfg, "--minutes", "0"), "--minutes")
    (tmp_path / "bench.json").write_text('{"ort_ms": {}}')
    assert_one_line_error(run_rig("doctor", "-c", cfg, "--bench", tmp_path / "bench.json"), "not `rig model bench --json` output")
    notes = tmp_path / "notes.txt"
    notes.write_text("mine\n")
    assert_one_line_error(run_rig("doctor", "-c", cfg, "--fix-script", notes), "not a fix script")
    assert notes.read_text() == "mine\n"  # never overwritten
    (tmp_path / "file").write_text("")
    assert_one_line_error(run_rig("doctor", "-c", cfg, "--output", tmp_path / "file"), "is a file")


def test_inputs_that_are_devices_pipes_or_under_a_file_are_one_line_and_exit_2(tmp_path):
    """An existing --fix-script is read to tell an earlier fix script from another file: a device that
    never ends (/dev/zero: the whole of it was read into memory until the process was killed) or a pipe
    (its open blocks) is refused unread; --bench reads a bounded amount; a take folder under a file
    cannot be made (it was a failed write-rate check, exit 1)."""
    import os

    cfg = sim_config(tmp_path)
    assert_one_line_error(run_rig("doctor", "-c", cfg, "--fix-script", "/dev/zero", timeout=60), "not a regular file")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert_one_line_error(run_rig("doctor", "-c", cfg, "--fix-script", fifo, timeout=60), "not a regular file")
    assert_one_line_error(run_rig("doctor", "-c", cfg, "--bench", "/dev/zero", timeout=60), "not `rig model bench --json` output")
    (tmp_path / "file").write_text("")
    assert_one_line_error(run_rig("doctor", "-c", cfg, "--output", tmp_path / "file" / "takes"), "file is a file, not a folder")


def test_sigterm_during_the_write_test_removes_its_file(tmp_path):
    """`kill` (a time limit, a service manager) during the write test: the test file goes, as with
    Ctrl-C; before, up to 256 MB stayed hidden in the take folder."""
    import os
    import signal
    import sys
    import time

    cfg = sim_config(tmp_path)
    out = tmp_path / "takes"
    out.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "rig", "doctor", "-c", str(cfg), "--output", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while not any(out.iterdir()) and proc.poll() is None and time.monotonic() - t0 < 60:
            time.sleep(0.001)
        assert any(out.iterdir()), "the write test was not seen"
        os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130 and "Traceback" not in err
    assert list(out.iterdir()) == []


def test_a_disk_that_fails_the_write_test_is_a_failed_check_not_a_crash(tmp_path):
    """A write error during the test (here EFBIG from a file size limit; on a venue's disk EIO or a
    quota) is what the doctor is there to find: a failed check in the report, which goes on. Before,
    the doctor stopped with `rig: error: ... cannot measure the disk's write rate` and no report."""
    import resource
    import sys

    cfg = sim_config(tmp_path)
    out = tmp_path / "takes"
    out.mkdir()

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, 1 << 20))  # writes past 1 MiB fail (EFBIG)

    proc = subprocess.run([sys.executable, "-m", "rig", "doctor", "-c", str(cfg), "--output", str(out), "--json"],
                          capture_output=True, text=True, timeout=120, preexec_fn=small_files)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    doc = json.loads(proc.stdout)
    rate = next(c for c in doc["checks"] if c["name"].startswith("write rate"))
    assert rate["status"] == "fail" and "File too large" in rate["measured"]
    assert {c["area"] for c in doc["checks"]} == set(AREAS)  # the other areas were checked too
    assert list(out.iterdir()) == []


def test_a_leftover_test_file_or_folder_does_not_stop_the_write_test(tmp_path):
    """The write test's file has a name of its own: a leftover of that name (here a folder, the
    worst case) no longer stops `rig doctor` and `rig record` with 'Is a directory'."""
    cfg = sim_config(tmp_path)
    out = tmp_path / "takes"
    (out / ".rig-disk-write-test.tmp").mkdir(parents=True)
    proc = run_rig("doctor", "-c", cfg, "--output", out, "--json", "--write-test-mb", "8")
    rate = next(c for c in json.loads(proc.stdout)["checks"] if c["name"].startswith("write rate"))
    assert "8.0 MiB in" in rate["measured"], proc.stderr
    assert sorted(p.name for p in out.iterdir()) == [".rig-disk-write-test.tmp"]
