"""`rig calibrate`: printable boards, calibration from images, capture of calibration views, report, exports."""
from __future__ import annotations

import argparse
from pathlib import Path

EXPORT_FORMATS = ("opencv", "easymocap", "anipose", "nerfstudio", "colmap")


def register(subparsers) -> None:
    p = subparsers.add_parser("calibrate", help="calibrate the rig with a ChArUco or chessboard board",
                              description="Calibrate the rig's cameras (intrinsics, stereo pair, all cameras in the left camera's frame).")
    sub = p.add_subparsers(dest="calibrate_command", metavar="SUBCOMMAND")
    sub.required = True

    b = sub.add_parser("board", help="render a printable board at true size",
                       description="Render the board a BOARD.toml describes as a PNG that prints at true size.")
    b.add_argument("board", metavar="BOARD.toml", help="board description (type = chessboard | charuco, ...)")
    b.add_argument("-o", "--output", required=True, metavar="board.png", help="PNG file to write")
    b.add_argument("--dpi", type=float, default=300.0, help="printer resolution (default 300)")
    b.add_argument("--json", action="store_true", help="print one JSON object with the image size")
    b.set_defaults(func=cmd_board)

    r = sub.add_parser("run", help="calibrate from images on disk",
                       description="Calibrate from images DIR/CAMNAME/*.png|jpg (same file stem = same instant) "
                                   "or leftNN/rightNN pairs in one folder.")
    r.add_argument("--images", required=True, metavar="DIR", help="image folder")
    r.add_argument("--board", required=True, metavar="BOARD.toml", help="board description")
    r.add_argument("-o", "--output", required=True, metavar="calib.json", help="rig calibration file to write")
    r.add_argument("--left", metavar="NAME", help="camera at the origin (default: 'left', else the first)")
    r.add_argument("--right", metavar="NAME", help="other camera of the stereo pair (default: 'right', else the last)")
    r.add_argument("--outlier-px", type=float, default=1.0, help="reject views whose RMS exceeds max(this, 5 x median) (default 1.0)")
    r.add_argument("--json", action="store_true", help="print one JSON object with the results")
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("capture", help="collect calibration views from the rig",
                       description="Show the board to the rig; views that add coverage are kept as DIR/CAMNAME/NNNN.png for `rig calibrate run`.")
    c.add_argument("-c", "--config", required=True, metavar="FILE", help="rig configuration (TOML)")
    c.add_argument("--board", required=True, metavar="BOARD.toml", help="board description")
    c.add_argument("-o", "--output", required=True, metavar="DIR", help="folder for the views")
    c.add_argument("--views", type=int, default=40, help="stop after keeping this many views (default 40)")
    c.add_argument("--max-frames", type=int, default=2000, help="stop after looking at this many frame sets (default 2000)")
    c.add_argument("--interval", type=float, default=0.0, help="seconds between frame sets (default 0: as fast as frames come)")
    c.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for a camera's frame (default 5)")
    c.add_argument("--json", action="store_true", help="print one JSON object with what was kept")
    c.set_defaults(func=cmd_capture)

    rp = sub.add_parser("report", help="print a calibration's quality report",
                        description="Reprojection errors, coverage, stereo epipolar error and warnings of a calibration file.")
    rp.add_argument("calibration", metavar="calib.json")
    rp.add_argument("--json", action="store_true", help="print one JSON object")
    rp.set_defaults(func=cmd_report)

    e = sub.add_parser("export", help="write a calibration in another tool's format",
                       description="Export to OpenCV YAML (+ rectification maps), EasyMocap, aniposelib TOML, nerfstudio transforms.json or COLMAP text.")
    e.add_argument("calibration", metavar="calib.json")
    e.add_argument("--format", required=True, choices=EXPORT_FORMATS)
    e.add_argument("-o", "--output", required=True, metavar="OUT", help="folder to write into")
    e.add_argument("--json", action="store_true", help="print one JSON object with the files written")
    e.set_defaults(func=cmd_export)


def _status():
    from rig.progress import StatusLine

    return StatusLine()


def cmd_board(args: argparse.Namespace) -> int:
    from calibration.boards import load_board
    from calibration.printable import write_board
    from rig.commands._output import emit_json

    board = load_board(args.board)
    info = write_board(board, args.output, args.dpi)
    if args.json:
        emit_json(info)
    else:
        print(f"{info['path']}: {info['width_px']}x{info['height_px']} px, prints at {info['width_mm']} x {info['height_mm']} mm "
              f"at {info['dpi']:g} dpi (squares {info['square_mm']} mm); print at 100% scale")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from calibration.boards import load_board
    from calibration.images import detect_images, find_images
    from calibration.report import format_report
    from calibration.solve import Options, calibrate_rig
    from rig.commands._output import emit_json

    board = load_board(args.board)
    images = find_images(args.images)
    status = _status()
    detections = detect_images(images, board, progress=lambda i, n: status.update(f"detecting the board: {i}/{n} images"))
    status.done()
    opts = Options(left=args.left or images.roles.get("left"), right=args.right or images.roles.get("right"), outlier_px=args.outlier_px)
    result = calibrate_rig(detections, board, opts, progress=lambda s: status.update(s, force=True))
    status.done()
    rig = result.rig
    rig.meta["images"] = str(Path(args.images))
    rig.save(args.output)
    meta = rig.meta
    if args.json:
        emit_json({
            "output": str(args.output),
            "cameras": rig.names,
            "views_used": meta["views_used"],
            "views_found": {c: len(detections.corners[c]) for c in rig.names},
            "images": detections.images_seen,
            "rms_px": meta["rms_px"],
            "stereo_rms_px": meta["stereo_rms_px"],
            "baseline_m": meta["baseline_m"],
            "epipolar_rms_px": (meta["report"]["stereo"] or {}).get("epipolar_rms_px"),
            "stereo_pair": meta["stereo_pair"],
            "intrinsics": {c.name: {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "dist": c.dist.tolist()} for c in rig.cameras},
            "rejected": meta["rejected"],
            "warnings": meta["report"]["warnings"],
        })
    else:
        print(format_report(rig))
        print(f"\nwrote {args.output}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from calibration.camera import RigCalibration
    from calibration.report import format_report
    from rig.commands._output import emit_json

    rig = RigCalibration.load(args.calibration)
    if args.json:
        out = {"calibration": str(args.calibration), "cameras": [c.to_dict() for c in rig.cameras]}
        out.update({k: v for k, v in rig.meta.items()})
        emit_json(out)
    else:
        print(format_report(rig))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from calibration.camera import RigCalibration
    from calibration.export import export
    from rig.commands._output import emit_json

    rig = RigCalibration.load(args.calibration)
    files = export(rig, args.format, args.output)
    if args.json:
        emit_json({"format": args.format, "files": [str(f) for f in files]})
    else:
        for f in files:
            print(f)
    return 0


def cmd_capture(args: argparse.Namespace) -> int:
    """Pull synchronised frame sets from the rig, keep those that add coverage, write DIR/CAMNAME/NNNN.png."""
    import dataclasses
    import json
    import time

    import cv2

    from calibration.boards import load_board
    from calibration.detect import make_detector, to_gray
    from calibration.selection import ViewSelector
    from rig.cameras import open_camera
    from rig.commands._output import emit_json
    from rig.config import load_config
    from rig.errors import ConfigError, StorageError

    cfg = load_config(args.config)
    board = load_board(args.board)
    if args.views < 1 or args.max_frames < 1:
        raise ConfigError("--views and --max-frames must be at least 1")
    out = Path(args.output)
    if out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out}: folder is not empty; views are numbered from 0000, choose a new folder")
    detector = make_detector(board)
    # Calibration views are stills: cameras that take triggers are fired by software so that every
    # camera exposes the same instant without the trigger board; free-running ones are paired by time.
    settings = []
    for c in cfg.cameras:
        s = dataclasses.replace(c, trigger="software" if c.trigger in ("hardware", "software") else "free")
        if hasattr(c, "rig"):
            s.rig = c.rig  # the whole rig, which simulated cameras need to show the shared scene
        settings.append(s)
    cameras = []
    status = _status()
    kept: list[dict] = []
    looked = 0
    try:
        roles = {c.role: c.name for c in cfg.cameras if c.role in ("left", "right")}
        for s in settings:
            cameras.append(open_camera(s))
        for cam in cameras:
            cam.start()
        selector = ViewSelector({s.name: (s.width, s.height) for s in settings})
        while looked < args.max_frames and len(kept) < args.views:
            images = _grab_set(cameras, args.timeout)
            looked += 1
            detections = {name: detector(img) for name, img in images.items()}
            verdict = selector.consider(detections)
            if verdict.keep:
                index = len(kept)
                if index == 0 and roles:  # tells `rig calibrate run` which cameras are the stereo pair
                    out.mkdir(parents=True, exist_ok=True)
                    (out / "roles.json").write_text(json.dumps(roles) + "\n")
                for name, img in images.items():
                    path = out / name / f"{index:04d}.png"
                    path.parent.mkdir(parents=True, exist_ok=True)
                    if not cv2.imwrite(str(path), _to_bgr(img, to_gray)):
                        raise StorageError(f"{path}: could not write the image (disk full or no permission?)")
                kept.append({"view": f"{index:04d}", "cameras": verdict.cameras, "reason": verdict.reason})
            status.update(f"looked at {looked} views, kept {len(kept)}/{args.views}")
            if args.interval > 0:
                time.sleep(args.interval)
    finally:
        for cam in cameras:
            try:
                cam.stop()
                cam.close()
            except Exception:  # closing must not hide the error that stopped the capture
                pass
    status.done()
    summary = {"output": str(out), "views_kept": len(kept), "views_looked_at": looked, "coverage": selector.coverage(), "kept": kept}
    if args.json:
        emit_json(summary)
    else:
        for k in kept:
            print(f"{k['view']}: {k['reason']} (board seen by {', '.join(k['cameras'])})")
        cov = ", ".join(f"{n} {v * 100:.0f}%" for n, v in summary["coverage"].items())
        print(f"kept {len(kept)} of {looked} views in {out}; coverage {cov}")
        print(f"next: rig calibrate run --images {out} --board {args.board} -o calib.json")
    return 0


def _to_bgr(image, to_gray):
    """PNG-ready pixels: mono stays mono, RGB becomes OpenCV's BGR order."""
    import cv2
    import numpy as np

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if img.dtype != np.uint8 and img.dtype != np.uint16:
        return to_gray(img)
    return img


def _grab_set(cameras, timeout: float) -> dict:
    """One synchronised set of images: software-triggered cameras fire together; free-running cameras
    give their newest frame."""
    from rig.errors import CameraTimeout

    triggered = [c for c in cameras if c.settings.trigger == "software"]
    for cam in triggered:
        cam.software_trigger()
    images = {}
    for cam in cameras:
        if cam.settings.trigger == "software":
            images[cam.name] = cam.get_frame(timeout).image
        else:
            frame = cam.get_frame(timeout)
            while True:  # drop what queued up while we were detecting: the newest frame is the present
                try:
                    frame = cam.get_frame(0.0)
                except CameraTimeout:
                    break
            images[cam.name] = frame.image
    return images
