"""`rig discover`: list the devices every backend can see."""
from __future__ import annotations

import argparse
import sys


def register(sub) -> None:
    p = sub.add_parser("discover", help="list cameras of every backend (sim devices always)")
    p.add_argument("--json", action="store_true", help='print one JSON object: {"devices": [{uri, backend, model, serial, ...}], "errors": {backend: why it could not look}}')
    p.set_defaults(func=cmd_discover)


def cmd_discover(args: argparse.Namespace) -> int:
    from rig.cameras import discover_all
    from rig.commands._output import emit_json

    problems: list[str] = []
    devices = discover_all(problems)
    if args.json:  # one object, as every --json prints; a backend that could not look is not fatal
        errors = dict(line.split(": ", 1) if ": " in line else (line, "failed") for line in problems)
        emit_json({"devices": [d.to_dict() for d in devices], "errors": errors})
        return 0
    for line in problems:
        print(f"rig: note: backend {line}", file=sys.stderr)
    if not devices:
        print("no devices found")
    for d in devices:
        label = " ".join(x for x in (d.vendor, d.model) if x)
        print(f"{d.uri:32s} {d.backend:8s} {label} {('serial ' + d.serial) if d.serial else ''}".rstrip())
    return 0
