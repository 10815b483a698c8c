"""`rig grab`: capture N frames from every camera of a rig to PNG files and frames.jsonl."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("grab", help="capture N frames per camera to PNGs plus frames.jsonl")
    p.add_argument("-c", "--config", required=True, type=Path, help="rig configuration (TOML)")
    p.add_argument("-n", type=int, required=True, help="frames per camera")
    p.add_argument("-o", "--out", required=True, type=Path, help="new (or empty) output folder")
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for each frame (default 2)")
    p.add_argument("--json", action="store_true", help="print one JSON object: frames, dropped, fps per camera")
    p.set_defaults(func=cmd_grab)


def cmd_grab(args: argparse.Namespace) -> int:
    from rig.capture.grab import grab
    from rig.commands._output import emit_json
    from rig.commands._paths import new_output_folder
    from rig.config import load_config
    from rig.errors import ConfigError
    from rig.progress import Notes

    if args.n < 1:
        raise ConfigError(f"-n: must be at least 1, got {args.n}")
    if not args.timeout > 0:
        raise ConfigError(f"--timeout: must be a positive number of seconds, got {args.timeout:g}")
    cfg = load_config(args.config)
    new_output_folder(args.out)  # an earlier grab there would be appended to and its frames overwritten
    result = grab(cfg, args.n, args.out, timeout=args.timeout, notes=Notes(quiet=args.json))
    summary = result.summary()
    if args.json:
        emit_json(summary)
    else:
        for name, r in result.cameras.items():
            print(f"{name}: {r.frames} frames, {r.dropped} dropped, {r.fps:.1f} fps")
        print(f"written to {args.out} (index: {args.out / 'frames.jsonl'})")
    for err in result.errors:
        print(f"rig: error: {err}", file=sys.stderr)
    if result.errors:
        return max(getattr(e, "exit_code", 1) for e in result.errors)
    return 0
