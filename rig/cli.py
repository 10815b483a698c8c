"""The `rig` command line. Each subcommand group lives in `rig/commands/<group>.py` with `register()`.

Rules: every subcommand has --help; commands that report take --json and then print one JSON object
on stdout (a failure too: {"error": ..., "exit_code": ...}); bad input exits 2 with one line on stderr and no traceback; failures during work exit 1
(an OSError no command turned into a message included: one line, exit 1).
"""
from __future__ import annotations

import sys

from common.errors import ReportedError
from rig.commands import dispatch


def _json_error(argv: list[str] | None, message: str, code: int) -> None:
    """With --json, a failure is also one JSON object on stdout, for the tool that reads it."""
    if "--json" in (sys.argv[1:] if argv is None else [str(a) for a in argv]):
        from rig.commands._output import emit_json

        emit_json({"error": message, "exit_code": code})


def main(argv: list[str] | None = None) -> int:
    try:
        return dispatch(argv)
    except ReportedError as exc:
        print(f"rig: error: {exc}", file=sys.stderr)
        _json_error(argv, str(exc), int(exc.exit_code))
        return int(exc.exit_code)
    except KeyboardInterrupt:
        print("rig: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 1
    except OSError as exc:
        # The safety net for a file the work could not read or write after all (commands check their
        # outputs before the work, exit 2): one line, exit 1, never a traceback.
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"rig: error: {where}{exc.strerror or exc} (the work stopped here)", file=sys.stderr)
        _json_error(argv, f"{where}{exc.strerror or exc} (the work stopped here)", 1)
        return 1


if __name__ == "__main__":
    sys.exit(main())
