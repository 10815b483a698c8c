"""`rig calibrate`: printable boards, calibration from images, capture of calibration views, report, exports."""
from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path

EXPORT_FORMATS = ("opencv", "easymocap", "anipose", "nerfstudio", "colmap")


def register(subparsers) -> None:
    p = subparsers.add_parser("calibrate", help="calibrate the rig with a ChArUco or chessboard board",
                              description="Calibrate the rig's cameras (intrinsics, stereo pair, all cameras in the left camera's frame).")
    sub = p.add_subparsers(dest="calibrate_command", metavar="SUBCOMMAND")
    sub.required = True
    for add in (_board_parser, _run_parser, _intrinsics_parser, _capture_parser, _report_parser, _export_parser):
        add(sub)


def _board_parser(sub) -> None:
    """`rig calibrate board`."""
    b = sub.add_parser("board", help="render a printable board at true size",
                       description="Render the board a BOARD.toml describes as a PNG that prints at true size.")
    b.add_argument("board", metavar="BOARD.toml", help="board description (type = chessboard | charuco, ...)")
    b.add_argument("-o", "--output", required=True, metavar="board.png", help="PNG file to write")
    b.add_argument("--dpi", type=float, default=300.0, help="printer resolution (default 300)")
    b.add_argument("--json", action="store_true", help="print one JSON object with the image size")
    b.set_defaults(func=cmd_board)


def _run_parser(sub) -> None:
    """`rig calibrate run`."""
    r = sub.add_parser("run", help="calibrate from images on disk",
                       description="Calibrate from images DIR/CAMNAME/*.png|jpg (same file stem = same instant; when no two cameras share a stem, the same number ending the name, as in CAM-TIME-N.jpg) "
                                   "or leftNN/rightNN pairs in one folder.")
    r.add_argument("--images", required=True, metavar="DIR", help="image folder")
    r.add_argument("--board", required=True, metavar="BOARD.toml", help="board description")
    r.add_argument("-o", "--output", required=True, metavar="calib.json", help="rig calibration file to write")
    r.add_argument("-c", "--config", metavar="RIG.toml", help="the rig's configuration: the stereo pair is its left and right cameras")
    r.add_argument("--left", metavar="NAME", help="camera at the origin (default: the config's left camera, 'left', else the first)")
    r.add_argument("--right", metavar="NAME", help="other camera of the stereo pair (default: 'right', else the last)")
    _lens_options(r)
    r.add_argument("--intrinsics", metavar="FILE",
                   help="hold these cameras' intrinsics fixed while the rig is solved: a `rig calibrate intrinsics` file, "
                        "a calibration file, or an anipose calibration TOML")
    r.add_argument("--prior-sigma", metavar="SPEC",
                   help="with --intrinsics: use the given intrinsics as priors, not held fixed: each term named may move "
                        "from its given value at a cost of ((change / SIGMA))^2 against the corners' squared errors in "
                        "their measured noise; SPEC as f=1%%,c=8,dist=0.02 (f c fx fy cx cy in px or %% of the focal "
                        "length; k1 k2 k3 k4 p1 p2, or dist for all); terms not named stay held")
    r.add_argument("--hold", action="append", metavar="NAME",
                   help="with --intrinsics: hold only this camera (repeatable; default: every camera the file has)")
    r.add_argument("--free-intrinsics", action="store_true",
                   help="let the joint adjustment move every fitted lens term freely (by default each camera's own lens fit "
                        "is a prior there, weighted by how well its views measured it)")
    r.add_argument("--offset", action="append", metavar="CAMERA=N",
                   help="pair CAMERA's images with the instants N later (negative: earlier) than their names say, as cam_1=+1 "
                        "(repeatable); such a camera is not checked for being out of step")
    r.add_argument("--auto-offset", action="store_true",
                   help="apply the offset the pairing check finds for a camera out of step (by default the run stops and names it)")
    r.add_argument("--force", action="store_true", help="replace an existing calibration file")
    r.add_argument("--json", action="store_true", help="print one JSON object with the results")
    r.set_defaults(func=cmd_run)


def _intrinsics_parser(sub) -> None:
    """`rig calibrate intrinsics`."""
    i = sub.add_parser("intrinsics", help="calibrate each camera's lens from its own board session",
                       description="Each camera's intrinsics from its own close-up board views: DIR/CAMNAME/*.png|jpg, or one "
                                   "camera's images directly in DIR (named after DIR). Views that do not fit are rejected with one "
                                   "reason; the focal length's spread over subsets of the views, the board's coverage and a verdict "
                                   "(good / weak / unusable) are reported per camera.")
    i.add_argument("--images", required=True, metavar="DIR", help="image folder")
    i.add_argument("--board", required=True, metavar="BOARD.toml", help="board description")
    i.add_argument("-o", "--output", required=True, metavar="intrinsics.json", help="file to write")
    i.add_argument("--camera", action="append", metavar="NAME", help="only this camera (repeatable; default: every camera)")
    _lens_options(i)
    i.add_argument("--force", action="store_true", help="replace an existing file")
    i.add_argument("--json", action="store_true", help="print one JSON object with the results")
    i.set_defaults(func=cmd_intrinsics)


def _capture_parser(sub) -> None:
    """`rig calibrate capture`."""
    from rig.capture.calibration_views import MAX_FRAMES, TIMEOUT_S

    c = sub.add_parser("capture", help="collect calibration views from the rig",
                       description="Show the board to the rig; views that add coverage are kept as DIR/CAMNAME/NNNN.png for `rig calibrate run`.")
    c.add_argument("-c", "--config", required=True, metavar="FILE", help="rig configuration (TOML)")
    c.add_argument("--board", required=True, metavar="BOARD.toml", help="board description")
    c.add_argument("-o", "--output", required=True, metavar="DIR", help="folder for the views")
    c.add_argument("--views", type=int, default=40, help="stop after keeping this many views (default 40)")
    c.add_argument("--max-frames", type=int, default=MAX_FRAMES, help=f"stop after looking at this many frame sets (default {MAX_FRAMES})")
    c.add_argument("--interval", type=float, default=0.0, help="seconds between frame sets (default 0: as fast as frames come)")
    c.add_argument("--timeout", type=float, default=TIMEOUT_S, help=f"seconds to wait for a camera's frame (default {TIMEOUT_S:g})")
    c.add_argument("--json", action="store_true", help="print one JSON object with what was kept")
    c.set_defaults(func=cmd_capture)


def _report_parser(sub) -> None:
    """`rig calibrate report`."""
    rp = sub.add_parser("report", help="print a calibration's quality report",
                        description="Reprojection errors, coverage, stereo epipolar error and warnings of a calibration file.")
    rp.add_argument("calibration", metavar="calib.json")
    rp.add_argument("--json", action="store_true", help="print one JSON object")
    rp.set_defaults(func=cmd_report)


def _export_parser(sub) -> None:
    """`rig calibrate export`."""
    e = sub.add_parser("export", help="write a calibration in another tool's format",
                       description="Export to OpenCV YAML (+ rectification maps), EasyMocap, aniposelib TOML, nerfstudio transforms.json "
                                   "or COLMAP text. nerfstudio (and COLMAP, when a source is named) also get OUT/images/CAMNAME.png, one "
                                   "image per camera at one instant: a set of a recorded take (--take), or a calibration view (--images; "
                                   "by default the views the calibration was made from).")
    e.add_argument("calibration", metavar="calib.json")
    e.add_argument("--format", required=True, choices=EXPORT_FORMATS)
    e.add_argument("-o", "--output", required=True, metavar="OUT", help="folder to write into")
    src = e.add_mutually_exclusive_group()
    src.add_argument("--take", metavar="TAKE", help="images from this recorded take (`rig record -o TAKE`)")
    src.add_argument("--images", metavar="DIR", help="images from these calibration views (DIR/CAMNAME/NNNN.png)")
    e.add_argument("--set", type=int, metavar="N", help="with --take: the set to use (default: the first set every camera has a frame in)")
    e.add_argument("--view", metavar="NNNN", help="with --images: the view to use (default: the first view every camera has)")
    e.add_argument("--json", action="store_true", help="print one JSON object with the files written")
    e.set_defaults(func=cmd_export)


def _lens_options(p) -> None:
    """The lens model's options, the same for `run` and `intrinsics`."""
    p.add_argument("--outlier-px", type=float, default=1.0,
                   help="reject views whose RMS exceeds max(this, 5 x the other views' median) (default 1.0)")
    p.add_argument("--k3", choices=("auto", "hold", "fit"), default="auto",
                   help="third radial term: hold it at 0 (ordinary lenses, under ~90 degrees across: it is poorly observable "
                        "and fitted values are noise), fit it (wide-angle lenses), or auto: fit it from 10 views per camera (default)")
    p.add_argument("--fix-aspect", action="store_true", help="hold fy = fx (square pixels): for weak data from an ordinary camera")
    p.add_argument("--fix-principal-point", action="store_true",
                   help="hold the principal point at the image centre: for weak data (a board in few parts of the image)")
    p.add_argument("--tangential", choices=("auto", "hold", "fit"), default="auto",
                   help="tangential terms p1 p2: hold them at 0 (lenses centred on the sensor), fit them, or auto: "
                        "fit them from 10 views per camera (default)")
    p.add_argument("--fisheye", action="append", nargs="?", const="*", metavar="NAME",
                   help="fit OpenCV's fisheye lens model (k1..k4; wide lenses such as GoPros') to this camera, or to every camera "
                        "when no name is given (repeatable; default: the pinhole model with k1 k2 p1 p2 k3; with the fisheye model --k3 "
                        "holds or fits k3 and k4 together)")


def cmd_board(args: argparse.Namespace) -> int:
    from calibration.boards import load_board
    from calibration.printable import write_board
    from rig.commands._output import emit_json
    from rig.commands._paths import output_file

    board = load_board(args.board)
    output_file(args.output)
    try:
        info = write_board(board, args.output, args.dpi)
    except OSError as exc:
        raise _write_failed(args.output, exc, "the board image") from None
    if args.json:
        emit_json(info)
    else:
        print(f"{info['path']}: {info['width_px']}x{info['height_px']} px, prints at {info['width_mm']} x {info['height_mm']} mm "
              f"at {info['dpi']:g} dpi (squares {info['square_mm']} mm); print at 100% scale")
    return 0


def _write_failed(path, exc: OSError, what: str):
    from rig.errors import StorageError

    return StorageError(f"{path}: could not write {what} ({exc.strerror or exc})")


def cmd_run(args: argparse.Namespace) -> int:
    from calibration.report import format_report
    from rig.calibrate.run import UnusableCalibration, calibrate_images, run_inputs
    from rig.commands._output import emit_json

    inputs = run_inputs(args.images, args.board, _lens(args), config=args.config, left=args.left, right=args.right,
                        intrinsics=args.intrinsics, hold=args.hold, prior_sigma=args.prior_sigma, offsets=args.offset,
                        auto_offset=args.auto_offset, free_intrinsics=args.free_intrinsics)
    output = _checked_output(args)
    try:
        result = calibrate_images(inputs, args.output)
    except UnusableCalibration as exc:
        if not args.json:
            print(format_report(exc.rig))
        raise
    if args.json:
        emit_json(result.summary())
    else:
        print(format_report(result.rig))
        if result.written == output:
            print(f"\nwrote {output}")
        elif result.written is None:
            print(json.dumps(result.rig.to_dict(), indent=2))
    failed = result.write_error()
    if failed is not None:
        raise failed
    return 0


def _lens(args: argparse.Namespace):
    """The lens flags of `run` and `intrinsics`."""
    from rig.calibrate.lens import LensChoices

    return LensChoices(outlier_px=args.outlier_px, k3=args.k3, tangential=args.tangential, square_pixels=args.fix_aspect,
                       centred=args.fix_principal_point, fisheye=tuple(args.fisheye or ()))


def _checked_output(args: argparse.Namespace) -> Path:
    """The output file, checked before the detection and the solve, which take minutes."""
    from rig.commands._paths import output_file
    from rig.errors import ConfigError

    if Path(args.output).is_file() and not args.force:
        raise ConfigError(f"{args.output}: already exists; choose a new name, or replace it with --force (nothing was overwritten)")
    return output_file(args.output)


def cmd_intrinsics(args: argparse.Namespace) -> int:
    from rig.calibrate.intrinsics import calibrate_lenses, intrinsics_inputs
    from rig.commands._output import emit_json

    inputs = intrinsics_inputs(args.images, args.board, _lens(args), args.camera)
    output = _checked_output(args)
    result = calibrate_lenses(inputs, output)
    if args.json:
        emit_json({"output": str(output), **result.doc})
        return 0
    cams = result.doc["cameras"]
    for name, r in result.results.items():
        d = cams[name]
        spread = "not measured" if d["focal_spread_pct"] is None else f"{d['focal_spread_pct']:.2f} %"
        print(f"{name}: {'fisheye ' if r.model == 'fisheye' else ''}fx {d['fx']:.1f} fy {d['fy']:.1f} cx {d['cx']:.1f} cy {d['cy']:.1f}  RMS {d['rms_px']:.3f} px  "
              f"views {d['views_used']}/{d['views_found']} of {result.detections.images_seen.get(name)} images  focal spread {spread}  "
              f"coverage {100 * d['coverage']:.0f} %  -> {r.verdict}")
        for reason in r.reasons:
            print(f"  {r.verdict}: {reason}")
        for rej in r.rejected:
            print(f"  rejected {rej.view}: {rej.reason}")
        for view in d["not_found"]:
            print(f"  rejected {view}: the board was not found in the image")
    for name, why in result.failed.items():
        print(f"{name}: unusable: {why}")
    print(f"\nwrote {output}")
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
    from calibration.export import IMAGE_FORMATS, export
    from rig.commands._output import emit_json
    from rig.commands._paths import output_folder
    from rig.errors import ConfigError

    rig = RigCalibration.load(args.calibration)
    if (args.take or args.images) and args.format not in IMAGE_FORMATS:
        raise ConfigError(f"--take and --images give the images of a {' or '.join(IMAGE_FORMATS)} export, not of {args.format}")
    if args.set is not None and not args.take:
        raise ConfigError("--set chooses a set of a take: give --take TAKE too")
    if args.view is not None and args.take:
        raise ConfigError("--view chooses a calibration view: use --set with --take")
    out = output_folder(args.output)
    images = _export_images(rig, args) if args.format in IMAGE_FORMATS else None
    try:
        files = export(rig, args.format, out, images=images)
    except OSError as exc:
        raise _write_failed(exc.filename or out, exc, f"the {args.format} export") from None
    if args.json:
        emit_json({"format": args.format, "files": [str(f) for f in files]})
    else:
        for f in files:
            print(f)
    return 0


def _export_images(rig, args: argparse.Namespace):
    """One image per calibrated camera at one instant, for exports that point at images (None for
    COLMAP when no source is named: its model names the images, the user brings them)."""
    from calibration.export import images_from_views
    from rig.errors import ConfigError

    if args.take:
        return _take_images(rig, Path(args.take), args.set)
    folder = args.images or rig.meta.get("images")
    if folder is None or not Path(folder).is_dir():
        if args.format == "colmap":
            return None
        where = f" (the views it was made from, {folder}, are gone)" if folder else ""
        raise ConfigError(f"{args.calibration}: a nerfstudio export needs one image per camera{where}: "
                          "name a take (--take TAKE) or calibration views (--images DIR)")
    return images_from_views(rig, folder, args.view)


def _take_images(rig, take: Path, set_number):
    """The frames of one set of a recorded take, every calibrated camera's, at their calibrated size."""
    from rig.errors import ConfigError
    from rig.storage.dataset import Sequence

    seq = Sequence(take)
    missing = [n for n in rig.names if n not in seq.camera_names]
    if missing:
        raise ConfigError(f"{take}: has no camera {', '.join(repr(m) for m in missing)} of the calibration (it has: {', '.join(seq.camera_names)})")
    for sample in seq.samples(cameras=rig.names, with_depth=False):
        if set_number is None or sample.set == set_number:
            return {n: sample.images[n] for n in rig.names}
    if set_number is None:
        raise ConfigError(f"{take}: no set has a frame of every camera ({', '.join(rig.names)})")
    raise ConfigError(f"{take}: no set {set_number} with a frame of every camera ({', '.join(rig.names)})")


def cmd_capture(args: argparse.Namespace) -> int:
    """Pull synchronised frame sets from the rig, keep those that add coverage, write DIR/CAMNAME/NNNN.png."""
    from calibration.boards import load_board
    from rig.capture.calibration_views import capture_views, check_capture, stereo_roles, still_settings
    from rig.commands._paths import new_output_folder
    from rig.config import load_config
    from rig.errors import ConfigError

    # The calibration the config names may not exist yet: this is how it gets made.
    cfg = load_config(args.config, check_calibration=False)
    board = load_board(args.board)
    for name, value in (("--views", args.views), ("--max-frames", args.max_frames)):
        if value < 1:
            raise ConfigError(f"{name} must be at least 1, got {value}")
    for name, value in (("--interval", args.interval), ("--timeout", args.timeout)):
        if not (value >= 0 and value < float("inf")):
            raise ConfigError(f"{name} must be a number of seconds >= 0, got {value}")
    out = new_output_folder(args.output)
    settings = still_settings(cfg.cameras)  # views are stills: no trigger board
    # Simulated cameras have nobody to carry the board: the scene becomes a calibration session
    # that shows the board given here at stations through the volume.
    session = None
    if any(s.scheme == "sim" for s in settings):
        from rig.sim.calibration import calibration_session

        session = calibration_session(settings, board)
    limit = args.max_frames if session is None else min(args.max_frames, session.sets)
    if session is not None and not args.json:
        print(session.describe(), flush=True)
    summary = capture_views(settings, board, out, stereo_roles(cfg.cameras), args.views, limit, args.interval, args.timeout)
    check_capture(summary, args.board, [s.name for s in settings])
    if args.json:
        from rig.commands._output import emit_json

        emit_json(summary)
    else:
        for k in summary["kept"]:
            print(f"{k['view']}: {k['reason']} (board seen by {', '.join(k['cameras'])})")
        cov = ", ".join(f"{n} {v * 100:.0f}%" for n, v in summary["coverage"].items())
        print(f"kept {summary['views_kept']} of {summary['views_looked_at']} views in {out}; coverage {cov}")
        print(f"next: rig calibrate run --images {shlex.quote(str(out))} --board {shlex.quote(str(args.board))} -o {_free_name('calib.json')}")
    return 0


def _free_name(name: str) -> str:
    """`name`, or name-2, name-3, ... : the `next:` line must not name a calibration that exists
    (`rig calibrate run` refuses to replace one without --force)."""
    stem, suffix = Path(name).stem, Path(name).suffix
    k = 1
    while Path(name).exists():
        k += 1
        name = f"{stem}-{k}{suffix}"
    return name
