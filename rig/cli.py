"""The `rig` command line. Each subcommand group lives in `rig/commands/<group>.py` with `register()`.

Rules: every subcommand has --help; commands that report take --json and then print one JSON object
on stdout; bad input exits 2 with one line on stderr and no traceback; failures during work exit 1.
"""
from __future__ import annotations

import sys

from common.errors import ReportedError
from rig.commands import dispatch


def main(argv: list[str] | None = None) -> int:
    try:
        return dispatch(argv)
    except ReportedError as exc:
        print(f"rig: error: {exc}", file=sys.stderr)
        return int(exc.exit_code)
    except KeyboardInterrupt:
        print("rig: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 1


if __name__ == "__main__":
    sys.exit(main())
