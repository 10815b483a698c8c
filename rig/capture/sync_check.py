"""`rig sync check`: run the rig with its trigger board and measure how well its frames are synced.

On a sim rig every figure is also checked against the simulator's truth: which pulse each frame
really answered (mismatched sets, undetected and false drops) and the emulated board's real clock
(the board-to-host mapping error). On real hardware the same run reports what can be observed.

The report ends with a verdict against stated limits (`LIMITS`, each can be changed on the command
line). Its skew is *exposure* skew: per set, the spread across cameras of when each exposure started
relative to the trigger pulse (a hardware-triggered camera's frame time on its own clock against the
fitted pulse time, so it is trigger-latency jitter; a constant per-camera latency is absorbed by the
fit), which is what matters for the pictures. `rig record validate` reports *arrival* skew: the spread
of the host times at which a set's frames reached the computer, which adds transfer, driver and
scheduling delays and is normally far larger; it says nothing about when the pictures were taken.
"""
from __future__ import annotations

import time
from typing import Callable, Optional

import numpy as np

from rig.config import RigConfig
from rig.errors import ConfigError


# Default limits of the verdict. Exposure skew well under a millisecond is what a hardware trigger
# gives (real triggered cameras jitter by microseconds); the clock mapping must place every pulse far
# within half a frame period; drops are the camera link's, but a check that loses 1 in 20 is not good.
LIMITS = {"skew_p99_us": 1000.0, "clock_residual_p99_us": 1000.0, "drop_rate": 0.05, "mismatched_sets": 0, "errors": 0}


def judge(report: dict, limits: Optional[dict] = None) -> tuple[str, list[str]]:
    """("pass" | "fail", one line per limit the run broke)."""
    lim = dict(LIMITS, **(limits or {}))
    failures = []
    if not report["sets"]:
        failures.append("no frame sets were made")
    p99 = (report.get("skew_us") or {}).get("p99")
    if p99 is not None and p99 > lim["skew_p99_us"]:
        failures.append(f"exposure skew p99 {p99:.1f} us > {lim['skew_p99_us']:g} us")
    clock = report.get("clock_residual_us")
    if clock is not None and clock > lim["clock_residual_p99_us"]:
        failures.append(f"board-to-host clock error p99 {clock:.1f} us > {lim['clock_residual_p99_us']:g} us")
    wanted = report.get("pulses") or report["sets"]
    for name, drops in report["drops_detected"].items():
        rate = drops / wanted if wanted else 0.0
        if rate > lim["drop_rate"]:
            failures.append(f"{name}: {drops} of {wanted} frames missing ({rate:.1%}) > {lim['drop_rate']:.1%}")
    mismatched = report.get("mismatched_sets")
    if mismatched is not None and mismatched > lim["mismatched_sets"]:
        failures.append(f"{mismatched} sets hold a frame of another pulse (simulator truth) > {lim['mismatched_sets']}")
    if len(report["errors"]) > lim["errors"]:
        failures.append(f"{len(report['errors'])} errors during the run")
    return ("fail" if failures else "pass"), failures


def _p(values, q) -> Optional[float]:
    return float(np.percentile(values, q)) if len(values) else None


def sync_check(cfg: RigConfig, seconds: float, progress: Optional[Callable[[str], None]] = None,
               session_options: Optional[dict] = None, limits: Optional[dict] = None, tap=None) -> dict:
    """`tap`: an onlooker (rig.capture.tap: the console's previews), told of the session and of each set."""
    from rig.capture.session import RigSession
    from rig.capture.tap import guard, tapped

    tap = guard(tap)

    if not seconds > 0 or seconds == float("inf"):
        raise ConfigError(f"--seconds must be positive, got {seconds}")
    limits = dict(LIMITS, **(limits or {}))
    for key, value in limits.items():
        if not value >= 0:
            raise ConfigError(f"limit {key} must be >= 0, got {value}")
    mismatched = 0
    misassigned = 0
    detected: dict[str, set] = {c.name: set() for c in cfg.cameras}
    exposed: dict[str, set] = {c.name: set() for c in cfg.cameras}
    sets = 0
    t0 = time.monotonic()
    with RigSession(cfg, **(session_options or {})) as session, tapped(tap, session):
        # cameras that know which pulse each of their frames truly exposed (simulated ones do)
        truth_cams = {name for name, cam in session.cameras.items() if hasattr(cam, "truth_pulse")}
        rate = cfg.trigger.rate_hz if cfg.trigger else cfg.camera(session.grouper.reference).fps
        pulses_wanted = max(1, int(round(seconds * rate)))
        session.start(pulses_wanted if session.board is not None else 0)
        started = time.monotonic()

        def over() -> bool:
            # Asked also while no set arrives: the board's DONE can come after the last set.
            elapsed = time.monotonic() - started
            if session.board is None:
                return elapsed >= seconds
            return session.train_done.is_set() or elapsed >= seconds + 10.0

        for fs in session.framesets(until=over):
            sets += 1
            if tap is not None:  # before the images are let go below
                tap.frame_set(fs, {"sets": sets, "pulses": fs.index + 1, "seconds": round(time.monotonic() - started, 2)})
            bad = False
            for name, frame in fs.frames.items():
                if frame is None:
                    detected[name].add((fs.train, fs.trigger_index))
                    continue
                if name in truth_cams:
                    true_pulse = session.cameras[name].truth_pulse.get(frame.frame_id)
                    if true_pulse is not None:
                        exposed[name].add((fs.train, true_pulse))
                    if session.board is not None and true_pulse != frame.trigger_index:
                        misassigned += 1
                        bad = True
                frame.image = None  # keep the metadata only: a long check must not hold every image
            mismatched += bad
            if progress is not None:
                progress(f"{time.monotonic() - started:6.1f} s  {sets} sets  {fs.index + 1} pulses")
        stats = session.grouper.stats()
        link = session.board.report() if session.board is not None else None
        report = {
            "pulses": None,
            "frames": dict(session.frames_delivered),
            "sets": stats["sets"],
            "complete_sets": stats["complete_sets"],
            "mismatched_sets": mismatched if session.board is not None and truth_cams else None,
            "drops_detected": {n: c["drops"] for n, c in stats["cameras"].items()},
            "skew_us": stats["skew_us"],
            "clock_residual_us": None,
            "drift_ppm": session.board.clock.drift_ppm if session.board is not None else None,
            "seconds": round(time.monotonic() - t0, 3),
            "cameras": stats["cameras"],
            "errors": session.errors(),
        }
        if session.board is not None:
            report["pulses"] = int(sum(1 for _ in _fired_pulses(session)))
            report["board"] = link
            report["clock_residual_source"] = "fit"
            report["clock_residual_us"] = link["clock"]["fit_residual_p99_us"]
        else:
            report["pulses"] = stats["sets"]
        if session.emulator is not None:
            truth = _emulator_truth(session, truth_cams, misassigned, exposed, detected)
            report["clock_residual_us"] = truth["clock_error_us"]["p99"]
            report["clock_residual_source"] = "emulator truth"
            report["truth"] = truth
    report["limits"] = limits
    report["verdict"], report["failures"] = judge(report, limits)
    return report


def _emulator_truth(session, truth_cams: set[str], misassigned: int, exposed: dict[str, set], detected: dict[str, set]) -> dict:
    """What the emulated board and the sim cameras know: the clock model's error against each
    pulse's true host time, the drops injected (pulses fired that a camera did not expose), those
    the grouper missed and those it saw where there was none. Pulses as (train, index)."""
    truth_host = {(p.train - 1, p.index): p.host_ns for p in session.emulator.pulses}
    errors_us = [abs(h - truth_host[(e, i)]) / 1000.0 for e, i, h in session.grouper.mapped_pulses if (e, i) in truth_host]
    fired = {(p.train - 1, p.index) for p in session.emulator.pulses}
    truth = {"misassigned_frames": misassigned, "drops_injected": {}, "undetected_drops": {}, "false_drops": {},
             "drift_ppm": float(session.emulator.options["drift_ppm"]),
             "clock_error_us": {"p50": _p(errors_us, 50), "p99": _p(errors_us, 99), "max": max(errors_us) if errors_us else None}}
    for name in truth_cams:
        injected = fired - exposed[name]
        truth["drops_injected"][name] = len(injected)
        truth["undetected_drops"][name] = len(injected - detected[name])
        truth["false_drops"][name] = len(detected[name] - injected)
    return truth


def _fired_pulses(session):
    if session.emulator is not None:
        return iter(session.emulator.pulses)
    return iter(range(session.grouper.emitted))
