"""`rig calibrate intrinsics`: each camera's lens from its own close-up board views.

`intrinsics_inputs` checks the inputs; the caller then checks where the result goes, and
`calibrate_lenses` detects the board, calibrates every camera on its own (one that fails is listed
with why, the others still calibrated) and writes one file for all of them.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rig.calibrate.lens import LensChoices


@dataclass
class IntrinsicsInputs:
    images_dir: str
    board: Any  # calibration.boards board
    images: Any  # calibration.images.ImageSet
    lens: LensChoices


def intrinsics_inputs(images_dir: str, board_file: str, lens: LensChoices = LensChoices(),
                      cameras: list[str] | None = None) -> IntrinsicsInputs:
    """The inputs, checked: DIR/CAMNAME/*.png|jpg, or one camera's images directly in DIR;
    `cameras`: only these (default every camera)."""
    from calibration.boards import load_board
    from calibration.images import find_camera_images

    lens.check()
    board = load_board(board_file)
    images = find_camera_images(images_dir, cameras)
    lens.check_cameras(images.cameras)
    return IntrinsicsInputs(images_dir, board, images, lens)


@dataclass
class IntrinsicsResult:
    output: Path
    doc: dict  # what was written (format rig-intrinsics)
    results: dict  # camera -> calibration.intrinsics result, for the cameras calibrated
    failed: dict  # camera -> why it could not be
    detections: Any


def calibrate_lenses(inputs: IntrinsicsInputs, output: str | Path) -> IntrinsicsResult:
    """Detect the board, calibrate each camera and write the file `output` (already checked). When no
    camera could be calibrated, nothing is written and the error gives each one's reason."""
    from calibration.camera import CalibrationError
    from calibration.intrinsics import calibrate_camera
    from common.files import atomic_write_json
    from rig.calibrate.lens import detect
    from rig.errors import StorageError
    from rig.progress import StatusLine

    images, board = inputs.images, inputs.board
    detections = detect(images, board)
    opts = inputs.lens.options()
    status = StatusLine()
    object_points = board.object_points()[1]
    results, failed = {}, {}
    for name in images.empty:  # before: left out without a word
        failed[name] = f"camera '{name}': no images in its folder {Path(images.root) / name}"
    for name in images.cameras:
        status.update(f"calibrating {name}", force=True)
        try:
            r = calibrate_camera(name, detections.image_size[name], detections.corners.get(name, {}), object_points, opts)
        except CalibrationError as exc:
            failed[name] = str(exc)
            continue
        if r.verdict == "unusable":  # no intrinsics for it: listed in `failed` with why
            failed[name] = (f"camera '{name}': reprojection RMS {r.rms_px:.2f} px over {len(r.views_used)} views: the corners fit no lens "
                            "model (is the board file the board shown: its size, orientation and squares? a moving board?)")
        else:
            results[name] = r
    status.done()
    cams = {}
    for n, r in results.items():
        cams[n] = r.to_dict()
        # every image that gave no view says why, like every rejected view
        cams[n]["not_found"] = [v for v in sorted(images.paths[n]) if v not in detections.corners.get(n, {})]
    doc = {"format": "rig-intrinsics", "version": 1, "board": board.to_dict(), "images": str(Path(inputs.images_dir).absolute()),
           "cameras": cams,
           "failed": failed}
    if not results:  # one error, nothing written
        raise CalibrationError("no camera could be calibrated: " + "; ".join(failed.values()))
    path = Path(output)
    try:
        atomic_write_json(path, doc, make_parents=True)
    except OSError as exc:
        raise StorageError(f"{output}: could not write the intrinsics ({exc.strerror or exc})") from None
    return IntrinsicsResult(path, doc, results, failed, detections)
