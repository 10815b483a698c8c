"""`rig calibrate run`: the rig's calibration from board images on disk, every camera in the left
camera's frame.

`run_inputs` checks every input (board, images, held intrinsics and their priors, pairing offsets,
the config's stereo pair) before anything slow; the caller then checks where the result goes, and
`calibrate_images` detects the board, solves, refuses a calibration some camera cannot use, and
writes the file, keeping the result elsewhere when that write fails.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from calibration.camera import CalibrationError
from rig.calibrate.lens import LensChoices


class UnusableCalibration(CalibrationError):
    """The solve gave a calibration some camera cannot use; nothing was written. `rig` is that
    calibration, for its report."""

    def __init__(self, message: str, rig):
        super().__init__(message)
        self.rig = rig


@dataclass
class RunInputs:
    """What `calibrate_images` needs, every part of it checked."""

    images_dir: str
    board: Any  # calibration.boards board
    images: Any  # calibration.images.ImageSet
    lens: LensChoices
    known: dict = field(default_factory=dict)  # camera -> intrinsics held (or priors' centres)
    prior: dict = field(default_factory=dict)  # term -> sigma
    offsets: dict = field(default_factory=dict)  # camera -> instants its images are shifted by
    roles: dict = field(default_factory=dict)  # left/right -> camera
    left: str | None = None
    right: str | None = None
    lens_priors: bool = True
    auto_offset: bool = False


def run_inputs(images_dir: str, board_file: str, lens: LensChoices = LensChoices(), *, config: str | None = None,
               left: str | None = None, right: str | None = None, intrinsics: str | None = None, hold: list[str] | None = None,
               prior_sigma: str | None = None, offsets: list[str] | None = None, auto_offset: bool = False,
               free_intrinsics: bool = False) -> RunInputs:
    """Every input of a run, checked before the detection and the solve, which take minutes.
    `intrinsics`: a file whose cameras (`hold`, default all it has) are held, or with `prior_sigma`
    (as f=1%,c=8,dist=0.02) used as priors; `offsets`: CAMERA=N; `config`: a rig config whose left
    and right cameras are the stereo pair."""
    from calibration.boards import load_board
    from calibration.images import find_images
    from calibration.pairing import check_offsets, parse_offsets
    from rig.config import load_config
    from rig.errors import ConfigError

    lens.check()
    board = load_board(board_file)
    images = find_images(images_dir)
    known = _known_intrinsics(intrinsics, hold, images.cameras)
    _check_known_sizes(known, images)
    lens.check_cameras(images.cameras)
    shifts = parse_offsets(offsets)
    check_offsets(shifts, images.paths)
    prior = {}
    if prior_sigma is not None:
        from calibration.known import parse_prior, prior_sigmas

        if not known:
            raise ConfigError("--prior-sigma needs --intrinsics FILE (the values the priors are centred on)")
        prior = parse_prior(prior_sigma)
        for k in known.values():
            prior_sigmas(k, prior)  # a term the camera's lens lacks is refused before the detection
    roles = dict(images.roles)
    if config:
        cfg = load_config(config, check_calibration=False)
        for role in ("left", "right"):
            cam = cfg.by_role(role)
            if cam is not None:
                if cam.name not in images.cameras:
                    raise ConfigError(f"{config}: its {role} camera '{cam.name}' has no images in {images_dir} "
                                      f"(cameras: {', '.join(images.cameras)})")
                roles[role] = cam.name
    return RunInputs(images_dir, board, images, lens, known, prior, shifts, roles, left, right,
                     lens_priors=not free_intrinsics, auto_offset=auto_offset)


def _known_intrinsics(intrinsics: str | None, hold: list[str] | None, cameras: list[str]) -> dict:
    """The intrinsics the file gives for the cameras to hold (`hold`, default all it has)."""
    from calibration.known import load_known
    from rig.errors import ConfigError

    if intrinsics is None:
        if hold:
            raise ConfigError("--hold needs --intrinsics FILE")
        return {}
    known = load_known(intrinsics)
    names = hold or [c for c in cameras if c in known]
    for name in names:
        if name not in known:
            raise ConfigError(f"--hold {name}: {intrinsics} has no camera '{name}' (it has: {', '.join(known)})")
        if name not in cameras:
            raise ConfigError(f"--hold {name}: no images of camera '{name}' (cameras: {', '.join(cameras)})")
    if not names:
        raise ConfigError(f"{intrinsics}: none of its cameras ({', '.join(known)}) has images here (cameras: {', '.join(cameras)})")
    return {n: known[n] for n in names}


def _check_known_sizes(known: dict, images) -> None:
    """A held camera's size in the file against its first image's, before minutes of detection (the
    solve checks every image again); an image that cannot be read is left to the detection to name."""
    import cv2

    for name, k in known.items():
        first = next(iter(sorted(images.paths[name].values())), None)
        img = None if first is None else cv2.imread(str(first), cv2.IMREAD_UNCHANGED)
        if img is not None:
            k.check((img.shape[1], img.shape[0]))


@dataclass
class RunResult:
    """A solved calibration: `written` is where it was saved (`path`, or a file kept beside when
    writing `path` failed, then `why`; None when it could be written nowhere)."""

    rig: Any  # calibration.camera.RigCalibration
    detections: Any
    path: Path
    requested: str  # the output as the caller named it
    written: Path | None
    why: str | None

    def write_error(self):
        """The StorageError to end with when the calibration could not be written where asked."""
        from rig.errors import StorageError

        if self.why is None:
            return None
        kept = f"the result is kept in {self.written}; move it where you want it" if self.written else \
            "it could not be written anywhere either and was printed on stdout"
        return StorageError(f"{self.requested}: could not write the calibration ({self.why}); {kept}")

    def summary(self) -> dict:
        """The results as one JSON-ready object (`rig calibrate run --json`)."""
        rig, meta, detections = self.rig, self.rig.meta, self.detections
        cameras = meta["report"]["cameras"]
        return {
            "output": str(self.written) if self.written else None,
            "requested_output": str(self.requested),
            "cameras": rig.names,
            "views_used": meta["views_used"],
            "views_found": {c: len(detections.corners[c]) for c in rig.names},
            "images": detections.images_seen,
            "rms_px": meta["rms_px"],
            "stereo_rms_px": meta["stereo_rms_px"],
            "baseline_m": meta["baseline_m"],
            "epipolar_rms_px": (meta["report"]["stereo"] or {}).get("epipolar_rms_px"),
            "stereo_pair": meta["stereo_pair"],
            "intrinsics": {c.name: {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "dist": c.dist.tolist(), "model": c.model}
                           for c in rig.cameras},
            # every camera in the rig frame (the left camera's): world-to-camera R, t (metres)
            "per_camera": {c.name: {"K": c.K.tolist(), "dist": c.dist.tolist(), "model": c.model, "R": c.R.tolist(), "t": c.t.tolist(),
                                    "width": c.width, "height": c.height, "rms_px": meta["rms_px"].get(c.name),
                                    "verdict": cameras[c.name].get("verdict"),
                                    "reasons": cameras[c.name].get("reasons"),
                                    "focal_spread_pct": cameras[c.name].get("focal_spread_pct")}
                           for c in rig.cameras},
            "rejected": meta["rejected"],
            "pairing": meta["report"].get("pairing", []),
            "warnings": meta["report"]["warnings"],
            **({"calibration": rig.to_dict()} if self.written is None else {}),
        }


def calibrate_images(inputs: RunInputs, output: str | Path) -> RunResult:
    """Detect the board in every image, solve the rig and write it to `output` (already checked:
    writable, and replaceable if it exists). Raises UnusableCalibration, writing nothing, when some
    camera's corners fit no lens model."""
    from calibration.solve import calibrate_rig
    from rig.calibrate.lens import detect
    from rig.progress import StatusLine

    path = Path(output)
    detections = detect(inputs.images, inputs.board)
    opts = inputs.lens.options(left=inputs.left or inputs.roles.get("left"), right=inputs.right or inputs.roles.get("right"),
                               known=inputs.known, prior=inputs.prior, lens_priors=inputs.lens_priors, offsets=inputs.offsets,
                               auto_offset=inputs.auto_offset)
    status = StatusLine()
    rig = calibrate_rig(detections, inputs.board, opts, progress=lambda s: status.update(s, force=True)).rig
    status.done()
    rig.meta["images"] = str(Path(inputs.images_dir).absolute())
    unusable = _unusable_cameras(rig)
    if unusable:  # a calibration no camera pair can use is not written, nor replaces one
        raise UnusableCalibration(_unusable_message(rig, unusable, output), rig)
    written, why = save_keeping(rig, path)
    return RunResult(rig, detections, path, str(output), written, why)


def _unusable_cameras(rig) -> list[str]:
    """The cameras whose verdict is `unusable` (their corners fit no lens model in the joint solve)."""
    cams = rig.meta["report"]["cameras"]
    return [n for n in rig.names if cams.get(n, {}).get("verdict") == "unusable"]


def _unusable_message(rig, unusable: list[str], output) -> str:
    from calibration.quality import MIN_JOINT_VIEWS, RMS_UNUSABLE_PX

    cams = rig.meta["report"]["cameras"]
    rms = {n: rig.meta["rms_px"].get(n) for n in unusable}
    high = [n for n in unusable if rms[n] is None or rms[n] > RMS_UNUSABLE_PX]
    few = [n for n in unusable if n not in high]  # unusable by the views the joint fit kept
    why = []
    if high:
        why.append("reprojection RMS " + ", ".join(f"'{n}' " + ("unknown" if rms[n] is None else f"{rms[n]:.2f} px") for n in high)
                   + f" (above {RMS_UNUSABLE_PX:g} px)")
    if few:
        why.append("the joint rig fit kept only " + ", ".join(f"{cams[n]['views_used']} of '{n}''s views" for n in few)
                   + f" (the rest rejected as outliers; {MIN_JOINT_VIEWS} are needed)")
    stalled = any("did not converge" in w for w in rig.meta["report"]["warnings"])
    return (f"the calibration is unusable: {'; '.join(why)}"
            f"{'; the joint adjustment did not converge' if stalled else ''}; nothing was written to {output}. "
            "Check that the board file describes the board shown (its size, in the board's orientation) "
            "and that every camera's images of one instant share a name or number")


def save_keeping(rig, output: Path) -> tuple[Path | None, str | None]:
    """Write the calibration to `output`; a solve is never lost to a failed write (the disk filled up,
    the folder went away during the solve): it is then kept beside as NAME.unsaved-TIME in the working
    folder, else in the temporary folder. Returns (where it was written or None, why `output` failed
    or None)."""
    import tempfile
    import time

    try:
        rig.save(output)
        return output, None
    except OSError as exc:
        why = exc.strerror or str(exc)
    name = f"{output.name}.unsaved-{time.strftime('%Y%m%d-%H%M%S')}"
    for folder in (Path.cwd(), Path(tempfile.gettempdir())):
        try:
            rig.save(folder / name)
            return folder / name, why
        except OSError:
            continue
    return None, why
