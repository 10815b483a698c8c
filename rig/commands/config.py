"""`rig config init|check`: write a working rig configuration, validate one."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rig.errors import ConfigError


def register(sub) -> None:
    p = sub.add_parser("config", help="write or check a rig configuration (TOML)")
    s = p.add_subparsers(dest="config_command", metavar="ACTION")
    s.required = True

    init = s.add_parser("init", help="write a working rig configuration")
    init.add_argument("file", type=Path, help="TOML file to write")
    init.add_argument("--sim", action="store_true", required=True, help="a rig of simulated cameras (sim://)")
    init.add_argument("--cameras", type=int, default=2, help="number of cameras: 2 (the stereo pair) or more, adding supervision cameras (default 2)")
    init.add_argument("--width", type=int, default=640)
    init.add_argument("--height", type=int, default=360)
    init.add_argument("--fps", type=float, default=30.0)
    init.add_argument("--force", action="store_true", help="overwrite an existing file")
    init.set_defaults(func=cmd_init)

    check = s.add_parser("check", help="validate a rig configuration; one line per problem, exit 2 when invalid")
    check.add_argument("file", type=Path)
    check.add_argument("--json", action="store_true",
                       help='print one JSON object: {"ok": true, "config": {...}} or {"ok": false, "problems": [one line each]}')
    check.set_defaults(func=cmd_check)


def cmd_init(args: argparse.Namespace) -> int:
    from common.files import atomic_write_bytes
    from rig.sim.rig_config import SIM_RIG_BOARD, board_toml, sim_rig_config
    from rig.commands._paths import output_file
    from rig.config import dump_config, parse_config
    from rig.errors import StorageError

    if args.file.exists() and not args.file.is_dir() and not args.force:
        raise ConfigError(f"{args.file}: already exists (use --force to overwrite)")
    output_file(args.file)  # a folder, or a folder we cannot write in: one line, before anything
    if args.cameras < 2:
        raise ConfigError(f"--cameras: a rig needs at least the left and right cameras (2), got {args.cameras}")
    data = sim_rig_config(n_cameras=args.cameras, width=args.width, height=args.height, fps=args.fps)
    try:
        cfg = parse_config(data)  # the file we write must pass our own check (and --width etc. are user input)
    except ConfigError as exc:
        raise ConfigError(f"{'; '.join(exc.problems)} (from the command line options)") from None
    try:
        atomic_write_bytes(args.file, dump_config(cfg).encode(), make_parents=True)
    except OSError as exc:
        raise StorageError(f"{args.file}: could not write the config ({exc.strerror or exc})") from None
    print(f"wrote {args.file}: simulated rig with {len(cfg.cameras)} cameras ({', '.join(c.name for c in cfg.cameras)})")
    # a newcomer has no board file yet: write the one that suits the simulated rig, never replacing one
    board = args.file.parent / "board.toml"
    if not board.exists():
        try:
            atomic_write_bytes(board, board_toml(SIM_RIG_BOARD).encode())
            print(f"wrote {board}: the A0 ChArUco board the simulated cameras show (print one with `rig calibrate board`)")
        except OSError as exc:
            print(f"rig: note: could not write {board} ({exc.strerror or exc})", file=sys.stderr)
    views = args.file.parent / "views"
    print(f"next: rig calibrate capture -c {args.file} --board {board} -o {views}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from rig.commands._output import emit_json
    from rig.config import load_config

    try:
        cfg = load_config(args.file)
    except ConfigError as exc:  # every problem, one line each (other commands print the first)
        if args.json:
            emit_json({"ok": False, "problems": exc.problems})
        for line in exc.problems:
            print(f"rig: error: {line}", file=sys.stderr)
        return exc.exit_code
    if args.json:
        d = asdict(cfg)
        d["path"] = str(cfg.path)
        emit_json({"ok": True, "config": d})
    else:
        roles = ", ".join(f"{c.name} ({c.role}, {c.uri})" for c in cfg.cameras)
        trig = f"; trigger board {cfg.trigger.uri} at {cfg.trigger.rate_hz:g} Hz" if cfg.trigger else ""
        print(f"{args.file}: ok: rig '{cfg.name}', {len(cfg.cameras)} cameras: {roles}{trig}")
    return 0
