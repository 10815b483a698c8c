"""The steps of `rig demo`: each runs the library function its command runs (the command line is
printed, so a user sees what to type on a real rig) and gives the command's --json object. A step
that fails as its command would (exit 1) prints the command's error lines on stderr and stops the
demo with one error naming the step.
"""
from __future__ import annotations

import contextlib
import io
import json
import sys
from pathlib import Path


def echo(argv: list[str]) -> None:
    print(f"$ rig {' '.join(argv)}", flush=True)


def _failed(argv: list[str], errors: list[str]):
    from rig.errors import RigError

    for e in errors:
        print(f"rig: error: {e}", file=sys.stderr)
    return RigError(f"demo step `rig {' '.join(argv)}` failed (exit 1)")


def run_command(argv: list[str]) -> dict:
    """A step with no function of its own outside its command: the command, run in this process
    with --json, its output read back."""
    from rig.commands import dispatch
    from rig.errors import RigError

    echo(argv)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = dispatch(argv + ["--json"])
    if rc != 0:
        raise RigError(f"demo step `rig {' '.join(argv)}` failed (exit {rc})")
    return json.loads(buf.getvalue())


def record(rig_file: Path, take: Path, seconds: float) -> dict:
    """`rig record -c RIG -o TAKE --seconds S`."""
    import signal

    from rig.capture.record import record as record_take
    from rig.commands.record import _stop_on_sigterm
    from rig.config import load_config
    from rig.progress import Notes, StatusLine

    argv = ["record", "-c", str(rig_file), "-o", str(take), "--seconds", str(seconds)]
    echo(argv)
    cfg = load_config(rig_file)
    signal.signal(signal.SIGTERM, _stop_on_sigterm)
    result = record_take(cfg, take, seconds=seconds, status=StatusLine(sys.stderr), notes=Notes(quiet=True))
    if result.errors:
        raise _failed(argv, result.errors)
    return result.to_dict()


def validate(take: Path) -> dict:
    """`rig record validate TAKE`."""
    from rig.commands.record import unreadable
    from rig.storage.validate import validate as validate_take

    argv = ["record", "validate", str(take)]
    echo(argv)
    v = validate_take(take)
    if not v.readable:
        raise _failed(argv, [unreadable(v)])
    return v.to_dict()


def align(take: Path) -> dict:
    """`rig record align TAKE`."""
    from rig.commands.record import not_aligned
    from rig.storage.align import align as align_take

    argv = ["record", "align", str(take)]
    echo(argv)
    r = align_take(take)
    failed = not_aligned(r, take)
    if failed:
        raise _failed(argv, [failed])
    return r


def orbit(take: Path, frames: int, out: Path) -> dict:
    """`rig model render --sequence TAKE --orbit --frames K -o OUT` with the shipped model."""
    from rig.progress import StatusLine
    from rig.render.take import Steer, open_renderer, open_take, plan_views, render_take, summary

    echo(["model", "render", "--sequence", str(take), "--orbit", "--frames", str(frames), "-o", str(out)])
    seq = open_take(take)
    plan = plan_views(seq, 0, Steer(), frames=frames)
    renderer = open_renderer(None, "cpu")
    status = StatusLine()
    done = render_take(seq, plan, renderer, out, progress=lambda text: status.update(text, force=True))
    status.done()
    return summary(seq, plan, renderer, out, done)
