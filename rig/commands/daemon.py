"""`rig daemon CAMERA`, `rig up`, `rig down`: cameras as supervised processes (rig/daemon/)."""
from __future__ import annotations

import argparse
import json
import secrets
import signal
import sys
import threading
from pathlib import Path

from rig.daemon.supervisor import STALE_S


def register(sub) -> None:
    d = sub.add_parser("daemon", help="run one camera of the rig as a daemon (frames in shared memory, a control API)",
                       description="One camera as a process: frames into its shared-memory ring (/dev/shm/rig/RIG/CAMERA, or "
                                   "$RIG_SHM_ROOT), an HTTP control API, mDNS advertisement. Sessions on this host (rig record, "
                                   "rig live, ...) read its frames when it runs. Stops on SIGINT/SIGTERM.")
    d.add_argument("camera", metavar="CAMERA", nargs="?", help="the camera's name in the config")
    d.add_argument("--board", action="store_true", help="own the rig's trigger board instead (sessions drive it through this daemon)")
    d.add_argument("-c", "--config", type=Path, required=True, help="rig configuration (TOML)")
    d.add_argument("--host", default="127.0.0.1", help="address of the control API (default 127.0.0.1; any other needs a token)")
    d.add_argument("--port", type=int, default=0, help="port of the control API (default: any free port)")
    d.add_argument("--token", help="token the API requires (default: generated and printed when --host is not loopback)")
    d.add_argument("--slots", type=int, help="frames the ring holds (default: about a second of frames within 64 MB, at least 8)")
    d.add_argument("--no-advertise", action="store_true", help="do not advertise the daemon on mDNS")
    d.add_argument("--interface", action="append", metavar="ADDR", help="advertise on this interface address only (repeatable)")
    d.set_defaults(func=cmd_daemon)

    u = sub.add_parser("up", help="start a daemon per camera and keep them running (Ctrl-C or `rig down` stops them)",
                       description="Starts `rig daemon` for every camera of the config and restarts one that exits or whose "
                                   "heartbeat stops, with back-off; prints its events. With --status, prints the state of the "
                                   "rig's running supervisor instead.")
    u.add_argument("-c", "--config", type=Path, required=True, help="rig configuration (TOML)")
    u.add_argument("--stale", type=float, default=STALE_S, help=f"seconds without a heartbeat before a camera daemon is restarted (default {STALE_S:g})")
    u.add_argument("--status", action="store_true", help="print the running supervisor's state and exit")
    u.add_argument("--json", action="store_true", help="with --status: one JSON object")
    u.add_argument("--no-advertise", action="store_true", help="the daemons do not advertise on mDNS")
    u.add_argument("--interface", action="append", metavar="ADDR", help="the daemons advertise on this interface address only (repeatable)")
    u.add_argument("--cameras", metavar="NAMES", help="only these cameras' daemons, comma-separated, '@board' for the trigger board's: "
                                                      "this host's part of a rig whose cameras hang on several hosts")
    u.add_argument("--host", help="the daemons' APIs listen on this address, for other hosts (needs --token)")
    u.add_argument("--token", help="the token every daemon's API (and networked trigger input) requires, the same on every host of the rig")
    u.set_defaults(func=cmd_up)

    dn = sub.add_parser("down", help="stop the rig's supervisor and its daemons")
    dn.add_argument("-c", "--config", type=Path, required=True, help="rig configuration (TOML)")
    dn.set_defaults(func=cmd_down)


def _stop_on_signals(event: threading.Event) -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: event.set())


def cmd_daemon(args: argparse.Namespace) -> int:
    from rig.config import load_config
    from rig.daemon.camera_daemon import CameraDaemon
    from rig.errors import ConfigError
    from rig.http_access import is_loopback_name

    if args.slots is not None and not 1 <= args.slots <= 1024:
        raise ConfigError(f"--slots must be from 1 to 1024, got {args.slots}")
    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port must be from 0 to 65535, got {args.port}")
    if args.board == (args.camera is not None):
        raise ConfigError("name one CAMERA, or give --board for the trigger board's daemon")
    cfg = load_config(args.config, check_calibration=False)
    if not args.board and args.camera not in [c.name for c in cfg.cameras]:
        raise ConfigError(f"{args.config}: no camera named {args.camera!r} (cameras: {', '.join(c.name for c in cfg.cameras)})")
    token = args.token
    if token is None and not is_loopback_name(args.host):
        token = secrets.token_urlsafe(24)
        print(f"rig daemon {args.camera or '--board'}: API token {token}", file=sys.stderr, flush=True)
    if args.board:
        return _board_daemon(cfg, args, token)
    daemon = CameraDaemon(cfg, args.camera, host=args.host, port=args.port, token=token, advertise=not args.no_advertise,
                          interfaces=args.interface, slots=args.slots)
    _stop_on_signals(daemon.stop_event)
    try:
        daemon.open()
        print(f"rig daemon {args.camera}: serving {daemon.ring.path}, API {daemon.api.url}", file=sys.stderr, flush=True)
        daemon.run()
    finally:
        daemon.close()
    return 0


def _board_daemon(cfg, args: argparse.Namespace, token) -> int:
    from rig.daemon.board_daemon import BoardDaemon

    daemon = BoardDaemon(cfg, host=args.host, port=args.port, token=token, advertise=not args.no_advertise, interfaces=args.interface)
    _stop_on_signals(daemon.stop_event)
    try:
        daemon.open()
        api = daemon.api.url + (f" and {daemon.net_api.url} (with the token)" if daemon.net_api else "")
        print(f"rig daemon --board: trigger board {cfg.trigger.uri}, API {api}", file=sys.stderr, flush=True)
        daemon.run()
    finally:
        daemon.close()
    return 0


def cmd_up(args: argparse.Namespace) -> int:
    from rig.config import load_config
    from rig.daemon import paths
    from rig.daemon.supervisor import Supervisor
    from rig.errors import ConfigError, DeviceError

    if not args.stale > 0:
        raise ConfigError(f"--stale must be positive, got {args.stale}")
    cfg = load_config(args.config, check_calibration=False)
    state = paths.read_json(paths.supervisor_path(cfg.name))
    running = state is not None and paths.pid_alive(state.get("pid"))
    if args.status:
        if not running:
            raise DeviceError(f"rig '{cfg.name}': no supervisor runs (start one with `rig up -c {args.config}`)")
        if args.json:
            from rig.commands._output import emit_json

            emit_json(state)
        else:
            for name, c in state["cameras"].items():
                print(f"{name:12s} {c['state']:10s} pid {c['pid']}  restarts {c['restarts']}  {c['last_event']}")
        return 0
    if running:
        raise DeviceError(f"rig '{cfg.name}': a supervisor already runs (pid {state['pid']}); `rig down -c {args.config}` stops it")
    daemon_args = ["--no-advertise"] if args.no_advertise else [a for addr in args.interface or () for a in ("--interface", addr)]
    if args.host is not None:
        if not args.token:
            raise ConfigError("--host: daemons that other hosts reach need --token (the same on every host of the rig)")
        daemon_args += ["--host", args.host]
    if args.token:
        daemon_args += ["--token", args.token]
    only = None
    if args.cameras is not None:
        from rig.daemon.supervisor import BOARD

        only = {n.strip() for n in args.cameras.split(",") if n.strip()}
        known = [c.name for c in cfg.cameras] + ([BOARD] if cfg.trigger is not None else [])
        unknown = sorted(only - set(known))
        if unknown or not only:
            raise ConfigError(f"--cameras {args.cameras}: " + (f"no camera named {', '.join(unknown)}" if unknown else "name at least one")
                              + f" (this rig has: {', '.join(known)})")
    sup = Supervisor(cfg, args.config, stale_s=args.stale, daemon_args=tuple(daemon_args),
                     say=lambda line: print(f"rig up: {line}", flush=True), only=only)
    _stop_on_signals(sup.stop_event)
    from rig.daemon.supervisor import BOARD

    names = [n for n in sup.children if n != BOARD]
    board = " and its trigger board's" if BOARD in sup.children else ""
    print(f"rig up: starting {len(names)} camera daemons{board} of rig '{cfg.name}' ({', '.join(names)})", flush=True)
    sup.run()
    print(json.dumps({"restarts": {c.camera: c.restarts for c in sup.children.values()}}), flush=True)
    return 0


def cmd_down(args: argparse.Namespace) -> int:
    from rig.config import load_config
    from rig.daemon.supervisor import stop_supervisor

    cfg = load_config(args.config, check_calibration=False)
    pid = stop_supervisor(cfg.name)
    print(f"rig down: rig '{cfg.name}': " + ("no supervisor was running" if pid is None else f"supervisor {pid} and its daemons stopped"))
    return 0
