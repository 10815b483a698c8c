"""`rig demo --gopro [N]`: the simulated rig's two sources, hardware-triggered by the emulated board,
with N GoPros as its supervision cameras: emulators (simulator/gopro) that serve the Open GoPro
HTTP API on loopback and stream MPEG-TS webcam video of the simulated scene, reached through the
real gopro:// backend.

1. the rig: two triggered sources and N free-running GoPros standing where the supervision cameras
   stand, the trigger board's LED hanging above the stage;
2. the GoPros' emulators start (each films the scene from its camera's place);
3. a take is recorded: the GoPros' frames are grouped live by arrival time, and the board flashes its
   LED twice (`rig record` does this for rigs with free-running cameras);
4. `rig record align` puts every GoPro frame on the trigger pulses by the flashes it saw;
5. the take is validated, and the alignment is compared with the simulator's truth: each GoPro
   frame's true pulse and sub-frame offset, known from when its stream began.
"""
from __future__ import annotations

import argparse
from pathlib import Path


def run(args: argparse.Namespace) -> int:
    from rig.commands import _demo_steps as step
    from rig.commands.record import alignment_lines
    from rig.config import dump_config, load_config, parse_config
    from rig.demo.disk import check_space, mb, written
    from rig.demo.gopro import GOPRO_FPS, GOPRO_SIZE, alignment_truth, gopro_emulators, gopro_rig, stream_starts

    out: Path = args.out
    n = args.gopro
    data = gopro_rig(n, args.width, args.height, 30.0)
    frame_src = args.width * args.height * 3
    frame_gopro = GOPRO_SIZE[0] * GOPRO_SIZE[1] * 3
    estimate = int((args.seconds + 1) * (30.0 * 2 * frame_src + GOPRO_FPS * n * frame_gopro))
    check_space(out, estimate)
    out.mkdir(parents=True, exist_ok=True)
    rig_file = out / "rig.toml"
    rig_file.write_text(dump_config(parse_config(data)))
    cfg = load_config(rig_file, check_calibration=False)
    gopros = [c for c in cfg.cameras if c.scheme == "gopro"]
    print(f"1/5  simulated rig: left and right at {args.width}x{args.height}, hardware-triggered by the emulated board at 30 Hz; "
          f"{n} GoPro{'s' if n > 1 else ''} ({', '.join(c.name for c in gopros)}) free-running at {GOPRO_SIZE[0]}x{GOPRO_SIZE[1]}, "
          f"{GOPRO_FPS:g} fps; the board's LED above the stage  ->  {rig_file}")
    print(f"     the demo writes about {mb(estimate)} into {out}")

    take = out / "take"
    with gopro_emulators(cfg) as emulators:  # served by this process: the record step runs in it
        print(f"2/5  GoPro emulators serving the Open GoPro API: {', '.join(c.uri for c in gopros)}")
        print(f"3/5  recording {args.seconds:g} s: the GoPros grouped live by arrival time, the LED flashed twice")
        rec = step.record(rig_file, take, args.seconds)
        starts = stream_starts(emulators)
    print(f"     {rec['sets']} sets, frames {', '.join(f'{k} {v}' for k, v in rec['frames'].items())}; flashes {rec['flashes']}"
          + (f"; errors: {'; '.join(rec['errors'])}" if rec["errors"] else ""))

    print("4/5  aligning the GoPros to the trigger pulses by the LED flashes")
    try:
        al = step.align(take)
    except Exception as exc:  # noqa: BLE001 - said, and the take is kept as recorded
        print(f"     NOT aligned: {exc}")
        al = None
    period_ms = 1e3 / cfg.trigger.rate_hz
    if al is not None:
        for line in alignment_lines(al):
            print(f"     {line}")

    val = step.validate(take)
    print(f"5/5  validated: {'readable' if val['readable'] else 'NOT readable'}, {val['sets']} sets")
    ok = bool(val["readable"]) and al is not None and not any(c["problem"] for c in al["cameras"].values())
    if al is not None:
        truth = alignment_truth(take, gopros, starts)
        for name, t in truth.items():
            err = "-" if t["offset_error_max"] is None else f"{t['offset_error_max']:.3f} periods ({t['offset_error_max'] * period_ms:.2f} ms)"
            print(f"     against the simulator's truth: {name}: {t['frames']} frames, {t['wrong_set']} in the wrong set, "
                  f"offset error at most {err}")
            ok = ok and t["frames"] > 0 and t["wrong_set"] == 0
    print(f"\nthe take: {take}/  (index.jsonl with each GoPro frame's pulse and offset; the index before alignment kept beside it)")
    print(f"disk: {mb(written(out))} written into {out}")
    print("next: on a real rig, calibrate the GoPros with the sources (`rig calibrate capture`, the board in view of every "
          "camera) and train on such takes (`rig train`); docs/sequence-format.md says how aligned frames are stored")
    return 0 if ok else 1
