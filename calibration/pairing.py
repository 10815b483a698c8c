"""Which instant each camera's images belong to: a camera whose frames are out of step with the others'
(a video started a frame late, a free-running camera whose frames were numbered from another start)
pairs every view with the wrong instant of a moving board, and a rig solved from such pairs is wrong
however well each lens was fitted.

An instant is a position in the sorted list of the names all cameras' views carry (`0000`, `0001`, ...
or the number that ends a file name): offset +1 pairs a camera's image named after position p with
the others' images of position p + 1. Before the joint solve each camera is tried against the
reference camera (the rig's left camera) at offsets -2..+2: the pair's stereo residual with both
lenses held (their relative pose and the board poses adjusted to both cameras' corners) at each offset. A clear winner
other than 0 means the camera is out of step; one that still fits far worse than the two lenses fit
their own views means no offset tried pairs it (photos not taken together, or further out of step).
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass

import numpy as np

from calibration.camera import CalibrationError
from calibration.detect import Corners
from calibration.images import natural_key
from calibration.result import CameraIntrinsics

SEARCH = (-2, -1, 0, 1, 2)
MIN_PAIRED_VIEWS = 4  # views the camera and the reference must share at an offset to compare it
MAX_VIEWS = 24  # views a residual is measured on at most (every k-th of those shared): its cost grows with them
# The best offset wins clearly when its residual is at most this share of the residual at 0 (the
# example that motivated the check: 0.53 against 1.05 px); a static board, or a board that moves
# little between instants, leaves the residuals close and the images as they are.
CLEAR_RATIO = 0.7
# A pairing that is right fits about as well as the two cameras' own fits do (on real recordings
# 1.2-1.5 times their RMS). A clear winner well above that is no pairing at all: the images are not
# of the same instants (photos taken apart), or out of step by more than SEARCH reaches; applying the
# best offset tried then pairs them with other wrong instants (a camera three instants late, tried at
# -2, came out of the joint solve with one view of 21 left and was written).
FIT_FACTOR = 5.0  # times the larger of the two cameras' single-camera RMS
FIT_FLOOR_PX = 0.5


@dataclass
class PairingCheck:
    camera: str
    reference: str
    residuals: dict[int, float]  # offset -> stereo RMS px (offsets with too few shared views absent)
    best: int  # the offset with the least residual
    clear: bool  # best is not 0 and wins clearly
    applied: int = 0  # the offset applied to this camera's images (given or found)
    given: bool = False  # the offset was given (--offset), not searched for
    limit: float | None = None  # px: a pairing that fits has a residual under this (FIT_FACTOR x the fits' RMS)
    lost: bool = False  # best is not 0 and wins clearly, yet fits no better than `limit`: no offset tried pairs it

    def line(self) -> str:
        """One line: which instant the images fit best, with the residuals."""
        k = self.best
        return f"{self.camera}'s images fit best {_when(k)} ({self.residuals[k]:.2f} vs {self.residuals[0]:.2f} px)"

    def lost_line(self) -> str:
        """One line: no offset tried pairs this camera's images with the reference's."""
        k = self.best
        return (f"{self.camera}'s images fit {self.reference}'s at none of the offsets {SEARCH[0]:+d}..{SEARCH[-1]:+d} "
                f"({self.residuals[k]:.2f} px at best, {_when(k)}, {self.residuals[0]:.2f} px as named; a pairing that fits "
                f"stays under {self.limit:.2f} px, {FIT_FACTOR:g} times the two cameras' own fits)")

    def to_dict(self) -> dict:
        return {"camera": self.camera, "reference": self.reference, "residuals_px": {f"{k:+d}": round(v, 4) for k, v in self.residuals.items()},
                "best": self.best, "clear": self.clear, "applied": self.applied, "given": self.given,
                "limit_px": None if self.limit is None else round(self.limit, 4), "lost": self.lost}


def _when(k: int) -> str:
    return f"{_count(abs(k))} instant{'s' if abs(k) > 1 else ''} {'later' if k > 0 else 'earlier'}"


def _count(n: int) -> str:
    return {1: "one", 2: "two"}.get(n, str(n))


def instant_order(views_per_camera: dict[str, list[str]] | dict[str, dict]) -> list[str]:
    """Every instant any camera has an image of, in order (names compared as natural sort keys)."""

    return sorted({v for per in views_per_camera.values() for v in per}, key=natural_key)


def shifted_name(view: str, offset: int, order: list[str], index: dict[str, int] | None = None) -> str | None:
    """The instant `offset` positions after `view` in `order`; None beyond either end."""
    p = (index or {v: i for i, v in enumerate(order)})[view] + offset
    return order[p] if 0 <= p < len(order) else None


def shift(per_view: dict, offset: int, order: list[str]) -> dict:
    """A camera's per-view mapping re-keyed by `offset` instants; views shifted past the ends drop out."""
    if offset == 0:
        return dict(per_view)
    index = {v: i for i, v in enumerate(order)}
    out = {}
    for v, x in per_view.items():
        to = shifted_name(v, offset, order, index)
        if to is not None:
            out[to] = x
    return out


def shift_fit(fit: CameraIntrinsics, offset: int, order: list[str]) -> CameraIntrinsics:
    """A single-camera fit whose views are re-keyed by `offset` (the lens does not depend on pairing)."""
    return dataclasses.replace(fit, poses=shift(fit.poses, offset, order), view_rms=shift(fit.view_rms, offset, order))


def check_offsets(offsets: dict[str, int], views_per_camera: dict[str, list[str]] | dict[str, dict], where: str = "--offset") -> None:
    """Given offsets must name cameras that have images and leave each such camera MIN_PAIRED_VIEWS
    instants paired with the others; CalibrationError (one line) otherwise, before anything is done."""
    cams = list(views_per_camera)
    order = instant_order(views_per_camera)
    for name, k in offsets.items():
        if name not in views_per_camera:
            raise CalibrationError(f"{where} {name}={k:+d}: no images of camera '{name}' (cameras: {', '.join(cams)})")
        others = {v for c, per in views_per_camera.items() if c != name for v in per}
        paired = set(shift({v: None for v in views_per_camera[name]}, k, order)) & others
        if len(paired) < MIN_PAIRED_VIEWS:
            limit = max(len(order) - MIN_PAIRED_VIEWS, 0)
            raise CalibrationError(
                f"{where} {name}={k:+d}: the images span {len(order)} instants; shifted by {k:+d}, {len(paired)} of camera '{name}''s "
                f"would be paired with another camera's ({MIN_PAIRED_VIEWS} are needed; offsets up to +-{limit} at most)")


def parse_offsets(specs: list[str] | None) -> dict[str, int]:
    """`["cam_1=+1", "cam_2=-2"]` -> {"cam_1": 1, "cam_2": -2}; CalibrationError (one line) on a bad spec."""
    out: dict[str, int] = {}
    for spec in specs or ():
        name, eq, value = str(spec).partition("=")
        name, value = name.strip(), value.strip()
        # ASCII digits only: int() also reads '1_0' as 10 and other scripts' digits
        k = int(value) if re.fullmatch(r"[+-]?[0-9]+", value) else None
        if not eq or not name or k is None:
            raise CalibrationError(f"--offset {spec!r}: expected CAMERA=N with N a whole number of instants, as cam_1=+1")
        if name in out:
            raise CalibrationError(f"--offset {spec!r}: camera '{name}' is given an offset twice")
        out[name] = k
    return out


def stereo_residual(reference: str, camera: str, corners: dict[str, dict[str, Corners]], intr: dict[str, CameraIntrinsics],
                    object_points: np.ndarray, offset: int, order: list[str]) -> float | None:
    """The pair's stereo RMS (px) with both lenses held when `camera`'s images are shifted by `offset`:
    the relative pose and every shared view's board pose adjusted to both cameras' corners together
    (calibration.bundle, started from the single-camera fits' poses). None when they would share fewer
    than MIN_PAIRED_VIEWS views. (`cv2.stereoCalibrate` gives the same figure, but its dense solver
    spends seconds per offset on a few dozen mispaired views.)"""
    from calibration import bundle, lens
    from calibration.geometry import compose, invert_pose, robust_mean_pose, rotation_vector

    ref, moved = intr[reference], shift_fit(intr[camera], offset, order)
    shifted = shift(corners[camera], offset, order)
    shared = [v for v in order if v in ref.poses and v in moved.poses]
    if len(shared) < MIN_PAIRED_VIEWS:
        return None
    shared = shared[:: -(-len(shared) // MAX_VIEWS)]  # spread over the session: enough to tell pairings apart
    rel = [compose(*moved.poses[v], *invert_pose(*ref.poses[v])) for v in shared]  # reference -> camera, per view
    R, t, _ = robust_mean_pose(np.array([r[0] for r in rel]), np.array([r[1] for r in rel]))
    cam_idx, view_idx, xyz, uv = [], [], [], []
    for k, v in enumerate(shared):
        for ci, c in enumerate((corners[reference][v], shifted[v])):
            cam_idx.append(np.full(len(c.ids), ci))
            view_idx.append(np.full(len(c.ids), k))
            xyz.append(object_points[c.ids])
            uv.append(c.points)
    problem = bundle.Problem(np.concatenate(cam_idx), np.concatenate(view_idx), np.concatenate(xyz), np.concatenate(uv), 2, len(shared),
                             np.array([ref.model == "fisheye", moved.model == "fisheye"]))
    intr0 = np.array([[f.K[0, 0], f.K[1, 1], f.K[0, 2], f.K[1, 2], *lens.coefficients("pinhole", f.dist)] for f in (ref, moved)])
    cams0 = np.array([np.zeros(6), np.r_[rotation_vector(R), t]])
    views0 = np.array([np.r_[rotation_vector(ref.poses[v][0]), ref.poses[v][1]] for v in shared])
    # A few iterations: from the fits' poses the right pairing converges in two or three; a wrong one
    # only has to show a residual well above it, not its exact least value.
    sol = bundle.solve(problem, intr0, cams0, views0, fixed_cameras=(0,), fixed_intrinsics=np.ones((2, bundle.N_INTR), dtype=bool),
                       max_iterations=6)
    rms = sol.rms()
    return float(rms) if np.isfinite(rms) else None


def check_pairing(reference: str, cameras: list[str], corners: dict[str, dict[str, Corners]], intr: dict[str, CameraIntrinsics],
                  object_points: np.ndarray, given: dict[str, int] | None = None) -> list[PairingCheck]:
    """Each camera but the reference tried at offsets -2..+2 against it; cameras given an offset are
    not searched (their check records the offset as given). Cameras sharing too few views with the
    reference at offset 0 are left out."""
    given = given or {}
    order = instant_order(corners)
    checks = []
    for cam in cameras:
        if cam == reference:
            continue
        if cam in given:
            checks.append(PairingCheck(cam, reference, {}, given[cam], False, given[cam], True))
            continue
        residuals = {}
        for k in SEARCH:
            r = stereo_residual(reference, cam, corners, intr, object_points, k, order)
            if r is not None:
                residuals[k] = r
        if 0 not in residuals:
            continue
        best = min(residuals, key=residuals.get)
        limit = max(FIT_FACTOR * max(intr[reference].rms, intr[cam].rms), FIT_FLOOR_PX)
        wins = best != 0 and residuals[best] <= CLEAR_RATIO * residuals[0]
        fits = residuals[best] <= limit
        checks.append(PairingCheck(cam, reference, residuals, best, wins and fits, limit=limit, lost=wins and not fits))
    return checks
