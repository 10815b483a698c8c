"""`rig console`: one page in the browser that runs the rig (docs/console.md)."""
from __future__ import annotations

import argparse
import secrets
import signal
import sys
import threading
from pathlib import Path

DEFAULT_PORT = 8090


def register(sub) -> None:
    p = sub.add_parser("console", help="serve the crew's console: camera tiles, exposure and gain, takes (docs/console.md)",
                       description="Run the rig and serve its console at http://HOST:PORT/: a tile per camera (preview, fps, "
                                   "drops, exposure and gain set live), takes recorded with rig record's own recorder, notes, "
                                   "and the list of takes, the trigger board and a sync check, calibration views and rig "
                                   "calibrate run's solve, a Live tab with rig live's view, the host's checks. In-process or attached to the daemons of `rig up`. Loopback by "
                                   "default; any other address needs an operator token (generated and printed if not given); "
                                   "a viewer token may watch only.")
    p.add_argument("-c", "--config", type=Path, required=True, help="rig configuration (TOML)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT}; 0 = any free port)")
    p.add_argument("--token", help="operator token: may change settings and record (at least 8 characters)")
    p.add_argument("--viewer-token", help="viewer token: may watch only (at least 8 characters; needs --token or a generated one)")
    p.add_argument("--board", type=Path, help="calibration board (TOML) for the calibration panel (default: board.toml beside "
                                               "the config, as `rig config init --sim` writes it, when there is one)")
    p.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C)")
    p.set_defaults(func=cmd_console)


def cmd_console(args: argparse.Namespace) -> int:
    from rig.config import load_config
    from rig.console.rigstate import ConsoleRig
    from rig.console.server import ConsoleServer
    from rig.errors import ConfigError, RigError
    from rig.http_access import bind_socket, is_loopback_name

    if args.seconds is not None and not args.seconds > 0:
        raise ConfigError("console: --seconds must be positive")
    if not 0 <= args.port < 65536:
        raise ConfigError(f"console: --port must be between 0 and 65535, got {args.port}")
    for flag, value in (("--token", args.token), ("--viewer-token", args.viewer_token)):
        if value is not None and len(value) < 8:
            raise ConfigError(f"console: {flag} must be at least 8 characters")
    token = args.token
    if token is None and (args.viewer_token is not None or not is_loopback_name(args.host)):
        token = secrets.token_urlsafe(18)  # a non-loopback console is never open
    if token is not None and token == args.viewer_token:
        raise ConfigError("console: --viewer-token must differ from the operator token")
    # The calibration the config names may not exist yet: the console's calibration panel makes it.
    cfg = load_config(args.config, check_calibration=False)
    board = args.board
    if board is None and cfg.path is not None and (cfg.path.parent / "board.toml").is_file():
        board = cfg.path.parent / "board.toml"
    if board is not None:
        from calibration.boards import load_board

        load_board(board)  # a bad board file is one line now, not a failed calibration later
    try:
        sock = bind_socket(args.host, args.port, "console")
    except RigError as exc:
        raise ConfigError(str(exc)) from None
    rig = ConsoleRig(cfg, board_file=board).start()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        server = ConsoleServer(rig, args.host, args.port, token, args.viewer_token, sock=sock).start()
        print(f"console: serving {server.url}" + (f"?token={token}" if token else "") + "  (Ctrl-C stops)", file=sys.stderr, flush=True)
        if token and args.token is None:
            print(f"console: operator token {token} (give it as ?token=, a Bearer header, or --token to choose one)", file=sys.stderr, flush=True)
        try:
            stop.wait(args.seconds)
        except KeyboardInterrupt:
            pass
        server.stop()
    finally:
        rig.close()
    return 0
