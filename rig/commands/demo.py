"""`rig demo`: the main job, end to end on the simulated six-camera rig.

1. write the rig (six sim:// cameras on an arc, fired by the emulated trigger board);
2. calibrate it: capture synced views of a ChArUco board carried through the volume, solve, and
   compare with the simulator's exact cameras;
3. record a take of the people in the scene, in sync, with the calibration;
4. validate the take and say where it is and what to do next.
Each step is the same command a user runs on a real rig (printed as it runs).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the main job on the simulated rig: calibrate, record, validate (no hardware needed)")
    p.add_argument("-o", "--out", type=Path, default=Path("out/demo"), help="working folder (default out/demo)")
    p.add_argument("--cameras", type=int, default=6, help="cameras in the simulated rig (default 6: 2 sources + 4 supervision)")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=360)
    p.add_argument("--seconds", type=float, default=10.0, help="length of the recorded take (default 10)")
    p.add_argument("--views", type=int, default=24, help="calibration views to keep (default 24)")
    p.set_defaults(func=cmd_demo)


def _run(argv: list[str]) -> dict:
    """Run one `rig` command in this process, echoing it; returns its --json output."""
    from rig.commands import dispatch
    from rig.errors import RigError

    print(f"$ rig {' '.join(argv)}", flush=True)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = dispatch(argv + ["--json"])
    if rc != 0:
        raise RigError(f"demo step `rig {' '.join(argv)}` failed (exit {rc})")
    return json.loads(buf.getvalue())


def cmd_demo(args: argparse.Namespace) -> int:
    from calibration.camera import RigCalibration
    from calibration.compare import describe, errors_against_truth
    from rig.cameras.sim import sim_rig_config
    from rig.config import dump_config, parse_config
    from rig.errors import ConfigError
    from simulator.scene import default_board
    from simulator.sensor import sim_rig

    out: Path = args.out
    if (out / "take").exists():
        raise ConfigError(f"{out}: holds an earlier demo; remove it or choose another folder with -o")
    out.mkdir(parents=True, exist_ok=True)

    # 1. the rig, and the same rig looking at a calibration board instead of people
    data = sim_rig_config(n_cameras=args.cameras, width=args.width, height=args.height, fps=30.0)
    data["sim"].update({"loop_frames": 20})
    rig_file = out / "rig.toml"
    board_rig = dict(data, sim=dict(data["sim"], board="charuco", people=0, loop_frames=0))
    board_rig_file = out / "rig-board.toml"
    board_rig_file.write_text(dump_config(parse_config(board_rig)))
    board = default_board("charuco")
    board_file = out / "board.toml"
    board_file.write_text("".join(f"{k} = {json.dumps(v)}\n" for k, v in board.to_dict().items()))
    print(f"1/4  simulated rig: {args.cameras} cameras at {args.width}x{args.height}, emulated trigger board  ->  {rig_file}")

    # 2. calibration
    print("2/4  calibrating: a ChArUco board is carried through the volume")
    views = out / "calibration-views"
    cap = _run(["calibrate", "capture", "-c", str(board_rig_file), "--board", str(board_file), "-o", str(views),
                "--views", str(args.views), "--max-frames", str(3 * args.views), "--interval", "0.25"])
    calib_file = out / "calibration.json"
    res = _run(["calibrate", "run", "--images", str(views), "--board", str(board_file), "-o", str(calib_file)])
    calib = RigCalibration.load(calib_file)
    truth = sim_rig(parse_config(board_rig)).calibration
    worst = errors_against_truth(calib, truth).worst  # both in the calibration's frame (its left camera's)
    print(f"     kept {cap.get('views_kept')} views; RMS {', '.join(f'{k} {v:.2f}' for k, v in res['rms_px'].items())} px; "
          f"stereo RMS {res['stereo_rms_px']:.2f} px; baseline {res['baseline_m'] * 1000:.1f} mm")
    print(f"     against the simulator's exact cameras (worst camera): {describe(worst)}")

    # 3. the take, with the calibration
    data["rig"]["calibration"] = calib_file.name
    rig_file.write_text(dump_config(parse_config(data)))
    take = out / "take"
    print(f"3/4  recording {args.seconds:g} s of the scene in sync")
    rec = _run(["record", "-c", str(rig_file), "-o", str(take), "--seconds", str(args.seconds)])
    print(f"     {rec['sets']} sets ({rec['complete_sets']} complete), frames lost {sum(rec['frames_lost'].values())}, "
          f"{rec['mb_per_s']:.1f} MB/s")

    # 4. validation
    val = _run(["record", "validate", str(take)])
    print(f"4/4  validated: {'readable' if val['readable'] else 'NOT readable'}, {val['sets']} sets, "
          f"skew p99 {val['skew_us'].get('p99', 0):.0f} us, calibrated: {val['calibrated']}")
    print(f"\nthe take: {take}/  (index.jsonl, frames/, calibration.json; format: docs/sequence-format.md)")
    print(f"next: `rig record validate {take}`; read it for training with rig.storage.dataset.Sequence('{take}');"
          f" export the calibration with `rig calibrate export {calib_file} --format colmap -o OUT`")
    return 0 if val["readable"] else 1
