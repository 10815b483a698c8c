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
import json
import socket
from pathlib import Path

import numpy as np

GOPRO_SIZE = (1280, 720)  # a HERO12 streams 720p or 1080p in webcam mode: the smaller one, for N streams on the host
GOPRO_FPS = 15.0  # the emulators render, encode and the backend decodes every stream on this host
MAX_GOPROS = 8


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def gopro_rig(n_gopros: int, width: int, height: int, fps: float) -> dict:
    """The rig's configuration: the simulated rig of 2 + N cameras, its supervision cameras made
    GoPros on loopback emulators (a control port and a stream port each, free on this host)."""
    from rig.sim.rig_config import sim_rig_config

    data = sim_rig_config(n_cameras=2 + n_gopros, width=width, height=height, fps=fps)
    data["rig"]["name"] = f"sim-gopro-{n_gopros}"
    data["sim"].update(led=True, loop_frames=20)
    k = 0
    for cam in data["cameras"]:
        if cam["role"] != "supervision":
            continue
        k += 1
        serial = f"C35013246455{10 + k:02d}"
        cam.update(uri=f"gopro://{serial}@127.0.0.1:{_free_port(socket.SOCK_STREAM)}?port={_free_port(socket.SOCK_DGRAM)}",
                   width=GOPRO_SIZE[0], height=GOPRO_SIZE[1], pixel_format="RGB8", trigger="free", fps=GOPRO_FPS)
        for key in ("sim", "exposure_us", "gain"):
            cam.pop(key, None)
    return data


def alignment_truth(take: Path, cameras: list, starts: dict[str, float]) -> dict[str, dict]:
    """Per GoPro: how many of its frames the aligned index puts on their true pulse, and the largest
    error of their sub-frame offsets (pulse periods). The truth: a GoPro frame's device time is its
    stream's presentation time, frame k showing the simulated instant t0 + k / fps (t0: `starts`,
    by serial); the pulses' simulated times come from the hardware-triggered left camera's frames."""
    from rig.storage.layout import INDEX

    rows = [json.loads(line) for line in (take / INDEX).read_text().splitlines() if line.strip()]
    hw = np.array([(r["trigger"], r["frames"]["left"]["device_ts_ns"]) for r in rows if r["frames"].get("left")], dtype=np.float64)
    ns_per_pulse, at_zero = np.polyfit(hw[:, 0], hw[:, 1], 1)
    out = {}
    for cam in cameras:
        t0 = starts.get(cam.uri.split("//", 1)[1].split("@", 1)[0])
        if t0 is None:
            out[cam.name] = {"frames": 0, "wrong_set": 0, "offset_error_max": None}
            continue
        wrong = n = 0
        worst = 0.0
        for r in rows:
            f = r["frames"].get(cam.name)
            if f is None or f.get("offset") is None:
                continue
            pos = (t0 * 1e9 + f["device_ts_ns"] - at_zero) / ns_per_pulse
            nearest = int(np.floor(pos + 0.5))
            n += 1
            if nearest != r["trigger"]:
                wrong += 1
            else:
                worst = max(worst, abs((pos - nearest) - f["offset"]))
        out[cam.name] = {"frames": n, "wrong_set": wrong, "offset_error_max": worst if n else None}
    return out


def run(args: argparse.Namespace, run_step) -> int:
    """The demo with GoPros; `run_step(argv)` runs one `rig` command in this process (echoed), so the
    emulators this process serves answer it."""
    from rig.sim.clock import SIM_EPOCH_NS
    from rig.config import dump_config, load_config, parse_config
    from rig.commands._demo_disk import check_space, mb, written
    from rig.commands.record import alignment_lines
    from simulator.gopro.scene import scene_emulators, stream_start

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

    emulators = scene_emulators(cfg, SIM_EPOCH_NS)
    take = out / "take"
    try:
        print(f"2/5  GoPro emulators serving the Open GoPro API: {', '.join(c.uri for c in gopros)}")
        print(f"3/5  recording {args.seconds:g} s: the GoPros grouped live by arrival time, the LED flashed twice")
        rec = run_step(["record", "-c", str(rig_file), "-o", str(take), "--seconds", str(args.seconds)])
        starts = {e.serial: stream_start(e) for e in emulators}
    finally:
        for e in emulators:
            e.stop()
    print(f"     {rec['sets']} sets, frames {', '.join(f'{k} {v}' for k, v in rec['frames'].items())}; flashes {rec['flashes']}"
          + (f"; errors: {'; '.join(rec['errors'])}" if rec["errors"] else ""))

    print("4/5  aligning the GoPros to the trigger pulses by the LED flashes")
    try:
        al = run_step(["record", "align", str(take)])
    except Exception as exc:  # noqa: BLE001 - said, and the take is kept as recorded
        print(f"     NOT aligned: {exc}")
        al = None
    period_ms = 1e3 / cfg.trigger.rate_hz
    if al is not None:
        for line in alignment_lines(al):
            print(f"     {line}")

    val = run_step(["record", "validate", str(take)])
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
