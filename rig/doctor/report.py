"""The doctor's report as text lines, a JSON object, and a fix script for the user to review."""
from __future__ import annotations

import shlex
import socket
import time

from rig.doctor.check import FAIL, OK, WARN, Check, worst

MARK = {OK: "ok  ", WARN: "warn", FAIL: "FAIL"}


def text_lines(checks: list[Check]) -> list[str]:
    out = []
    for c in checks:
        line = f"{MARK[c.status]}  {c.area:<8} {c.name}: {c.measured} (needs {c.needed})"
        if c.status != OK and c.fix:
            line += f"\n          fix: {c.fix}"
        if c.status != OK and c.note:
            line += f"\n          {c.note}"
        out.append(line)
    n = {s: sum(c.status == s for c in checks) for s in (OK, WARN, FAIL)}
    out.append(f"{worst(checks)}: {n[OK]} ok, {n[WARN]} warn, {n[FAIL]} fail")
    return out


def to_json(checks: list[Check], rig: str, config: str | None) -> dict:
    return {"rig": rig, "config": config, "verdict": worst(checks),
            "counts": {s: sum(c.status == s for c in checks) for s in (OK, WARN, FAIL)},
            "checks": [c.to_json() for c in checks]}


def _comment(text: str) -> str:
    return " ".join(str(text).split())  # one line: a newline would end the comment


def fix_script(checks: list[Check], rig: str, config: str | None) -> str:
    """A bash script of every fix (failures first, then warnings), each under a comment saying what
    it fixes. Nothing runs until the user runs it; `set -e` stops at the first command that fails."""
    lines = ["#!/usr/bin/env bash",
             f"# Fixes `rig doctor` proposes for rig {_comment(rig)!s}"
             + (f" ({_comment(config)})" if config else "") + f" on {_comment(socket.gethostname())}, "
             + time.strftime("%Y-%m-%d %H:%M") + ".",
             "# Review every line before running it: each one changes this host. Run `rig doctor` again after.",
             "set -euo pipefail", ""]
    todo = [c for c in checks if c.status == FAIL] + [c for c in checks if c.status == WARN]
    fixed = 0
    for c in todo:
        lines.append(f"# [{c.status}] {_comment(c.area)} {_comment(c.name)}: {_comment(c.measured)} (needs {_comment(c.needed)})")
        if c.note:
            lines.append(f"#   {_comment(c.note)}")
        if c.fix:
            lines.append(c.fix)
            fixed += 1
        else:
            lines.append("#   (no command fixes this one: see the note)")
        lines.append("")
    if not todo:
        lines.append("# nothing to fix: every check is ok")
    lines.append(f"echo {shlex.quote(f'{fixed} fix(es) applied; run rig doctor again')}")
    return "\n".join(lines) + "\n"
