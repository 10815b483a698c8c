"""Subcommand groups of the `rig` CLI: one module per group, each with `register(subparsers)`.

`build_parser()` finds the groups by module name (adding a group is adding a module); `dispatch()`
parses a command line and runs it. `rig.cli.main` wraps `dispatch` with the one-line error rule.
A command parses its arguments, checks them, calls the function of its step (in the package of the
step: rig.capture, rig.storage, rig.render, inference, calibration) and prints what it gives.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil


class _Parser(argparse.ArgumentParser):
    """Every parser of the CLI (argparse makes sub-parsers of the parent's class).

    Options go before or after positionals on every command: a command's own parser (one without
    sub-commands) parses intermixed, options first and then the positionals from what is left.
    Plain argparse matches positionals in runs between options, so two optional positionals such as
    `rig record validate DIR` were both consumed by `validate` alone when an option came between
    (`rig record validate --json DIR`: "unrecognized arguments"). argparse cannot parse a parser
    with sub-commands intermixed, hence per command rather than once at the top.
    """

    _intermixing = False  # set while parse_known_intermixed_args runs: its own inner passes are plain

    def error(self, message: str):  # one line, exit 2
        self.exit(2, f"{self.prog}: error: {message}\n")

    def parse_known_args(self, args=None, namespace=None):
        if self._intermixing or self._subparsers is not None:
            return super().parse_known_args(args, namespace)
        self._intermixing = True
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._intermixing = False


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
