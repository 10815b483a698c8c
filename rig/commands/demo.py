"""`rig demo`: the main job, end to end on the simulated six-camera rig.

1. write the rig (six sim:// cameras on an arc, fired by the emulated trigger board), as
   `rig config init --sim` does;
2. calibrate it: `rig calibrate capture` on that rig (a simulated rig shows the board itself: someone
   holds it at stations through the volume), `rig calibrate run`, its warnings, and how far the result
   is from the simulator's exact cameras;
3. record a take of the people in the scene, in sync, with the calibration;
4. validate the take;
5. render novel views of the take with the shipped trained model (ONNX Runtime, the live path) in
   place of every supervision camera, against what that camera recorded; say where everything is,
   how much disk it took and what to do next.
Each step is the same command a user runs on a real rig (printed as it runs). Every argument, the
output folder and the free disk space are checked before any of it starts.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

FPS = 30.0
MAX_CAMERAS = 64
# What the demo's calibration must reach against the simulator's exact cameras at its default size
# (six cameras, 640x360); measured: see docs/calibration.md, "The demo's calibration".
TARGET = {"focal_pct": 0.1, "principal_px": 1.0, "rotation_deg": 0.05, "position_mm": 2.0}
PNG_RATIO = 0.6  # a rendered calibration view's PNG against its raw size (measured about 0.55)


ORBIT_FRAMES = 48  # at most: one frame per set, from the take's first set


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the main job on the simulated rig: calibrate, record, validate, render novel views with the shipped model "
                            "(no hardware needed)",
                       description="Calibrate a simulated rig, record a take with the calibration and validate it, running the same "
                                   "commands a user runs on a real rig; then render novel views of the take with the shipped model "
                                   "(PNGs against the supervision cameras, an orbit video and a strip) and print how to run the rig "
                                   "live. Writes a few hundred MB by default (it says how much first).")
    p.add_argument("-o", "--out", type=Path, default=Path("out/demo"), help="working folder, new or empty (default out/demo)")
    p.add_argument("--cameras", type=int, default=6, help=f"cameras in the simulated rig, 2 to {MAX_CAMERAS} (default 6: 2 sources + 4 supervision)")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=360)
    p.add_argument("--seconds", type=float, default=10.0, help="length of the recorded take (default 10)")
    p.add_argument("--views", type=int, default=None,
                   help="calibration views to keep (default: every view the simulated session offers, about 13 per camera + 13)")
    p.add_argument("--gopro", type=int, nargs="?", const=2, default=None, metavar="N",
                   help="instead: the two sources with N GoPros (default 2) as supervision cameras, on emulators of the Open "
                        "GoPro API filming the scene: record, align the GoPros to the trigger pulses by the board's LED, "
                        "validate, and compare the alignment with the simulator's truth")
    p.set_defaults(func=cmd_demo)


def _check_arguments(args: argparse.Namespace) -> None:
    """Every argument, before anything is written or rendered (one line, exit 2)."""
    from rig.errors import ConfigError

    if not 2 <= args.cameras <= MAX_CAMERAS:
        raise ConfigError(f"--cameras: a rig needs at least the left and right cameras (2) and at most {MAX_CAMERAS}, got {args.cameras}")
    for name, value, lo, hi in (("--width", args.width, 64, 8192), ("--height", args.height, 48, 8192)):
        if not lo <= value <= hi:
            raise ConfigError(f"{name} must be between {lo} and {hi} pixels, got {value}")
    if not (math.isfinite(args.seconds) and 0 < args.seconds <= 3600):
        raise ConfigError(f"--seconds must be more than 0 and at most 3600, got {args.seconds}")
    if args.gopro is not None and not 1 <= args.gopro <= 8:
        raise ConfigError(f"--gopro: between 1 and 8 GoPros, got {args.gopro}")
    if args.gopro is not None and args.views is not None:
        raise ConfigError("--views: the GoPro demo does not calibrate (its emulators film the scene, not a board); leave out --views")
    if args.gopro is not None and args.cameras != 6:
        raise ConfigError("--gopro sets the rig's cameras itself (the two sources and the GoPros): leave out --cameras")
    if args.views is not None and args.views < 4:
        raise ConfigError(f"--views must be at least 4 (the solver needs 4 views of the board per camera), got {args.views}")


def _check_output(out: Path) -> None:
    from rig.commands._paths import new_output_folder
    from rig.errors import ConfigError

    if (out / "take").exists():
        raise ConfigError(f"{out}: holds an earlier demo; remove it or choose another folder with -o (nothing was overwritten)")
    new_output_folder(out)


def disk_estimate(args: argparse.Namespace, calibration_views: int) -> dict[str, int]:
    """Bytes the demo will write: the take's raw frames (RGB8 PPM, one per camera at 30 sets/s) and
    the calibration views (PNG)."""
    frame = args.width * args.height * 3 + 20
    take = int(math.ceil(args.seconds * FPS) + 5) * args.cameras * frame  # a take runs a few sets past its length
    views = int(calibration_views * args.cameras * frame * PNG_RATIO)
    return {"take": take, "calibration_views": views, "total": take + views}


def cmd_demo(args: argparse.Namespace) -> int:
    from rig.commands import _demo_steps as step
    from calibration.boards import board_from_dict
    from rig.sim.rig_config import SIM_RIG_BOARD, board_toml, sim_rig_config
    from rig.config import dump_config, parse_config
    from rig.demo.disk import check_space, mb, written
    from simulator.calibration_session import CalibrationSession

    _check_arguments(args)
    out: Path = args.out
    _check_output(out)
    if args.gopro is not None:
        from rig.commands import _demo_gopro

        return _demo_gopro.run(args)
    data = sim_rig_config(n_cameras=args.cameras, width=args.width, height=args.height, fps=FPS)
    data["sim"].update({"loop_frames": 20})
    cfg = parse_config(data)
    session = CalibrationSession(cfg, board_from_dict(SIM_RIG_BOARD))  # the stations the capture will see
    views = session.sets if args.views is None else min(args.views, session.sets)
    estimate = disk_estimate(args, views)
    check_space(out, estimate["total"])
    out.mkdir(parents=True, exist_ok=True)

    # 1. the rig
    rig_file = out / "rig.toml"
    rig_file.write_text(dump_config(cfg))
    board_file = out / "board.toml"
    board_file.write_text(board_toml(SIM_RIG_BOARD))
    print(f"1/5  simulated rig: {args.cameras} cameras at {args.width}x{args.height}, emulated trigger board  ->  {rig_file}")
    print(f"     the demo writes about {mb(estimate['total'])} into {out} (take {mb(estimate['take'])}, "
          f"calibration views {mb(estimate['calibration_views'])})")

    # 2. calibration
    views_dir, calib_file = out / "calibration-views", out / "calibration.json"
    _calibrate(args, session, rig_file, board_file, views_dir, calib_file, views)

    # 3. the take, with the calibration
    data["rig"]["calibration"] = calib_file.name
    rig_file.write_text(dump_config(parse_config(data)))
    take = out / "take"
    print(f"3/5  recording {args.seconds:g} s of the scene in sync")
    rec = step.record(rig_file, take, args.seconds)
    print(f"     {rec['sets']} sets ({rec['complete_sets']} complete), frames lost {sum(rec['frames_lost'].values())}, "
          f"{rec['mb_per_s']:.1f} MB/s")

    # 4. validation
    val = step.validate(take)
    print(f"4/5  validated: {'readable' if val['readable'] else 'NOT readable'}, {val['sets']} sets, "
          f"exposure skew p99 {_us(val['skew_us'])} (device clocks), arrival spread p99 {_us(val['arrival_spread_us'])}, "
          f"frames lost {sum(val['frames_lost'].values())}, calibrated: {val['calibrated']}")

    # 5. novel views
    _novel_views(take, out, rec["sets"])
    print(f"\nthe take: {take}/  (index.jsonl, frames/, calibration.json; format: docs/sequence-format.md)")
    print(f"disk: {mb(written(out))} written into {out} (take {mb(written(take))}, calibration views {mb(written(views_dir))})")
    print(f"live: `rig live -c {rig_file}` runs this rig through the model and serves the novel view at "
          f"http://{cfg.live.host}:{cfg.live.port}/ (Ctrl-C stops it)")
    print(f"next: `rig record validate {take}`; read it for training with rig.storage.dataset.Sequence('{take}');"
          f" export the calibration with `rig calibrate export {calib_file} --format colmap -o OUT`")
    return 0 if val["readable"] else 1


def _calibrate(args: argparse.Namespace, session, rig_file: Path, board_file: Path, views_dir: Path, calib_file: Path,
               views: int) -> None:
    """Step 2: capture the calibration views, calibrate, and say how far the result is from the
    simulator's exact cameras."""
    from rig.commands import _demo_steps as step
    from calibration.camera import RigCalibration
    from calibration.compare import describe, errors_against_truth

    print(f"2/5  calibrating: {session.describe()}")
    cap = step.calibration_views(rig_file, board_file, views_dir, views)
    res = step.calibrate(views_dir, board_file, calib_file)
    calib = RigCalibration.load(calib_file)
    errs = errors_against_truth(calib, session.truth)  # both in the calibration's frame (its left camera's)
    print(f"     kept {cap.get('views_kept')} views; RMS {', '.join(f'{k} {v:.2f}' for k, v in res['rms_px'].items())} px; "
          f"stereo RMS {res['stereo_rms_px']:.2f} px; baseline {res['baseline_m'] * 1000:.1f} mm")
    for w in res["warnings"]:
        print(f"     warning: {w}")
    worst = errs.worst
    print(f"     against the simulator's exact cameras (worst camera): {describe(worst)}")
    over = [f"{k} {worst[k]:.3g} > {v:g}" for k, v in TARGET.items() if worst[k] > v]
    print("     within the demo's targets (focal 0.1 %, principal point 1 px, 0.05 deg, 2 mm)" if not over else
          f"     OUTSIDE the demo's targets: {', '.join(over)}" + ("" if args.cameras == 6 and (args.width, args.height) == (640, 360)
                                                                 else " (the targets are for the default rig: 6 cameras, 640x360)"))


def _novel_views(take: Path, out: Path, sets: int) -> None:
    """Step 5: novel views in place of the supervision cameras beside what they recorded, a strip
    along the arc and an orbit video, by the shipped model (skipped, said, without one)."""
    from rig.commands import _demo_steps as step
    from inference.errors import InferenceError
    from rig.render.novel_views import render_novel_views, render_strip

    novel = out / "novel-views"
    try:
        nv = render_novel_views(take, novel)
    except InferenceError as exc:  # an installation without the shipped model
        nv = {"skipped": str(exc), "no_model": True}
    if "skipped" in nv:
        print(f"5/5  novel views: skipped: {nv['skipped']}")
    else:
        print(f"5/5  novel views by the shipped model ({nv['model']}): {nv['views']} views of {', '.join(nv['cameras'])} "
              f"from left + right, {nv['ms_per_view']:.0f} ms each")
        print(f"     PSNR against the real cameras {nv['psnr']:.2f} dB (the nearer source as it is: {nv['nearer_source_psnr']:.2f} dB); "
              f"PNGs (novel | real) in {novel}/")
    if nv.get("no_model"):
        return
    try:
        strip = render_strip(take, out / "novel-strip.png")
    except InferenceError as exc:  # an installation without the shipped model
        print(f"     orbit and strip: skipped: {exc}")
        return
    orbit = step.orbit(take, min(ORBIT_FRAMES, sets), out / "orbit.mp4")
    print(f"     orbit video, left to right over the take: {orbit['output']} ({orbit['frames']} frames, {orbit['codec']}); "
          f"strip (left | t = 0.25, 0.5, 0.75 | right): {strip['file']}")


def _us(spread: dict) -> str:
    """A p99 in microseconds, or "not measured"."""
    return f"{spread['p99']:.0f} us" if spread.get("p99") is not None else "not measured"
