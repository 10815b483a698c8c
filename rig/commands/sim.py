"""`rig sim snapshot`: ground-truth renders of a simulated rig at one instant; `rig sim dataset`:
simulated takes rendered offline for training."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from rig.errors import ConfigError


def register(sub) -> None:
    p = sub.add_parser("sim", help="the synthetic simulator: ground-truth snapshots of a sim rig")
    s = p.add_subparsers(dest="sim_command", metavar="ACTION")
    s.required = True
    snap = s.add_parser(
        "snapshot",
        help="render every camera of a sim config at one instant, with exact depth, mask and calibration",
        description="For every sim:// camera writes NAME.png (RGB), NAME.depth.npy (float32 metres, 0 where "
                    "nothing is hit), NAME.mask.png (people) and cameras.json (the exact calibration).")
    snap.add_argument("-c", "--config", required=True, type=Path, help="rig configuration (TOML) with sim:// cameras")
    snap.add_argument("-t", "--time", required=True, type=float, help="simulated time in seconds (>= 0)")
    snap.add_argument("-o", "--out", required=True, type=Path, help="new (or empty) output folder")
    snap.add_argument("--force", action="store_true",
                      help="write into a folder that holds files already (an earlier snapshot's files of the same names are replaced)")
    snap.add_argument("--json", action="store_true", help="print a summary as one JSON object (stderr: errors only)")
    snap.set_defaults(func=cmd_snapshot)
    ds = s.add_parser(
        "dataset",
        help="render simulated six-camera takes offline (as fast as the renderer goes) for training",
        description="Writes OUT/take-000, take-001, ... in the sequence format (docs/sequence-format.md), each "
                    "with a left and a right source and four supervision cameras between them, and "
                    "OUT/dataset.json. Take i of --seed K is seeded K*1000+i: data sets of different seeds "
                    "never share a take, so hold out takes with another --seed. People, clothes, body sizes, "
                    "motions, lighting, room, props and camera placement vary with the take's seed.")
    ds.add_argument("-o", "--out", required=True, type=Path, help="new (or empty) output folder")
    ds.add_argument("--takes", required=True, type=int, help="number of takes")
    ds.add_argument("--seconds", required=True, type=float, help="length of each take in seconds")
    ds.add_argument("--seed", type=int, default=0, help="data-set seed (default 0)")
    ds.add_argument("--fps", type=float, default=30.0, help="frame sets per second of a take (default 30)")
    ds.add_argument("--size", default="640x360", help="image size WxH (default 640x360; about 124 MB per second of take at 30 fps)")
    ds.add_argument("--noise", action="store_true", help="pass the images through the sensor model (shot and read noise)")
    ds.add_argument("--json", action="store_true", help="print a summary as one JSON object")
    ds.set_defaults(func=cmd_dataset)


def cmd_snapshot(args: argparse.Namespace) -> int:
    from rig.commands._paths import new_output_folder, output_folder
    from rig.config import load_config
    from rig.progress import Notes, StatusLine

    if not math.isfinite(args.time) or args.time < 0:
        raise ConfigError(f"-t: time must be a number of seconds >= 0, got {args.time:g}")
    cfg = load_config(args.config)
    if not any(c.scheme == "sim" for c in cfg.cameras):
        raise ConfigError(f"{args.config}: no sim:// cameras to render (make one with `rig config init --sim`)")
    # a snapshot can be made again, but the folder may hold anything (a take, someone's images)
    if args.force:
        output_folder(args.out)
    elif args.out.is_dir() and any(args.out.iterdir()):
        raise ConfigError(f"{args.out}: folder is not empty; choose a new folder, or --force to write into it (nothing was overwritten)")
    else:
        new_output_folder(args.out)
    from simulator.snapshot import write_snapshot

    notes = Notes(quiet=args.json)
    n = sum(c.scheme == "sim" for c in cfg.cameras)
    notes(f"building the simulated scene and rendering {n} cameras at t = {args.time:g} s")
    status = StatusLine()
    # on a terminal the live status says which camera is rendering; in a log, a line each
    summary = write_snapshot(cfg, args.time, args.out, progress=status.update if status.enabled else notes)
    status.done(f"wrote {len(summary['cameras'])} cameras to {args.out}")
    skipped = [c.name for c in cfg.cameras if c.scheme != "sim"]
    if skipped:
        summary["skipped"] = skipped
    if args.json:
        from rig.commands._output import emit_json

        emit_json(summary)
    else:
        names = ", ".join(c["name"] for c in summary["cameras"])
        print(f"wrote {args.out}: {names} (png, depth.npy, mask.png) and {summary['calibration']} at t = {args.time:g} s")
    return 0


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size: expected WIDTHxHEIGHT such as 640x360, got {text!r}") from None
    return w, h


def cmd_dataset(args: argparse.Namespace) -> int:
    from rig.commands._paths import new_output_folder
    from rig.progress import ProgressBar

    size = _size(args.size)
    new_output_folder(args.out)
    from simulator.takes import write_dataset

    with ProgressBar(f"rendering {args.takes} take(s)") as bar:
        summary = write_dataset(args.out, args.takes, args.seconds, args.seed, fps=args.fps, size=size,
                                noise=args.noise, progress=bar.update)
    if args.json:
        from rig.commands._output import emit_json

        emit_json(summary)
    else:
        print(f"wrote {len(summary['takes'])} takes of {summary['sets_per_take']} sets "
              f"({summary['size'][0]}x{summary['size'][1]}, {len(summary['cameras'])} cameras) to {args.out} "
              f"in {summary['wall_s']:.1f} s; take seeds {summary['take_seeds']}")
    return 0
