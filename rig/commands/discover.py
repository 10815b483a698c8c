"""`rig discover`: list the devices every backend can see; with --network, the camera daemons that
answer on mDNS (rig.cameras.discovery), on this host and others."""
from __future__ import annotations

import argparse
import ipaddress
import math
import sys


def register(sub) -> None:
    p = sub.add_parser(
        "discover", help="list cameras of every backend (sim devices always); --network: camera daemons found by mDNS",
        description="List the cameras every backend can see. With --network, list instead the camera daemons "
                    "(`rig daemon`, `rig up`) that answer on mDNS (_rigcam._tcp), on this host and others: "
                    "only daemons, no local devices.")
    p.add_argument("--json", action="store_true",
                   help='print one JSON object: {"devices": [{uri, backend, model, serial, ...}], "errors": {backend: why it could not look}}; '
                        'with --network: {"daemons": [{rig, camera, role, uri, model, serial, shm, host, port, pid, token_required, api_url}]}')
    p.add_argument("--network", action="store_true",
                   help="list the camera daemons found by mDNS (only them, not the local devices)")
    p.add_argument("--timeout", type=float, metavar="S",
                   help="with --network: wait at most S seconds (default 3; it returns earlier once answers stop coming)")
    p.add_argument("--rig", metavar="NAME", help="with --network: only the daemons of rig NAME")
    p.add_argument("--interface", action="append", metavar="ADDR",
                   help="with --network: look on the interface with this address only (repeatable, e.g. 127.0.0.1)")
    p.set_defaults(func=cmd_discover)


def cmd_discover(args: argparse.Namespace) -> int:
    if args.network:
        return _network(args)
    from rig.errors import ConfigError

    for flag, value in (("--timeout", args.timeout), ("--rig", args.rig), ("--interface", args.interface)):
        if value is not None:
            raise ConfigError(f"{flag} applies to `rig discover --network` only")

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


def _network(args: argparse.Namespace) -> int:
    from rig.commands._output import emit_json
    from rig.cameras.discovery import browse
    from rig.errors import ConfigError

    timeout = 3.0 if args.timeout is None else args.timeout
    if not math.isfinite(timeout) or timeout < 0:
        raise ConfigError(f"--timeout {args.timeout:g}: expected a number of seconds >= 0")
    for addr in args.interface or ():
        try:
            ipaddress.ip_address(addr)
        except ValueError:
            raise ConfigError(f"--interface {addr}: expected an IP address of this host (e.g. 127.0.0.1)") from None
    try:
        daemons = browse(timeout, interfaces=args.interface or None, rig=args.rig)
    except OSError as exc:
        if not args.interface:
            raise
        raise ConfigError(f"--interface {' '.join(args.interface)}: mDNS cannot use it ({exc.strerror or exc}): "
                          "expected an address of one of this host's interfaces") from None
    if args.json:
        emit_json({"daemons": [d.to_dict() for d in daemons]})
        return 0
    if not daemons:
        where = f" of rig {args.rig!r}" if args.rig else ""
        print(f"no daemons{where} answered on mDNS within {timeout:g} s")
    for d in daemons:
        token = "  (token required)" if d.token_required else ""
        print(f"{d.rig}/{d.camera:12s} {d.role:10s} {d.uri:28s} {d.api_url:24s} {d.shm}{token}")
    return 0
