"""The `rig` command line. Each subcommand group lives in `rig/commands/<group>.py` with `register()`.

Rules: every subcommand has --help; commands that report take --json and then print one JSON object
on stdout; bad input exits 2 with one line on stderr and no traceback; device failures exit 1.
"""
from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import sys

import rig.commands


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="rig", description="Multi-camera rig: capture, sync, calibration, recording and live free-viewpoint output.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for info in sorted(pkgutil.iter_modules(rig.commands.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"rig.commands.{info.name}")
        module.register(sub)
    return parser


def _known_errors() -> tuple[type, ...]:
    from calibration.camera import CalibrationError
    from inference.errors import InferenceError
    from rig.errors import RigError
    from simulator.errors import SimulatorError
    from sync.errors import SyncError

    return (RigError, CalibrationError, SyncError, SimulatorError, InferenceError)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
    except _known_errors() as exc:
        print(f"rig: error: {exc}", file=sys.stderr)
        return int(getattr(exc, "exit_code", 1))
    except KeyboardInterrupt:
        print("rig: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 1
    return int(result or 0)


def emit_json(obj) -> None:
    """Print one JSON object on stdout (the --json contract)."""
    sys.stdout.write(json.dumps(obj, default=_json_default) + "\n")
    sys.stdout.flush()


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


if __name__ == "__main__":
    sys.exit(main())
