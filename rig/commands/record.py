"""`rig record`: record synced, calibrated sequences; `validate` and `repair` them."""
from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("record", help="record every camera of the rig in sync to a sequence folder; validate, repair or align one, fetch its card videos")
    p.add_argument("action", nargs="?", choices=("validate", "repair", "align", "fetch"),
                   help="validate DIR | repair DIR | align DIR | fetch DIR (omit to record); repair keeps every good set and "
                        "the original index beside it; align puts free-running cameras' frames (and card cameras' videos) on "
                        "the trigger pulses by the LED flashes the board fired during the take (the original index kept "
                        "beside it); fetch downloads what cameras recording to their cards (gopro://...?record=card) recorded "
                        "during the take and is still missing from it, resuming partial downloads")
    p.add_argument("dir", nargs="?", type=Path, help="sequence folder (validate / repair / align / fetch)")
    p.add_argument("-c", "--config", type=Path, help="rig configuration (TOML), to record")
    p.add_argument("-o", "--out", type=Path, help="new (or empty) sequence folder, to record")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--seconds", type=float, help="record for this long")
    g.add_argument("--sets", type=int, help="record this many frame sets")
    p.add_argument("--pixels", action="store_true", help="validate, repair: also decode every image (slower; repair then "
                                                         "marks an image that does not decode missing)")
    p.add_argument("--camera", action="append", metavar="NAME", help="align, fetch: this camera (repeatable; default: every camera "
                                                                      "not hardware-triggered / every card camera)")
    p.add_argument("--no-flash", action="store_true", help="record: do not flash the board's LED (by default a take with free-running "
                                                           "cameras and a trigger board gets two flashes, for `rig record align`)")
    p.add_argument("--compress", choices=("png",), default=None,
                   help="record: store frames as lossless PNG (1.6 to 2 times smaller on simulator frames with and without "
                        "sensor noise; about 65 ms of CPU per 1280x720 frame, see docs/sequence-format.md) instead of raw netpbm")
    p.add_argument("--compress-ratio", type=float, metavar="R",
                   help="record with --compress: the compression ratio the disk check counts (an earlier take's "
                        "compression_ratio, 1 to 1000); without it compression counts for nothing in the check")
    p.add_argument("--no-disk-check", action="store_true",
                   help="record: skip measuring the output disk (a short test file) and refusing a rig whose data rate "
                        "it cannot take")
    p.add_argument("--json", action="store_true", help="print one JSON object (stderr: errors only)")
    p.set_defaults(func=cmd_record)


def cmd_record(args: argparse.Namespace) -> int:
    from rig.errors import ConfigError

    if args.action == "validate":
        return _validate(args)
    if args.action == "repair":
        return _repair(args)
    if args.action == "align":
        return _align(args)
    if args.action == "fetch":
        return _fetch(args)
    if args.config is None or args.out is None:
        raise ConfigError("record: needs -c RIG.toml and -o DIR (or: rig record validate|repair DIR)")
    return _record(args)


def _need_dir(args) -> Path:
    from rig.errors import ConfigError

    if args.dir is None:
        raise ConfigError(f"record {args.action}: name the sequence folder")
    if args.dir.exists() and not args.dir.is_dir():
        raise ConfigError(f"{args.dir}: is a file, not a sequence folder")
    if not args.dir.is_dir():
        raise ConfigError(f"{args.dir}: no such sequence folder")
    return args.dir


def _validate(args) -> int:
    from rig.commands._output import emit_json
    from rig.storage.validate import validate

    v = validate(_need_dir(args), check_pixels=args.pixels)
    if args.json:
        emit_json(v.to_dict())
    else:
        d = v.to_dict()
        print(f"{v.root}: {'readable' if v.readable else 'NOT readable'}; {v.sets} sets ({v.complete_sets} complete), "
              f"{d['duration_s']:.1f} s, gaps {v.gaps}, calibrated: {'yes' if v.calibrated else 'no'}")
        for cam, n in v.frames.items():
            print(f"  {cam}: {n} frames, {v.missing[cam]} missing, {v.frames_lost[cam]} lost (gaps in its frame ids)")
        if v.skew_us:
            print(f"  exposure skew (device clocks against the pulses): p50 {v.skew_us['p50']:.0f} us, "
                  f"p99 {v.skew_us['p99']:.0f} us, max {v.skew_us['max']:.0f} us")
        else:
            print("  exposure skew: not measured (it needs two hardware-triggered cameras, recorded with their trigger mode)")
        if v.arrival_spread_us:
            print(f"  arrival spread (when the frames reached this computer, not when they were taken): "
                  f"p50 {v.arrival_spread_us['p50']:.0f} us, p99 {v.arrival_spread_us['p99']:.0f} us, max {v.arrival_spread_us['max']:.0f} us")
        for w in v.warnings:
            print(f"  warning: {w}")
        for e in v.errors[:20]:
            print(f"  error: {e}")
        if len(v.errors) > 20:
            print(f"  ... and {len(v.errors) - 20} more errors")
    if not v.readable:
        print(f"rig: error: {unreadable(v, args.pixels)}", file=sys.stderr)
        return 1
    return 0


def unreadable(v, pixels: bool = False) -> str:
    """What a take that does not validate (rig.storage.validate) is told; `pixels`: validated with
    --pixels, so the repair must decode too to find what validate found."""
    return (f"{v.root}: {len(v.errors)} problem{'s' if len(v.errors) > 1 else ''} (first: {v.errors[0]}); "
            f"`rig record repair{' --pixels' if pixels else ''}` keeps every good set")


def _repair(args) -> int:
    from rig.commands._output import emit_json
    from rig.storage.repair import repair
    from rig.storage.validate import validate

    root = _need_dir(args)
    r = repair(root, check_pixels=args.pixels)
    after = validate(root, check_pixels=args.pixels)  # what is left that a repair of the index cannot mend (a corrupt calibration copy)
    r["readable"] = after.readable
    r["errors"] = after.errors
    if args.json:
        emit_json(r)
    else:
        _print_repair(r)
    if not after.readable:
        print(f"rig: error: {root}: still not readable after the repair: {after.errors[0]}", file=sys.stderr)
        return 1
    return 0


def _print_repair(r: dict) -> None:
    if not r["changed"]:
        print(f"{r['path']}: nothing to repair: {r['kept_sets']} sets, every indexed frame whole")
        return
    print(f"{r['path']}: kept {r['kept_sets']} of {r['sets_before']} sets; dropped {r['dropped_lines']} damaged index lines, "
          f"marked {r['frames_marked_missing']} frames missing")
    for c in r["dropped"][:20]:
        if c["what"] == "line":
            print(f"  line {c['line']}: dropped ({c['reason']})")
        else:
            print(f"  set {c['set']} {c['camera']}: {c['reason']}" + (f" ({c['file']})" if c.get("file") else ""))
    if len(r["dropped"]) > 20:
        print(f"  ... and {len(r['dropped']) - 20} more (all of them with --json)")
    print(f"the original index is kept as {r['backup']}")
    print(f"next: rig record validate {r['path']}")


def _rate(c: dict) -> str:
    if c["rate_ppm"] is None:
        return " (one flash: nominal clock rate)"
    error = c.get("rate_ppm_error")
    return f", clock {c['rate_ppm']:+.0f}" + (f" ± {error:.0f}" if error is not None else "") + " ppm"


def alignment_lines(r: dict) -> list[str]:
    """A line per camera of an alignment report (rig.storage.align.align)."""
    period_ms = 1e3 / r["rate_hz"]
    lines = []
    for name, c in r["cameras"].items():
        if c["problem"]:
            lines.append(f"{name}: NOT aligned: {c['problem']}")
            continue
        lines.append(f"{name}: {c['placed']} of {c['frames']} frames placed ({c['moved']} moved to another set), uncertainty "
                     f"{c['error_periods']:.3f} frame periods ({c['error_periods'] * period_ms:.2f} ms){_rate(c)}, latency {c['latency_ms']:.1f} ms")
    for v in r.get("videos", []):  # card cameras' videos: frame numbers to pulses
        what = f"{v['camera']} {v['file']}" if v["file"] else v["camera"]
        if v["problem"]:
            lines.append(f"{what}: NOT aligned: {v['problem']}")
            continue
        lines.append(f"{what}: frame 0 at trigger {v['trigger_at_frame0']:.3f}, {v['pulses_per_frame']:.5f} pulses per frame, "
                     f"uncertainty {v['error_periods']:.3f} pulse periods ({v['error_frames']:.3f} frames){_rate(v)}")
    return lines


def _align(args) -> int:
    from rig.commands._output import emit_json
    from rig.storage.align import align

    r = align(_need_dir(args), args.camera)
    if args.json:
        emit_json(r)
    else:
        for line in alignment_lines(r):
            print(f"  {line}")
        if r["backup"]:
            print(f"the original index is kept as {r['backup']}")
        print(f"the report is {Path(r['path']) / 'alignment.json'}")
    failed = not_aligned(r, args.dir)
    if failed:
        print(f"rig: error: {failed}", file=sys.stderr)
        return 1
    return 0


def not_aligned(r: dict, root) -> str | None:
    """What an alignment report (rig.storage.align.align) that left a camera or video unaligned is
    told; None when everything was aligned."""
    failed = [(n, c["problem"]) for n, c in r["cameras"].items() if c["problem"]]
    failed += [(v["file"] or v["camera"], v["problem"]) for v in r["videos"] if v["problem"]]
    if not failed:
        return None
    return f"{root}: could not align {', '.join(n for n, _ in failed)}: {failed[0][1]}"


def _fetch(args) -> int:
    from rig.capture.fetch import fetch
    from rig.commands._output import emit_json
    from rig.progress import Notes

    root = _need_dir(args)
    r = fetch(root, args.camera, notes=Notes(quiet=args.json))
    if args.json:
        emit_json(r)
    else:
        for name, c in r["cameras"].items():
            files = c["files"] or []
            done = [f for f in files if f["state"] == "done"]
            size = sum(f["size"] or 0 for f in done) / 1e6
            state = "done" if c["state"] == "done" else "NOT done"
            print(f"  {name}: {state}: {len(done)} of {len(files)} files in the take ({size:.1f} MB)"
                  + (f"; {c['problem']}" if c["problem"] else ""))
    failed = [(n, c["problem"]) for n, c in r["cameras"].items() if c["problem"] or c["state"] != "done"]
    if failed:
        print(f"rig: error: {root}: {failed[0][0]}: {failed[0][1] or 'files left to download'} (run `rig record fetch "
              f"{root}` again once the camera answers)", file=sys.stderr)
        return 1
    return 0


def _stop_on_sigterm(signum, frame) -> None:
    """`kill` (SIGTERM) ends a take like Ctrl-C: every set already written stays valid."""
    raise KeyboardInterrupt


def _record(args) -> int:
    from rig.capture.record import record
    from rig.commands._output import emit_json
    from rig.commands._paths import new_output_folder
    from rig.config import load_config
    from rig.errors import ConfigError
    from rig.progress import Notes, StatusLine, rate

    if args.seconds is None and args.sets is None:
        raise ConfigError("record: give --seconds S or --sets N")
    if (args.seconds is not None and not args.seconds > 0) or (args.sets is not None and args.sets <= 0):
        raise ConfigError("record: --seconds and --sets must be positive")
    if args.compress_ratio is not None and args.compress is None:
        raise ConfigError("record: --compress-ratio counts only with --compress png")
    cfg = load_config(args.config)
    new_output_folder(args.out)  # a take is never written over or into another folder's files
    status = StatusLine(sys.stderr)
    signal.signal(signal.SIGTERM, _stop_on_sigterm)
    result = record(cfg, args.out, seconds=args.seconds, sets=args.sets, status=status, notes=Notes(quiet=args.json),
                    flash=False if args.no_flash else None, codec=args.compress or "raw",
                    disk_check=not args.no_disk_check, compress_ratio=args.compress_ratio)
    status.done()
    d = result.to_dict()
    if args.json:
        emit_json(d)
    else:
        # rates only over a span long enough to mean something (a 3-set take lasts a fraction of a second)
        rates = f"{d['sets_per_s']:.1f} sets/s, {d['mb_per_s']:.1f} MB/s, " if rate(d["sets"], d["seconds"]) is not None else ""
        print(f"recorded {d['sets']} sets ({d['complete_sets']} complete) in {d['seconds']:.1f} s to {result.out}: "
              f"{rates}frames lost {sum(result.frames_lost.values())}")
        if d["compression_ratio"] and d["codec"] != "raw":
            print(f"  {d['codec']}: {d['compression_ratio']:.2f} times smaller than raw, {d['encode_ms_per_frame']} ms of CPU per frame")
        for n, count in result.frames.items():  # per camera
            print(f"  {n}: {count} frames, {result.drops.get(n, 0)} dropped by the camera link")
        for n, c in ((result.media or {}).get("cameras") or {}).items():
            done = [f for f in c["files"] or [] if f["state"] == "done"]
            print(f"  {n}: recorded to its card; {len(done)} of {len(c['files'] or [])} videos downloaded into "
                  f"{result.out / 'media' / n} ({sum(f['size'] or 0 for f in done) / 1e6:.1f} MB)")
        print(f"next: rig record validate {result.out}" + (f"; rig record align {result.out}" if result.flashes else ""))
    for e in result.errors:
        print(f"rig: error: {e}", file=sys.stderr)
    if result.errors:
        return 1
    return 0
