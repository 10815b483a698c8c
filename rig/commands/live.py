"""`rig live`: run the rig (or replay a take) through the model and serve the novel view to browsers."""
from __future__ import annotations

import argparse
import secrets
import signal
import sys
import threading
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("live", help="serve the live novel view of the rig to browsers (and MJPEG, snapshots, a video file)",
                       description="Run the rig (or replay a recorded take) through the model and serve the novel view at "
                                   "http://HOST:PORT/: a page with a slider between the two sources, a button per calibrated "
                                   "camera, orbit and zoom, and live figures; also /status, /snapshot.png, /mjpeg. Routes, wire "
                                   "format and access rules: docs/live.md.")
    p.add_argument("-c", "--config", type=Path, required=True, help="rig configuration (TOML): cameras, trigger, [live] address")
    p.add_argument("--model", type=Path, help="exported model (rig model export); default: the shipped trained model")
    p.add_argument("--calibration", type=Path, help="calibration file (default: the config's rig.calibration)")
    p.add_argument("--host", help="address to bind (default: the config's live.host, 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default: the config's live.port; 0 = any free port)")
    p.add_argument("--token", help="access token (a non-loopback address always needs one: generated and printed if not given)")
    p.add_argument("--replay", type=Path, metavar="SEQUENCE", help="replay a recorded take at its recorded rate (looped) instead of running the cameras")
    p.add_argument("--record-output", type=Path, metavar="FILE.mp4", help="also write the rendered view at --record-view to a video file")
    p.add_argument("--record-view", default="0.5", metavar="t|CAMERA", help="the viewpoint --record-output records: 0..1 from left to right, or a camera name (default 0.5)")
    p.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C)")
    p.add_argument("--threads", type=int, help="ONNX Runtime threads per model run (default: OMP_NUM_THREADS where it is set, else all cores)")
    p.add_argument("--providers", nargs="+", help="ONNX Runtime execution providers, best first (default: TensorRT, CUDA, CPU as installed); "
                                                   "CUDAExecutionProvider and TensorrtExecutionProvider need onnxruntime-gpu (docs/live.md, GPU)")
    p.add_argument("--device", default="cpu", metavar="cpu|cuda[:N]",
                   help="cpu (default): the exported ONNX model in ONNX Runtime, torch-free; cuda: the checkpoint behind the model "
                        "in torch on the GPU, stage 1 and the view as CUDA graphs (eager frames while they compile)")
    p.add_argument("--size", choices=("paper", "preview", "test"),
                   help="with --device cuda: the size preset the model runs at (default paper: 512x288 / 1024x576 -> 1280x720)")
    p.add_argument("--no-compile", dest="compile", action="store_false",
                   help="with --device cuda: eager only, no CUDA graphs (no compile time; slower)")
    p.add_argument("--jpeg-quality", type=int, default=85, help="JPEG quality of the served frames (default 85)")
    p.add_argument("--json", action="store_true", help="print one JSON object when the server stops (stderr: notes and errors)")
    p.set_defaults(func=cmd_live)


def view_message(text: str) -> dict:
    """--record-view as a viewpoint message: a number is a position on the arc, else a camera."""
    try:
        return {"type": "viewpoint", "t": float(text)}
    except ValueError:
        return {"type": "viewpoint", "preset": text}


def cmd_live(args: argparse.Namespace) -> int:
    from rig.commands._output import emit_json
    from rig.config import load_config
    from rig.errors import ConfigError
    from rig.live.app import LiveApp
    from rig.progress import Notes

    if args.seconds is not None and not args.seconds > 0:
        raise ConfigError("live: --seconds must be positive")
    if not 1 <= args.jpeg_quality <= 100:
        raise ConfigError(f"live: --jpeg-quality must be between 1 and 100, got {args.jpeg_quality}")
    cfg = load_config(args.config, check_calibration=args.calibration is None)
    host = args.host or cfg.live.host
    port = cfg.live.port if args.port is None else args.port
    if not 0 <= port < 65536:
        raise ConfigError(f"live: --port must be between 0 and 65535, got {port}")
    token = args.token
    if token is not None and len(token) < 8:
        raise ConfigError("live: --token must be at least 8 characters")
    from rig.http_access import is_loopback_name

    if token is None and not is_loopback_name(host):
        token = secrets.token_urlsafe(18)  # a non-loopback bind is never open
    from rig.errors import RigError
    from rig.http_access import bind_socket

    # The address first: one taken or not of this host is one line before the cameras and the model open.
    try:
        sock = bind_socket(host, port, "live")
    except RigError as exc:
        raise ConfigError(str(exc)) from None
    notes = Notes(quiet=False)
    try:
        app = LiveApp.build(cfg, model=args.model, calibration=args.calibration, replay=args.replay,
                            record_output=args.record_output, record_view=view_message(args.record_view),
                            threads=args.threads, providers=args.providers, jpeg_quality=args.jpeg_quality, notes=notes,
                            device=args.device, size=args.size, compile=args.compile)
    except BaseException:
        sock.close()
        raise
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with app:
        server = app.serve(host, port, token, sock=sock)
        where = f"http://{host if ':' not in host else '[' + host + ']'}:{server.port}/"
        print(f"live: serving {where}" + (f"?token={token}" if token else "") + "  (Ctrl-C stops)", file=sys.stderr, flush=True)
        if token and args.token is None:
            print(f"live: access token {token} (give it as ?token=, a Bearer header, or --token to choose one)", file=sys.stderr, flush=True)
        try:
            stop.wait(args.seconds)
        except KeyboardInterrupt:
            pass
        server.stop()
    summary = app.summary()  # after the engine stopped: every frame the video got is counted
    summary["url"] = where
    if args.json:
        emit_json(summary)
    else:
        s = summary
        print(f"live: {s['sets_in']} frame sets in, {s['stage1_runs']} stage-1 runs, {s['view_runs']} views rendered, "
              f"{s['sets_dropped']} sets dropped while the model was busy")
        if summary.get("record_output"):
            print(f"live: wrote {summary['record_output']['frames']} frames to {summary['record_output']['path']}")
    return 0
