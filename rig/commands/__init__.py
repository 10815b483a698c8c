"""Subcommand groups of the `rig` CLI: one module per group, each with `register(subparsers)`.

`build_parser()` finds the groups by module name (adding a group is adding a module); `dispatch()`
parses a command line and runs it. `rig.cli.main` wraps `dispatch` with the one-line error rule;
`rig demo` calls `dispatch` directly to run its steps.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="rig", description="Multi-camera rig: capture, sync, calibration, recording and live free-viewpoint output.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        importlib.import_module(f"{__name__}.{info.name}").register(sub)
    return parser


def dispatch(argv: list[str] | None = None) -> int:
    """Parse `argv` (default: the process's arguments) and run the command; its errors propagate."""
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)
