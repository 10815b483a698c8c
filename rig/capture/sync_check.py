"""`rig sync check`: run the rig with its trigger board and measure how well its frames are synced.

On a sim rig every figure is also checked against the simulator's truth: which pulse each frame
really answered (mismatched sets, undetected and false drops) and the emulated board's real clock
(the board-to-host mapping error). On real hardware the same run reports what can be observed.
"""
from __future__ import annotations

import time
from typing import Callable, Optional

import numpy as np

from rig.config import RigConfig
from rig.errors import ConfigError


def _p(values, q) -> Optional[float]:
    return float(np.percentile(values, q)) if len(values) else None


def sync_check(cfg: RigConfig, seconds: float, progress: Optional[Callable[[str], None]] = None,
               session_options: Optional[dict] = None) -> dict:
    from rig.capture.session import RigSession

    if not seconds > 0:
        raise ConfigError(f"--seconds must be positive, got {seconds}")
    truth_cams = {c.name for c in cfg.cameras if c.scheme == "sim"}
    mismatched = 0
    misassigned = 0
    detected: dict[str, set] = {c.name: set() for c in cfg.cameras}
    exposed: dict[str, set] = {c.name: set() for c in cfg.cameras}
    sets = 0
    t0 = time.monotonic()
    with RigSession(cfg, **(session_options or {})) as session:
        rate = cfg.trigger.rate_hz if cfg.trigger else cfg.camera(session.grouper.reference).fps
        pulses_wanted = max(1, int(round(seconds * rate)))
        session.start(pulses_wanted if session.board is not None else 0)
        started = time.monotonic()
        for fs in session.framesets():
            sets += 1
            bad = False
            for name, frame in fs.frames.items():
                if frame is None:
                    detected[name].add((fs.train, fs.trigger_index))
                    continue
                if name in truth_cams and hasattr(session.cameras[name], "truth_pulse"):
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
            elapsed = time.monotonic() - started
            if session.board is None and elapsed >= seconds:
                session.stop()
            elif session.board is not None and (session.train_done.is_set() or elapsed >= seconds + 10.0):
                session.stop()
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
            truth_host = {(p.train - 1, p.index): p.host_ns for p in session.emulator.pulses}
            errors_us = [abs(h - truth_host[(e, i)]) / 1000.0 for e, i, h in session.grouper.mapped_pulses if (e, i) in truth_host]
            report["clock_residual_us"] = _p(errors_us, 99)
            report["clock_residual_source"] = "emulator truth"
            fired = {(p.train - 1, p.index) for p in session.emulator.pulses}
            truth = {"misassigned_frames": misassigned, "drops_injected": {}, "undetected_drops": {}, "false_drops": {},
                     "drift_ppm": float(session.emulator.options["drift_ppm"]),
                     "clock_error_us": {"p50": _p(errors_us, 50), "p99": _p(errors_us, 99), "max": max(errors_us) if errors_us else None}}
            for name in truth_cams:
                injected = fired - exposed[name]
                truth["drops_injected"][name] = len(injected)
                truth["undetected_drops"][name] = len(injected - detected[name])
                truth["false_drops"][name] = len(detected[name] - injected)
            report["truth"] = truth
    return report


def _fired_pulses(session):
    if session.emulator is not None:
        return iter(session.emulator.pulses)
    return iter(range(session.grouper.emitted))
