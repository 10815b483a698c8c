"""`rig sync check` on the acceptance sim rig: two hardware-triggered sim cameras, 2% frame drops,
50 us trigger-latency jitter, 100 ppm clock drift (board and cameras), 200 us reply jitter on the
board's link; 60 s at 30 Hz by default. Prints the report (one JSON object).

    .venv/bin/python benchmarks/sync_check_sim.py --seconds 60
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rig.capture.sync_check import sync_check  # noqa: E402
from rig.config import parse_config  # noqa: E402


def acceptance_rig(rate_hz: float = 30.0) -> dict:
    cams = []
    for i, (name, drift) in enumerate((("left", 100.0), ("right", -100.0))):
        cams.append({"name": name, "uri": f"sim://{name}", "role": name, "width": 64, "height": 48, "fps": rate_hz,
                     "trigger": "hardware", "exposure_us": 5000.0,
                     "sim": {"drop_rate": 0.02, "jitter_us": 50.0, "drift_ppm": drift, "clock_offset_ns": 10**12 * (i + 1), "seed": 11 + i}})
    return {"rig": {"name": "sync-acceptance"}, "sim": {"loop_frames": 30, "people": 1}, "cameras": cams,
            "trigger": {"uri": "sim://trigger", "rate_hz": rate_hz, "sim": {"drift_ppm": 100.0, "reply_jitter_us": 200.0, "seed": 3}}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    args = ap.parse_args()
    report = sync_check(parse_config(acceptance_rig()), args.seconds)
    keys = ("pulses", "frames", "complete_sets", "mismatched_sets", "drops_detected", "skew_us", "clock_residual_us", "drift_ppm", "truth", "seconds")
    print(json.dumps({k: report[k] for k in keys}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
