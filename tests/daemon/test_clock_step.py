"""The wall clock steps mid-take, as NTP steps it after a long drift: +2 s in the daemons of `rig up`,
then -2 s in `rig record`; the monotonic clocks are left alone, as a step leaves them. Ordering,
timeouts and heartbeats run on the monotonic clock: no set is reordered or mispaired, no daemon is
taken for hung, the take validates.

The step is a small preload library built here with the C compiler: it moves CLOCK_REALTIME (and
gettimeofday, time) by the seconds written in a file, read at every call. Debian's libfaketime
cannot do this: with its monotonic clock left alone (FAKETIME_DONT_FAKE_MONOTONIC=1), 0.9.10 makes
Python's time.sleep fail with EINVAL (its clock_nanosleep on the monotonic clock).
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rig.storage.layout import INDEX
from rig.storage.validate import validate
from tests.daemon.test_daemon import Up, communicate, rig_file, wait_running
from tests.rig.cli_helpers import REPO

CC = shutil.which("cc")
pytestmark = [pytest.mark.skipif(CC is None, reason="no C compiler (cc) to build the wall-clock step library"), pytest.mark.timeout(240)]

WALLSTEP_C = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/time.h>
#include <time.h>

static long long step_ns(void) {
    const char *path = getenv("WALLSTEP_FILE");
    double s = 0.0;
    FILE *f = path ? fopen(path, "r") : NULL;
    if (f) { if (fscanf(f, "%lf", &s) != 1) s = 0.0; fclose(f); }
    return (long long)(s * 1e9);
}

int clock_gettime(clockid_t id, struct timespec *ts) {
    static int (*real)(clockid_t, struct timespec *) = NULL;
    if (!real) real = (int (*)(clockid_t, struct timespec *))dlsym(RTLD_NEXT, "clock_gettime");
    int r = real(id, ts);
    if (r == 0 && (id == CLOCK_REALTIME || id == CLOCK_REALTIME_COARSE)) {
        long long ns = (long long)ts->tv_sec * 1000000000LL + ts->tv_nsec + step_ns();
        ts->tv_sec = ns / 1000000000LL;
        ts->tv_nsec = ns % 1000000000LL;
    }
    return r;
}

int gettimeofday(struct timeval *tv, void *tz) {
    struct timespec ts;
    (void)tz;
    if (clock_gettime(CLOCK_REALTIME, &ts) != 0) return -1;
    tv->tv_sec = ts.tv_sec;
    tv->tv_usec = ts.tv_nsec / 1000;
    return 0;
}

time_t time(time_t *t) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    if (t) *t = ts.tv_sec;
    return ts.tv_sec;
}
"""


@pytest.fixture(scope="module")
def wallstep(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("wallstep")
    (folder / "wallstep.c").write_text(WALLSTEP_C)
    lib = folder / "libwallstep.so"
    subprocess.run([CC, "-shared", "-fPIC", "-O2", "-o", str(lib), str(folder / "wallstep.c"), "-ldl"], check=True)
    return lib


def faked(lib: Path, offset_file: Path) -> dict:
    offset_file.write_text("0\n")
    return {"LD_PRELOAD": str(lib), "WALLSTEP_FILE": str(offset_file)}


def test_a_wall_clock_step_of_plus_and_minus_2_s_mid_take_reorders_and_mispairs_nothing(tmp_path, wallstep):
    config = rig_file(tmp_path, n=3)
    daemons_clock, recorder_clock = tmp_path / "daemons.step", tmp_path / "recorder.step"
    up = Up(config, tmp_path / "shm", env=faked(wallstep, daemons_clock))
    take = tmp_path / "take"
    try:
        wait_running(up.root, "sim-3cam", 3)
        env = dict(up.env, **faked(wallstep, recorder_clock))
        rec = subprocess.Popen([sys.executable, "-m", "rig", "record", "-c", str(config), "-o", str(take), "--seconds", "6", "--json"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
        deadline = time.monotonic() + 60
        while not (take / INDEX).exists() or (take / INDEX).stat().st_size < 2000:
            assert rec.poll() is None and time.monotonic() < deadline, rec.communicate()
            time.sleep(0.05)
        # the step is live: a process started now with the daemons' environment reads the stepped wall clock
        probe = [sys.executable, "-c", "import time; print(time.time())"]
        time.sleep(1.0)
        daemons_clock.write_text("2\n")  # the daemons' wall clock jumps 2 s ahead
        stepped = float(subprocess.run(probe, capture_output=True, text=True, env=dict(up.env)).stdout) - time.time()
        assert 1.5 < stepped < 2.5, stepped
        time.sleep(1.5)
        recorder_clock.write_text("-2\n")  # the recorder's 2 s back
        out, err = communicate(rec, 120)
    finally:
        stopped = up.stop()
    print(stopped)
    assert rec.returncode == 0, err
    summary = json.loads(out)
    assert json.loads(stopped.strip().splitlines()[-1])["restarts"] == {"left": 0, "sup1": 0, "right": 0, "@board": 0}
    assert summary["frames_lost"] == {"left": 0, "sup1": 0, "right": 0} and summary["errors"] == []
    v = validate(take)
    assert v.readable and v.errors == [] and v.gaps == 0
    rows = [json.loads(line) for line in (take / INDEX).read_text().splitlines() if line.endswith("}")]
    assert [r["trigger"] for r in rows] == sorted(r["trigger"] for r in rows)  # in pulse order
    mispaired = [r["set"] for r in rows if len({round(f["sim_time_s"], 4) for f in r["frames"].values() if f}) > 1]
    assert mispaired == []
    assert v.complete_sets >= 150  # 6 s at 30 Hz, nothing dropped around the steps
