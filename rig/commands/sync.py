"""`rig sync check`: run the rig with its trigger board and report how well frames are synced."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rig.capture.sync_check import LIMITS


def register(sub) -> None:
    p = sub.add_parser("sync", help="trigger board and frame synchronisation")
    s = p.add_subparsers(dest="sync_command", metavar="ACTION")
    s.required = True
    check = s.add_parser("check", help="run the rig with its trigger board (on a sim rig, the emulator) and report sync quality")
    check.add_argument("-c", "--config", type=Path, required=True, help="rig configuration (TOML)")
    check.add_argument("--seconds", type=float, default=10.0, help="length of the pulse train (default 10)")
    check.add_argument("--max-skew-us", type=float, default=LIMITS["skew_p99_us"],
                       help=f"verdict limit: exposure skew p99 across cameras, us (default {LIMITS['skew_p99_us']:g})")
    check.add_argument("--max-clock-error-us", type=float, default=LIMITS["clock_residual_p99_us"],
                       help=f"verdict limit: board-to-host clock mapping error p99, us (default {LIMITS['clock_residual_p99_us']:g})")
    check.add_argument("--max-drop-rate", type=float, default=LIMITS["drop_rate"],
                       help=f"verdict limit: fraction of pulses a camera may miss (default {LIMITS['drop_rate']:g})")
    check.add_argument("--json", action="store_true",
                       help='print the report as one JSON object (with "verdict": "pass"|"fail", "limits" and "failures")')
    check.set_defaults(func=cmd_check)


def cmd_check(args: argparse.Namespace) -> int:
    from rig.capture.sync_check import sync_check
    from rig.commands._output import emit_json
    from rig.config import load_config
    from rig.errors import ConfigError
    from rig.progress import Notes, StatusLine

    # arguments first, before the config is read and the rig started
    if not (0 < args.seconds < float("inf")):
        raise ConfigError(f"--seconds must be positive, got {args.seconds}")
    for option, value in (("--max-skew-us", args.max_skew_us), ("--max-clock-error-us", args.max_clock_error_us),
                          ("--max-drop-rate", args.max_drop_rate)):
        if not (0 <= value < float("inf")):
            raise ConfigError(f"{option} must be a number >= 0, got {value}")
    limits = {"skew_p99_us": args.max_skew_us, "clock_residual_p99_us": args.max_clock_error_us, "drop_rate": args.max_drop_rate}
    cfg = load_config(args.config)
    status = StatusLine(sys.stderr)
    report = sync_check(cfg, args.seconds, progress=status.update, limits=limits,
                        session_options={"on_phase": Notes(quiet=args.json)})
    status.done()
    if args.json:
        emit_json(report)
    else:
        _print(report)
    return 0 if report["verdict"] == "pass" else 1


def _fmt(v, unit="") -> str:
    return "n/a" if v is None else (f"{v:.1f}{unit}" if isinstance(v, float) else f"{v}{unit}")


def _print(r: dict) -> None:
    print(f"pulses {r['pulses']}, sets {r['sets']}, complete {r['complete_sets']}, mismatched {_fmt(r['mismatched_sets'])}")
    for name, n in r["frames"].items():
        cam = r["cameras"][name]
        print(f"  {name}: {n} frames, {r['drops_detected'][name]} drops detected "
              f"({cam['lost_frames']} lost in transfer, {cam['missed_triggers']} triggers missed), "
              f"{cam['duplicates']} duplicates, {cam['unassigned']} unassigned")
    sk = r["skew_us"]
    print(f"exposure skew us: p50 {_fmt(sk['p50'])}, p99 {_fmt(sk['p99'])}, max {_fmt(sk['max'])}")
    print("  (how far apart the cameras' exposures started in a set, from each camera's own clock against the pulse;\n"
          "   `rig record validate` reports arrival skew instead: when the frames reached this computer, which adds\n"
          "   transfer and driver delays and says nothing about when the pictures were taken)")
    if r.get("clock_residual_us") is not None or r.get("drift_ppm") is not None:
        print(f"clock: board-to-host error p99 {_fmt(r['clock_residual_us'], ' us')} ({r.get('clock_residual_source')}), "
              f"drift {_fmt(r['drift_ppm'], ' ppm')}")
    truth = r.get("truth")
    if truth:
        print(f"truth: {truth['misassigned_frames']} frames misassigned; drops injected {truth['drops_injected']}, "
              f"undetected {truth['undetected_drops']}, false {truth['false_drops']}; board drift {truth['drift_ppm']} ppm")
    for e in r["errors"]:
        print(f"error: {e}")
    lim = r["limits"]
    print(f"limits: exposure skew p99 <= {lim['skew_p99_us']:g} us, clock error p99 <= {lim['clock_residual_p99_us']:g} us, "
          f"missing frames <= {lim['drop_rate']:.1%} per camera, mismatched sets <= {lim['mismatched_sets']}, errors <= {lim['errors']}")
    for f in r["failures"]:
        print(f"  failed: {f}")
    print(f"verdict: {r['verdict'].upper()}")
