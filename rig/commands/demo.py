"""`rig demo`: the main job, end to end on the simulated rig."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("demo", help="run the main job on the simulated rig (no hardware needed)")
    p.add_argument("-o", "--out", type=Path, default=Path("out/demo"), help="working folder (default out/demo)")
    p.add_argument("--frames", type=int, default=30, help="frames per camera to grab (default 30)")
    p.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    from rig.config import dump_config, load_config, parse_config
    from rig.grab import grab
    from rig.simrig import sim_rig_config

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / "rig.toml"
    cfg_path.write_text(dump_config(parse_config(sim_rig_config(n_cameras=2))))
    cfg = load_config(cfg_path)
    print(f"1/2  simulated two-camera rig written to {cfg_path}")
    result = grab(cfg, args.frames, out / "grab")
    for name, r in result.cameras.items():
        print(f"2/2  {name}: {r.frames} frames, {r.dropped} dropped, {r.fps:.1f} fps")
    if result.errors:
        for e in result.errors:
            print(f"rig: error: {e}")
        return 1
    print(f"\nframes and their index: {out / 'grab'}/ (frames.jsonl)")
    print("next: `rig config check` your own rig file, then `rig grab -c RIG.toml -n 10 -o DIR`")
    return 0
