"""`rig sync check`: run the rig with its trigger board and report how well frames are synced."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("sync", help="trigger board and frame synchronisation")
    s = p.add_subparsers(dest="sync_command", metavar="ACTION")
    s.required = True
    check = s.add_parser("check", help="run the rig with its trigger board (on a sim rig, the emulator) and report sync quality")
    check.add_argument("-c", "--config", type=Path, required=True, help="rig configuration (TOML)")
    check.add_argument("--seconds", type=float, default=10.0, help="length of the pulse train (default 10)")
    check.add_argument("--json", action="store_true", help="print the report as one JSON object")
    check.set_defaults(func=cmd_check)


def cmd_check(args: argparse.Namespace) -> int:
    from rig.capture.sync_check import sync_check
    from rig.commands._output import emit_json
    from rig.config import load_config
    from rig.progress import StatusLine

    cfg = load_config(args.config)
    status = StatusLine(sys.stderr)
    report = sync_check(cfg, args.seconds, progress=status.update)
    status.done()
    if args.json:
        emit_json(report)
    else:
        _print(report)
    return 1 if report["mismatched_sets"] else 0


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
    print(f"skew us: p50 {_fmt(sk['p50'])}, p99 {_fmt(sk['p99'])}, max {_fmt(sk['max'])}")
    if r.get("clock_residual_us") is not None or r.get("drift_ppm") is not None:
        print(f"clock: board-to-host error p99 {_fmt(r['clock_residual_us'], ' us')} ({r.get('clock_residual_source')}), "
              f"drift {_fmt(r['drift_ppm'], ' ppm')}")
    truth = r.get("truth")
    if truth:
        print(f"truth: {truth['misassigned_frames']} frames misassigned; drops injected {truth['drops_injected']}, "
              f"undetected {truth['undetected_drops']}, false {truth['false_drops']}; board drift {truth['drift_ppm']} ppm")
    for e in r["errors"]:
        print(f"error: {e}")
