"""`rig service install`: the rig's daemons as systemd services on a venue box (rig/daemon/service.py)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub) -> None:
    s = sub.add_parser("service", help="run the rig's daemons as systemd services (units, target, udev rules)",
                       description="systemd units for the rig's daemons: a rig-camera@.service template (one instance per "
                                   "camera), rig-board.service for a trigger board, rig.target wanting them all, and udev "
                                   "rules for stable device names (docs/services.md).")
    ss = s.add_subparsers(dest="service_command", metavar="SUBCOMMAND")
    ss.required = True
    i = ss.add_parser("install", help="write the unit files, the target and the udev rules",
                      description="Writes rig-camera@.service, rig.target (and rig-board.service when the rig has a trigger "
                                  "board) into /etc/systemd/system and 99-rig.rules into /etc/udev/rules.d (needs root), "
                                  "or under DIR with --dry-run. Reloads systemd and udev when systemd runs; prints the "
                                  "commands that start the rig.")
    i.add_argument("-c", "--config", type=Path, required=True, help="rig configuration (TOML); the units name its absolute path")
    i.add_argument("--dry-run", type=Path, metavar="DIR", help="write the files under DIR (DIR/etc/systemd/system/..., "
                                                               "DIR/etc/udev/rules.d/...) and install nothing")
    i.add_argument("--watchdog", type=float, default=5.0, metavar="S",
                   help="WatchdogSec: seconds without a WATCHDOG=1 before systemd restarts a daemon (default 5)")
    i.add_argument("--user", help="run the daemons as this user (default root); it joins the device groups")
    i.add_argument("--group", help="run the daemons with this group (default: the user's)")
    i.add_argument("--json", action="store_true", help="print one JSON object")
    i.set_defaults(func=cmd_install)


def cmd_install(args: argparse.Namespace) -> int:
    from rig.daemon import service

    service.check_watchdog(args.watchdog)  # before the config is read: one line for the first mistake
    written = service.install(args.config, dry_run_dir=args.dry_run, unit_dir=service.UNIT_DIR, udev_dir=service.UDEV_DIR,
                              python=sys.executable, watchdog_s=args.watchdog, user=args.user, group=args.group)
    commands = [] if written.reloaded else ["systemctl daemon-reload", "udevadm control --reload"]
    commands += service.next_commands()
    if args.json:
        from rig.commands._output import emit_json

        emit_json({"files": [str(p) for p in written], "dry_run": args.dry_run is not None, "reloaded": written.reloaded,
                   "notes": written.notes, "next": commands})
        return 0
    for p in written:
        print(f"wrote {p}")
    for note in written.notes:
        print(f"note: {note}")
    print("then:" if args.dry_run is None else "then, on the box:")
    for c in commands:
        print(f"  {c}")
    return 0
