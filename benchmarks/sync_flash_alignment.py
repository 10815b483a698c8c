"""Offline flash alignment accuracy on simulator video.

Each trial films the trigger board's LED (simulator.led.FlashLed, a light in the scene) with the
sensor model of one camera of the virtual rig, at a random frame phase and flash time, and finds the
flash onset in the frames (sync.alignment). Errors are in frame periods, against the true onset.
Frames are generated at their scheduled times directly through the sensor model (the sim:// camera
backend does the same in real time; tests/sync/test_sync_alignment.py runs that path).

    .venv/bin/python benchmarks/sync_flash_alignment.py --trials 40
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from simulator.led import FlashLed  # noqa: E402
from simulator.rig import virtual_rig  # noqa: E402
from simulator.scene import Scene  # noqa: E402
from simulator.sensor import SensorModel  # noqa: E402
from sync.alignment import brightness_trace, find_flash  # noqa: E402


def trials(n: int, fps: float, exposure_s: float, duration_known: bool, seed: int = 0) -> dict:
    rig = virtual_rig(2, 96, 54)
    scene = Scene(seed=1, people=1, name="studio")
    rng = np.random.default_rng(seed)
    period = 1.0 / fps
    errors, flagged = [], []
    for i in range(n):
        cam = rig.cameras[i % 2]
        led = FlashLed((0.0, 2.3, -1.5), radius_m=0.1)
        onset = 1.0 + rng.uniform(0, period)
        duration = 0.15
        led.set(True, onset)
        led.set(False, onset + duration)
        sensor = SensorModel(scene, cam, {"seed": i}, gain_db=-18.0)
        source = led.image_source(sensor)
        times = 0.5 + rng.uniform(0, period) + np.arange(40) * period
        images = [source(t, exposure_s, rng) for t in times]
        est = find_flash(times * 1e9, brightness_trace(images), exposure_s * 1e9, duration_ns=duration * 1e9 if duration_known else None)
        err = (est.onset_ns / 1e9 - onset) / period
        errors.append(abs(err))
        flagged.append(abs(err) <= est.uncertainty_ns / 1e9 / period + 0.02)
    e = np.array(errors)
    return {"exposure_ms": round(exposure_s * 1e3, 1), "duration_known": duration_known, "trials": n,
            "error_periods": {"p50": round(float(np.median(e)), 4), "p90": round(float(np.percentile(e, 90)), 4), "max": round(float(e.max()), 4)},
            "within_0.1_period": round(float((e < 0.1).mean()), 3),
            "error_within_reported_uncertainty": round(float(np.mean(flagged)), 3)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=40)
    ap.add_argument("--fps", type=float, default=30.0)
    args = ap.parse_args()
    rows = []
    for exposure in (1.0 / args.fps, 0.030, 0.020, 0.010):
        for known in (True, False):
            rows.append(trials(args.trials, args.fps, exposure, known))
            print(json.dumps(rows[-1]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
