"""`rig discover`: list the devices every backend can see."""
from __future__ import annotations

import argparse
import sys


def register(sub) -> None:
    p = sub.add_parser("discover", help="list cameras of every backend (sim devices always)")
    p.add_argument("--json", action="store_true", help="print a JSON list of devices (uri, backend, model, serial, ...)")
    p.set_defaults(func=cmd_discover)


def cmd_discover(args: argparse.Namespace) -> int:
    from rig.cameras import discover_all
    from rig.commands._output import emit_json

    problems: list[str] = []
    devices = discover_all(problems)
    for line in problems:
        print(f"rig: note: backend {line}", file=sys.stderr)
    if args.json:
        emit_json([d.to_dict() for d in devices])
        return 0
    if not devices:
        print("no devices found")
    for d in devices:
        label = " ".join(x for x in (d.vendor, d.model) if x)
        print(f"{d.uri:32s} {d.backend:8s} {label} {('serial ' + d.serial) if d.serial else ''}".rstrip())
    return 0
