"""Start-up of `rig record` on the simulated rig that `rig config init --sim` writes: the time from
launching the command to its first recorded set, cold (empty loop cache: the simulated cameras
render their loop) and warm (the same config again: the loop comes from the cache).

The first set's time is the host timestamp in the take's index (CLOCK_MONOTONIC, as `time.monotonic_ns`
in this process) minus the moment this script launched the command, so it includes Python's start,
imports, opening the cameras and the trigger board, and the board clock's warm-up.

    .venv/bin/python benchmarks/record_start_up.py [--warm-runs 3] [--cameras 2] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RIG = [sys.executable, "-m", "rig"]


def first_set_s(config: Path, out: Path, env: dict) -> tuple[float, float]:
    """(seconds to the first set, seconds for the whole command)."""
    start = time.monotonic_ns()
    proc = subprocess.run(RIG + ["record", "-c", str(config), "-o", str(out), "--sets", "1", "--json"],
                          env=env, capture_output=True, text=True, cwd=REPO)
    end = time.monotonic_ns()
    if proc.returncode != 0:
        raise SystemExit(f"rig record failed ({proc.returncode}): {proc.stderr.strip()}")
    with open(out / "index.jsonl") as f:
        first = json.loads(f.readline())
    return (first["host_ts_ns"] - start) / 1e9, (end - start) / 1e9


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--warm-runs", type=int, default=3)
    ap.add_argument("--cameras", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="rig-start-up-") as tmp:
        tmp = Path(tmp)
        env = dict(os.environ, RIG_CACHE_DIR=str(tmp / "cache"), PYTHONPATH=str(REPO))
        config = tmp / "sim.toml"
        subprocess.run(RIG + ["config", "init", "--sim", str(config), "--cameras", str(args.cameras)],
                       env=env, check=True, capture_output=True, cwd=REPO)
        cold = first_set_s(config, tmp / "take-cold", env)
        warm = [first_set_s(config, tmp / f"take-warm-{i}", env) for i in range(args.warm_runs)]
    result = {
        "cameras": args.cameras,
        "cold_first_set_s": round(cold[0], 3), "cold_command_s": round(cold[1], 3),
        "warm_first_set_s": [round(w[0], 3) for w in warm],
        "warm_first_set_median_s": round(statistics.median(w[0] for w in warm), 3),
        "warm_command_s": [round(w[1], 3) for w in warm],
    }
    if args.json:
        print(json.dumps(result))
    else:
        print(f"cold start: first set after {result['cold_first_set_s']:.2f} s (command {result['cold_command_s']:.2f} s)")
        print(f"warm start: first set after {', '.join(f'{w:.2f}' for w in result['warm_first_set_s'])} s "
              f"(median {result['warm_first_set_median_s']:.2f} s; commands {', '.join(f'{w:.2f}' for w in result['warm_command_s'])} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
