"""Clock model accuracy: board-to-host mapping error against the emulator's truth.

The emulated trigger board runs on a pty with a drifting clock and random reply delays; the host
driver keeps its clock model from time queries as in a real run; every pulse's board time is mapped
to host time with the model as it stood when the pulse report arrived, and compared with the
emulator's truth.

    .venv/bin/python benchmarks/sync_clock_model.py --seconds 30 --jitter-us 200 --drift-ppm 100
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from simulator.trigger_board import TriggerBoardEmulator  # noqa: E402
from sync.board import TriggerBoard  # noqa: E402


def measure(seconds: float, jitter_us: float, drift_ppm: float, rate_hz: float = 30.0, transport: str = "pty",
            warm_up_s: float = 3.0, seed: int = 0) -> dict:
    emu = TriggerBoardEmulator({"reply_jitter_us": jitter_us, "drift_ppm": drift_ppm, "transport": transport,
                                "clock_offset_us": 1_000_000_000, "seed": seed}).open()
    board = TriggerBoard(emu.url)
    errors_us: list[float] = []

    def on_pulse(p):
        errors_us.append((board.clock.board_to_host_ns(p.board_us) - emu.truth_host_ns(p.board_us)) / 1000.0)

    try:
        board.connect()
        board.subscribe(on_pulse=on_pulse)
        board.set_rate(rate_hz, 100)
        board.warm_up(warm_up_s)
        count = int(round(seconds * rate_hz))
        board.start(count)
        board.wait_done(seconds + 10)
        time.sleep(0.1)
        stats = board.clock.stats()
    finally:
        board.close()
        emu.close()
    err = np.abs(np.array(errors_us))
    return {
        "pulses": len(errors_us),
        "reply_jitter_us": jitter_us,
        "drift_ppm_true": drift_ppm,
        "drift_ppm_estimated": stats["drift_ppm"],
        "error_us": {"p50": float(np.percentile(err, 50)), "p99": float(np.percentile(err, 99)), "max": float(err.max())},
        "rtt_us": {"min": stats["rtt_us_min"], "p50": stats["rtt_us_p50"]},
        "rejected_slow": stats["rejected_slow"],
        "time_queries": stats["samples"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--jitter-us", type=float, default=200.0)
    ap.add_argument("--drift-ppm", type=float, default=100.0)
    ap.add_argument("--transport", choices=("pty", "socket"), default="pty")
    ap.add_argument("--warm-up", type=float, default=3.0)
    args = ap.parse_args()
    result = measure(args.seconds, args.jitter_us, args.drift_ppm, transport=args.transport, warm_up_s=args.warm_up)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
