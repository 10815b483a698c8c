"""The steps of `rig demo`: each runs the library function its command runs (the command line is
printed, so a user sees what to type on a real rig) and gives the command's --json object. A step
that fails as its command would (exit 1) prints the command's error lines on stderr and stops the
demo with one error naming the step.
"""
from __future__ import annotations

import sys
from pathlib import Path


def echo(argv: list[str]) -> None:
    print(f"$ rig {' '.join(argv)}", flush=True)


def _failed(argv: list[str], errors: list[str]):
    from rig.errors import RigError

    for e in errors:
        print(f"rig: error: {e}", file=sys.stderr)
    return RigError(f"demo step `rig {' '.join(argv)}` failed (exit 1)")


def calibration_views(rig_file: Path, board_file: Path, out: Path, views: int) -> dict:
    """`rig calibrate capture -c RIG --board BOARD -o OUT --views N` on the demo's simulated rig, whose
    scene becomes a calibration session (the board held at stations through the volume)."""
    from calibration.boards import load_board
    from rig.capture.calibration_views import MAX_FRAMES, TIMEOUT_S, capture_views, check_capture, stereo_roles, still_settings
    from rig.commands._paths import new_output_folder
    from rig.config import load_config
    from rig.sim.calibration import calibration_session

    echo(["calibrate", "capture", "-c", str(rig_file), "--board", str(board_file), "-o", str(out), "--views", str(views)])
    cfg = load_config(rig_file, check_calibration=False)
    board = load_board(board_file)
    new_output_folder(out)
    settings = still_settings(cfg.cameras)
    session = calibration_session(settings, board)
    summary = capture_views(settings, board, out, stereo_roles(cfg.cameras), views, min(MAX_FRAMES, session.sets), 0.0, TIMEOUT_S)
    check_capture(summary, board_file, [s.name for s in settings])
    return summary


def calibrate(images: Path, board_file: Path, output: Path) -> dict:
    """`rig calibrate run --images DIR --board BOARD -o OUT --k3 hold`: the simulated lenses are
    ordinary (62 degrees across, k3 = 0), so k3 is held, as it should be for such lenses; p1 p2 are
    fitted (the simulator's lenses have them)."""
    from rig.calibrate.lens import LensChoices
    from rig.calibrate.run import calibrate_images, run_inputs
    from rig.commands._paths import output_file

    echo(["calibrate", "run", "--images", str(images), "--board", str(board_file), "-o", str(output), "--k3", "hold"])
    inputs = run_inputs(str(images), str(board_file), LensChoices(k3="hold"))
    result = calibrate_images(inputs, output_file(output))
    failed = result.write_error()
    if failed is not None:
        raise failed
    return result.summary()


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
