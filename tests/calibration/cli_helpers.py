"""Run a `rig calibrate` command in this process, as the CLI would, and read its --json answer."""
from __future__ import annotations

import contextlib
import io
import json

from rig.cli import main


def run_json(*argv) -> dict:
    """`rig ARGV --json`; asserts it succeeded and returns the one JSON object it printed."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main([*map(str, argv), "--json"])
    assert rc == 0, (argv, buf.getvalue())
    return json.loads(buf.getvalue())
