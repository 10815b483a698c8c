"""Calibration benchmark: board detection time per 1280x720 image, and the time to solve a six-camera
rig from 50 views (intrinsics, stereo pair, joint bundle adjustment), with the accuracy reached.

    .venv/bin/python benchmarks/calibration.py [--views 50] [--json] [--synthetic]
    .venv/bin/python benchmarks/calibration.py --session [--cameras 6] [--size 640x360] [--compare-free]
    .venv/bin/python benchmarks/calibration.py --real [DIR] [--json]
    .venv/bin/python benchmarks/calibration.py --out-of-step [--json]

`--session`: the calibration `rig demo` makes. The simulated calibration session of an N-camera rig
(simulator.calibration_session: the A0 board held at stations through the volume) is rendered at
every station, detected, and solved with k3 held, from all the stations and from shorter first parts
of the session; each result is compared with the simulator's exact cameras.

With the simulator installed, the six-camera arc rig (1280x720) watches an A0 ChArUco board carried
through the volume for `--views` time steps; detection is timed on every rendered image and the solve on
those detections, and the result is compared with the simulator's ground truth. Rendering is not timed.
`--synthetic` (or no simulator) times detection on the board seen through known homographies and the
solve on exact corner projections with 0.1 px noise. Chessboard detection is always timed on the
homography images too.

`--real [DIR]`: the product's calibration on the three real datasets in DIR (default ../shared/data
beside the checkout; when it is absent, one line says so and the exit status is 0), each run through
the CLI (`rig calibrate ... --json`, in this process) into a temporary folder:
  xi-stereo-chessboard        `rig calibrate run` on 25 left/right pairs (9x6 chessboard, 24 mm): fx error
                              of each camera and baseline error against the README's plain-OpenCV figures
  pose2sim-4cam-chessboard    `rig calibrate intrinsics` on 4 cameras x 7 photos (4x7 chessboard, 60 mm):
                              fx error against the Qualisys file (focalLengthU / 64), focal spread, verdict
  sleap-anipose-4cam-charuco  `rig calibrate run --board DIR/board.toml --left back`: rotation error (deg)
                              and distance ratio of mid, side, top relative to back, against both OpenCV
                              calibrations in the README's table
For each: the images, the detection time per image (calibration.images.detect_images timed on its own,
JPEG decoding included), the command's time and the solve's share of it (the command less its own call
of detect_images), the RMS per camera. Every reference figure is read from the dataset's files.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from calibration.boards import CharucoSpec, ChessboardSpec  # noqa: E402
from calibration.compare import describe, errors_against_truth  # noqa: E402
from calibration.detect import make_detector  # noqa: E402
from calibration.images import DetectionSet  # noqa: E402
from calibration.solve import Options, calibrate_rig  # noqa: E402
from calibration.synthetic import arc_rig, board_poses, observe, warp_board  # noqa: E402

CHARUCO = CharucoSpec(11, 8, 0.105, 0.078, "DICT_5X5_100")  # A0 size
CHESSBOARD = ChessboardSpec(9, 6, 0.06)

REAL_DATA = REPO.parent / "shared" / "data"
XI, POSE2SIM, SLEAP = "xi-stereo-chessboard", "pose2sim-4cam-chessboard", "sleap-anipose-4cam-charuco"
# the boards as each dataset's README describes them (inner corners, square in metres)
XI_BOARD = 'type = "chessboard"\ncols = 9\nrows = 6\nsquare_size = 0.024\n'
POSE2SIM_BOARD = 'type = "chessboard"\ncols = 4\nrows = 7\nsquare_size = 0.06\n'


def simulated_sequence(n_views: int):
    """(truth, {camera: [(view, grey image)]}) rendered by the simulator, or None without it."""
    try:
        import cv2

        from simulator.rig import virtual_rig
        from simulator.scene import Scene
        from simulator.sensor import NOMINAL_EXPOSURE_S, SensorModel
    except ImportError:
        return None
    truth = virtual_rig(6, 1280, 720)
    scene = Scene(seed=0, people=0, board=CHARUCO)
    frames = {}
    for cam in truth.cameras:
        sensor = SensorModel(scene, cam, {"motion_blur": False})
        frames[cam.name] = [
            (f"{k:04d}", cv2.cvtColor(sensor.expose(scene.board_period * k / n_views, NOMINAL_EXPOSURE_S, sensor.frame_rng(k)), cv2.COLOR_RGB2GRAY))
            for k in range(n_views)
        ]
    return truth, frames


def warped_frames(board, n: int):
    rng = np.random.default_rng(0)
    frames = []
    for _ in range(n):
        cx, cy = rng.uniform(350, 930), rng.uniform(220, 500)
        w, h = rng.uniform(250, 500), rng.uniform(180, 330)
        quad = [[cx - w / 2, cy - h / 2], [cx + w / 2, cy - h / 2], [cx + w / 2, cy + h / 2], [cx - w / 2, cy + h / 2]]
        frames.append(warp_board(board, np.array(quad) + rng.normal(0, 20, (4, 2)))[0])
    return frames


def time_detection(board, images):
    """Per-image detection time (ms) and the detections."""
    detector = make_detector(board)
    detector(images[0])  # the first call builds lookup tables
    times, found = [], []
    for img in images:
        t0 = time.perf_counter()
        found.append(detector(img))
        times.append((time.perf_counter() - t0) * 1000)
    stats = {"images": len(images), "found": sum(c is not None for c in found), "ms_median": round(statistics.median(times), 2),
             "ms_mean": round(statistics.mean(times), 2), "ms_max": round(max(times), 2)}
    return stats, found


def time_solve(detections: DetectionSet, truth):
    t0 = time.perf_counter()
    result = calibrate_rig(detections, CHARUCO)
    seconds = time.perf_counter() - t0
    return {
        "cameras": len(detections.cameras),
        "views": len(detections.views),
        "camera_views": sum(len(v) for v in detections.corners.values()),
        "corners": sum(len(c) for per in detections.corners.values() for c in per.values()),
        "seconds": round(seconds, 3),
        "rms_px": result.rig.meta["rms_px"],
        "worst_error": {k: round(v, 4) for k, v in errors_against_truth(result.rig, truth).worst.items()},
    }


def session_accuracy(n_cameras: int, width: int, height: int, compare_free: bool = False) -> dict:
    """Errors against the truth of a session's calibration, from all stations and from its first
    parts (a capture with fewer --views), with the time per rendered and detected image; each solved
    with the lens priors and, with `compare_free`, also with every intrinsic free."""
    from rig.sim.rig_config import sim_rig_config
    from rig.config import parse_config
    from simulator.calibration_session import CalibrationSession
    from simulator.sensor import NOMINAL_EXPOSURE_S

    session = CalibrationSession(parse_config(sim_rig_config(n_cameras=n_cameras, width=width, height=height)), CHARUCO)
    detector = make_detector(CHARUCO)
    corners: dict[str, dict] = {c: {} for c in session.cameras}
    t0 = time.perf_counter()
    for k in range(session.sets):
        for c in session.cameras:
            sensor = session.sensor(c)
            found = detector(sensor.expose(session.scene_time(k), NOMINAL_EXPOSURE_S, sensor.frame_rng(k)))
            if found is not None:
                corners[c][f"{k:04d}"] = found
    per_image_ms = (time.perf_counter() - t0) * 1000 / (session.sets * len(session.cameras))
    out = {"cameras": n_cameras, "size": f"{width}x{height}", "stations": session.sets, "render_and_detect_ms_per_image": round(per_image_ms, 1),
           "by_stations": {}}
    for n in sorted({session.sets, (2 * session.sets) // 3, session.sets // 2, session.sets // 3}, reverse=True):
        sub = {c: {v: x for v, x in per.items() if int(v) < n} for c, per in corners.items()}
        det = DetectionSet({c: (width, height) for c in session.cameras}, sub, {c: n for c in session.cameras})
        result = calibrate_rig(det, CHARUCO, Options(fix_k3=True))
        out["by_stations"][n] = {"views_used": result.rig.meta["views_used"],
                                 "worst_error": {k: round(v, 4) for k, v in errors_against_truth(result.rig, session.truth).worst.items()},
                                 "warnings": result.rig.meta["report"]["warnings"]}
        if compare_free:
            free = calibrate_rig(det, CHARUCO, Options(fix_k3=True, lens_priors=False))
            out["by_stations"][n]["worst_error_free_intrinsics"] = {k: round(v, 4) for k, v in errors_against_truth(free.rig, session.truth).worst.items()}
    return out


# --- --real: the product's calibration on the real datasets in ../shared/data ---------------------


@contextlib.contextmanager
def detection_timed(spent: list):
    """Within: every call of calibration.images.detect_images (the commands look it up when they
    run) adds its seconds to `spent`."""
    import calibration.images as images

    original = images.detect_images

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            spent.append(time.perf_counter() - t0)

    images.detect_images = timed
    try:
        yield
    finally:
        images.detect_images = original


def run_rig(*argv) -> tuple[dict, dict]:
    """`rig ARGV --json` in this process: the JSON object it printed, and its time in seconds, all
    of it and less its own board detection (the solve, with the report and the file written)."""
    from rig.cli import main as rig_main

    buf, detecting = io.StringIO(), []
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(buf), detection_timed(detecting):
        rc = rig_main([*map(str, argv), "--json"])
    seconds = time.perf_counter() - t0
    if rc != 0:
        raise RuntimeError(f"rig {' '.join(map(str, argv))} exited {rc}")
    solve_s = round(seconds - sum(detecting), 2) if detecting else None  # None: the command's detection went unseen
    return json.loads(buf.getvalue()), {"command_s": round(seconds, 2), "solve_s": solve_s}


def time_image_detection(images, board) -> dict:
    """detect_images on an image set, timed image by image (reading the file included)."""
    from calibration.images import detect_images

    stamps = [time.perf_counter()]
    det = detect_images(images, board, progress=lambda i, n: stamps.append(time.perf_counter()))
    per_image = [(b - a) * 1000 for a, b in zip(stamps, stamps[1:])]
    return {"images": {c: len(p) for c, p in images.paths.items()},
            "found": {c: len(v) for c, v in det.corners.items()},
            "detect_ms_median": round(statistics.median(per_image), 1),
            "detect_ms_mean": round(statistics.mean(per_image), 1),
            "detect_ms_max": round(max(per_image), 1),
            "detect_s": round(stamps[-1] - stamps[0], 2)}


def pct(value: float, reference: float) -> float:
    """Signed error of `value` in % of `reference`."""
    return round(100 * (value / reference - 1), 3)


def readme_number(readme: Path, pattern: str) -> float:
    m = re.search(pattern, readme.read_text(), re.S)
    if m is None:
        raise ValueError(f"{readme}: no figure matching {pattern!r}")
    return float(m.group(1))


def xi_references(folder: Path) -> dict:
    """The README's plain-OpenCV figures: fx (px) and baseline (m)."""
    readme = folder / "README.md"
    return {"fx": readme_number(readme, r"fx about\s+([\d.]+)\s*px"),
            "baseline_m": readme_number(readme, r"baseline \|T\|.*?\(about\s+([\d.]+)\s*mm\)") / 1000}


def qualisys_fx(folder: Path) -> dict[str, float]:
    """focalLengthU per camera serial (1/64 px in the Qualisys file), in px."""
    text = (folder / "reference-qualisys.qca.txt").read_text()
    return {name: float(f) / 64.0 for name, f in re.findall(r'serial="(cam\d+)".*?focalLengthU="([\d.]+)"', text, re.S)}


def opencv_references(folder: Path) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """The README's table: model -> camera -> (rvec back->camera, centre in back's frame, mm)."""
    out: dict[str, dict] = {}
    model = None
    for line in (folder / "README.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 6 or not re.fullmatch(r"[a-z]+", cells[2]) or cells[2] == "camera":
            continue
        model = cells[0] or model
        out.setdefault(model, {})[cells[2]] = (np.array(cells[4].split(), float), np.array(cells[5].split(), float))
    return out


def pose_errors(rig, name: str, rvec_ref: np.ndarray, centre_ref_mm: np.ndarray) -> dict:
    """Camera `name` relative to back against a reference: rotation angle (deg), distance ratio."""
    import cv2

    back, cam = rig["back"], rig[name]
    rel = cam.R @ back.R.T
    centre_mm = back.R @ (cam.center - back.center) * 1000.0
    cos = (np.trace(rel @ cv2.Rodrigues(rvec_ref)[0].T) - 1) / 2
    return {"rotation_deg": round(float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), 3),
            "distance_ratio": round(float(np.linalg.norm(centre_mm) / np.linalg.norm(centre_ref_mm)), 4)}


def write_board(folder: Path, text: str) -> Path:
    path = folder / "board.toml"
    path.write_text(text)
    return path


def bench_xi(folder: Path, tmp: Path) -> dict:
    from calibration.boards import load_board
    from calibration.images import find_images

    board = write_board(tmp, XI_BOARD)
    out = time_image_detection(find_images(folder), load_board(board))
    summary, times = run_rig("calibrate", "run", "--images", folder, "--board", board, "-o", tmp / "xi.json")
    ref = xi_references(folder)
    return {**out, **times, "reference": ref, "views_used": summary["views_used"],
            "fx": {c: round(v["fx"], 2) for c, v in summary["intrinsics"].items()},
            "fx_error_pct": {c: pct(v["fx"], ref["fx"]) for c, v in summary["intrinsics"].items()},
            "rms_px": summary["rms_px"], "stereo_rms_px": summary["stereo_rms_px"], "epipolar_rms_px": summary["epipolar_rms_px"],
            "baseline_m": round(summary["baseline_m"], 5), "baseline_error_pct": pct(summary["baseline_m"], ref["baseline_m"])}


def bench_pose2sim(folder: Path, tmp: Path) -> dict:
    from calibration.boards import load_board
    from calibration.images import find_camera_images

    board = write_board(tmp, POSE2SIM_BOARD)
    out = time_image_detection(find_camera_images(folder), load_board(board))
    summary, times = run_rig("calibrate", "intrinsics", "--images", folder, "--board", board, "-o", tmp / "intrinsics.json")
    ref = qualisys_fx(folder)
    cams = {}
    for name, c in summary["cameras"].items():
        cams[name] = {"fx": c["fx"], "fx_reference": round(ref[name], 2), "fx_error_pct": pct(c["fx"], ref[name]), "rms_px": c["rms_px"],
                      "views_used": c["views_used"], "focal_spread_pct": c["focal_spread_pct"], "verdict": c["verdict"],
                      "rejected": [r["view"] for r in c["rejected"]], "not_found": c["not_found"]}
    return {**out, **times, "cameras": cams, "failed": summary["failed"]}


def bench_sleap(folder: Path, tmp: Path) -> dict:
    from calibration.boards import load_board
    from calibration.camera import RigCalibration
    from calibration.images import find_images

    board = folder / "board.toml"
    out = time_image_detection(find_images(folder), load_board(board))
    summary, times = run_rig("calibrate", "run", "--images", folder, "--board", board, "--left", "back", "-o", tmp / "sleap.json")
    rig = RigCalibration.load(tmp / "sleap.json")
    poses = {model: {name: pose_errors(rig, name, *ref[name]) for name in ("mid", "side", "top")}
             for model, ref in opencv_references(folder).items()}
    return {**out, **times, "views_used": summary["views_used"], "rms_px": summary["rms_px"],
            "warnings": summary["warnings"], "poses_vs_opencv": poses}


REAL_BENCHES = {XI: bench_xi, POSE2SIM: bench_pose2sim, SLEAP: bench_sleap}


def real_benchmarks(root: Path) -> dict:
    """Every dataset present under `root`; an absent one says so, a failed one says why."""
    results = {}
    for name, bench in REAL_BENCHES.items():
        folder = root / name
        if not folder.is_dir():
            results[name] = {"absent": str(folder)}
            continue
        with tempfile.TemporaryDirectory(prefix="rig-bench-") as tmp:
            try:
                results[name] = bench(folder, Path(tmp))
            except Exception as exc:  # one dataset failing must not hide the others' figures
                results[name] = {"error": f"{type(exc).__name__}: {exc}"}
    return results


def per_camera(d: dict, fmt: str = "{}") -> str:
    return ", ".join(f"{c} {fmt.format(v)}" for c, v in d.items())


def print_detection(r: dict) -> None:
    print(f"  images: {per_camera(r['images'])} (board found: {per_camera(r['found'])})")
    print(f"  detection per image (JPEG read included): {r['detect_ms_median']:.1f} ms median, {r['detect_ms_mean']:.1f} ms mean, "
          f"{r['detect_ms_max']:.1f} ms max; {r['detect_s']:.2f} s in all")
    solve = "not measured" if r["solve_s"] is None else f"{r['solve_s']:.2f} s"
    print(f"  command: {r['command_s']:.2f} s, of which solve {solve} (the rest: its own board detection)")


def print_xi(r: dict) -> None:
    ref = r["reference"]
    print(f"  {'camera':<8}{'fx px':>10}{'fx err %':>10}{'RMS px':>9}")
    for c, fx in r["fx"].items():
        print(f"  {c:<8}{fx:>10.2f}{r['fx_error_pct'][c]:>+10.2f}{r['rms_px'][c]:>9.3f}")
    print(f"  reference (README, plain OpenCV): fx {ref['fx']} px, baseline {ref['baseline_m'] * 1000:.1f} mm")
    print(f"  baseline {r['baseline_m'] * 1000:.2f} mm ({r['baseline_error_pct']:+.2f} %), stereo RMS {r['stereo_rms_px']:.3f} px, "
          f"epipolar RMS {r['epipolar_rms_px']:.3f} px")


def print_pose2sim(r: dict) -> None:
    print(f"  {'camera':<8}{'fx px':>10}{'Qualisys':>10}{'fx err %':>10}{'RMS px':>9}{'views':>7}{'spread %':>10}  {'verdict':<9}dropped")
    for c, d in r["cameras"].items():
        spread = "-" if d["focal_spread_pct"] is None else f"{d['focal_spread_pct']:.2f}"
        dropped = ", ".join([f"{v} (rejected)" for v in d["rejected"]] + [f"{v} (not found)" for v in d["not_found"]]) or "-"
        print(f"  {c:<8}{d['fx']:>10.2f}{d['fx_reference']:>10.2f}{d['fx_error_pct']:>+10.2f}{d['rms_px']:>9.3f}{d['views_used']:>7}"
              f"{spread:>10}  {d['verdict']:<9}{dropped}")
    for c, why in r["failed"].items():
        print(f"  {c}: failed: {why}")


def print_sleap(r: dict) -> None:
    print(f"  RMS px: {per_camera(r['rms_px'], '{:.3f}')}; views used: {per_camera(r['views_used'])}")
    models = list(r["poses_vs_opencv"])
    print(f"  {'camera':<8}" + "".join(f"{'vs OpenCV ' + m:>30}" for m in models))
    print(f"  {'':<8}" + f"{'rotation deg':>17}{'dist ratio':>13}" * len(models))
    for name in ("mid", "side", "top"):
        cells = [r["poses_vs_opencv"][m][name] for m in models]
        print(f"  {name:<8}" + "".join(f"{e['rotation_deg']:>17.2f}{e['distance_ratio']:>13.3f}" for e in cells))
    for w in r["warnings"]:
        print(f"  warning: {w}")


REAL_PRINTERS = {XI: print_xi, POSE2SIM: print_pose2sim, SLEAP: print_sleap}


def real_main(root: Path, as_json: bool) -> int:
    if not root.is_dir():
        message = f"the real calibration datasets are absent ({root}): nothing to benchmark"
        print(json.dumps({"data": str(root), "absent": message}) if as_json else message)
        return 0
    results = real_benchmarks(root)
    if as_json:
        print(json.dumps({"data": str(root), **results}))
        return 0
    for name, r in results.items():
        print(f"{name}:")
        if "absent" in r or "error" in r:
            print(f"  {'absent: ' + r['absent'] if 'absent' in r else 'error: ' + r['error']}")
            continue
        print_detection(r)
        REAL_PRINTERS[name](r)
    return 0


def out_of_step(as_json: bool) -> int:
    """The synthetic session of tests/calibration/test_calib_pairing.py (three cameras, 40 instants of a
    board under 10 % of every image, cam_1 one instant late), solved four ways: as named with every
    intrinsic free (what the joint solve did before the pairing check and the lens priors), as named
    with the priors, and with the offset applied with and without them. Errors against the truth."""
    from calibration.boards import CharucoSpec
    from calibration.camera import CalibrationError
    from calibration.compare import errors_against_truth
    from calibration.synthetic import image_share, moving_board_session, ring_rig

    board = CharucoSpec(7, 5, 0.09, 0.0675, "DICT_5X5_100")
    truth = ring_rig(3)
    det = moving_board_session(truth, board, 40, shifts={"cam_1": 1}, noise_px=0.15, speed=0.47)
    out = {"image_share": {c: round(v, 4) for c, v in image_share(truth, det).items()}, "runs": {}}
    ways = {"as named, free intrinsics": Options(left="cam_0", lens_priors=False, offsets={"cam_1": 0}),
            "as named, lens priors": Options(left="cam_0", offsets={"cam_1": 0}),
            "check (default)": Options(left="cam_0"),
            "offset applied, free intrinsics": Options(left="cam_0", lens_priors=False, auto_offset=True),
            "offset applied, lens priors": Options(left="cam_0", auto_offset=True)}
    for name, opts in ways.items():
        t0 = time.perf_counter()
        try:
            res = calibrate_rig(det, board, opts)
        except CalibrationError as exc:
            out["runs"][name] = {"stopped": str(exc), "s": round(time.perf_counter() - t0, 2)}
            continue
        errs = errors_against_truth(res.rig, truth).cameras
        out["runs"][name] = {"s": round(time.perf_counter() - t0, 2), "cameras": {
            c: {"focal_pct": round(100 * (res.rig[c].fx / truth[c].fx - 1), 3), "rotation_deg": round(e["rotation_deg"], 3),
                "position_mm": round(e["position_mm"], 2), "single_camera_focal_pct": round(100 * (res.intrinsics[c].K[0, 0] / truth[c].fx - 1), 3)}
            for c, e in errs.items()}}
    if as_json:
        print(json.dumps(out))
        return 0
    print(f"board's largest share of each image: {per_camera(out['image_share'], '{:.3f}')}")
    for name, r in out["runs"].items():
        if "stopped" in r:
            print(f"{name}: stopped ({r['s']:.1f} s): {r['stopped']}")
            continue
        print(f"{name} ({r['s']:.1f} s):")
        for c, e in r["cameras"].items():
            print(f"  {c}: focal {e['focal_pct']:+.2f} % (own fit {e['single_camera_focal_pct']:+.2f} %), rotation {e['rotation_deg']:.2f} deg, "
                  f"position {e['position_mm']:.1f} mm")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=50, help="time steps (views) of the six-camera sequence")
    ap.add_argument("--synthetic", action="store_true", help="do not render: homography images and exact projections")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--session", action="store_true", help="the simulated calibration session `rig demo` uses (see above)")
    ap.add_argument("--cameras", type=int, default=6, help="with --session: cameras in the rig (default 6)")
    ap.add_argument("--size", default="640x360", help="with --session: image size (default 640x360, the demo's)")
    ap.add_argument("--compare-free", action="store_true", help="with --session: solve each part again with every intrinsic free")
    ap.add_argument("--real", nargs="?", const=REAL_DATA, type=Path, metavar="DIR",
                    help=f"benchmark `rig calibrate` on the real datasets in DIR (default {REAL_DATA})")
    ap.add_argument("--out-of-step", action="store_true",
                    help="the synthetic far-board session with a camera one instant late, solved as named and re-paired, "
                         "with and without the lens priors")
    args = ap.parse_args()
    if args.out_of_step:
        return out_of_step(args.json)
    if args.real is not None:
        return real_main(args.real, args.json)
    if args.session:
        w, h = (int(v) for v in args.size.lower().split("x"))
        res = session_accuracy(args.cameras, w, h, args.compare_free)
        if args.json:
            print(json.dumps(res))
            return 0
        print(f"session: {res['cameras']} cameras at {res['size']}, {res['stations']} stations, "
              f"{res['render_and_detect_ms_per_image']} ms per image rendered and detected")
        for n, r in res["by_stations"].items():
            print(f"  first {n} stations: {describe(r['worst_error'])}; views used {r['views_used']}"
                  + (f"; {len(r['warnings'])} warnings" if r["warnings"] else ""))
            if "worst_error_free_intrinsics" in r:
                print(f"    with every intrinsic free (no lens priors): {describe(r['worst_error_free_intrinsics'])}")
        return 0

    results = {}
    seq = None if args.synthetic else simulated_sequence(args.views)
    if seq is not None:
        truth, frames = seq
        names = [c.name for c in truth.cameras]
        flat = [img for n in names for _, img in frames[n]]
        stats, found = time_detection(CHARUCO, flat)
        results["detect_charuco"] = {"source": "simulator renders with sensor noise (A0 ChArUco, 6-camera rig)", **stats}
        corners, i = {}, 0
        for n in names:
            corners[n] = {}
            for view, _ in frames[n]:
                if found[i] is not None:
                    corners[n][view] = found[i]
                i += 1
        det = DetectionSet({n: (1280, 720) for n in names}, corners, {n: args.views for n in names})
        results["solve"] = {"source": "detections in the simulator renders", **time_solve(det, truth)}
    else:
        stats, _ = time_detection(CHARUCO, warped_frames(CHARUCO, 12))
        results["detect_charuco"] = {"source": "board through known homographies", **stats}
        truth = arc_rig(6)
        det = observe(truth, CHARUCO, board_poses(args.views), noise_px=0.1)
        results["solve"] = {"source": "exact projections with 0.1 px noise", **time_solve(det, truth)}
    stats, _ = time_detection(CHESSBOARD, warped_frames(CHESSBOARD, 12))
    results["detect_chessboard"] = {"source": "board through known homographies", **stats}

    if args.json:
        print(json.dumps(results))
        return 0
    for key in ("detect_charuco", "detect_chessboard"):
        d = results[key]
        print(f"{key}: {d['ms_median']:.1f} ms median, {d['ms_mean']:.1f} ms mean, {d['ms_max']:.1f} ms max per 1280x720 image "
              f"({d['found']}/{d['images']} found; {d['source']})")
    s = results["solve"]
    print(f"solve: {s['cameras']} cameras x {s['views']} views ({s['camera_views']} camera views, {s['corners']} corners): "
          f"{s['seconds']:.2f} s ({s['source']})")
    print(f"accuracy, worst camera: {describe(s['worst_error'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
