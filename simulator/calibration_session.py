"""A calibration session on the simulated rig: the board the user names is carried to a series of
stations through the volume and held still at each while the rig takes one synchronised view;
nobody else is in the scene.

This is how a rig is calibrated in practice: the board is shown to every part of every camera's
image, tilted (a board seen squarely does not separate focal length from distance), close enough to
be measured well, and shown to several cameras at once so that they can be tied together. Someone
calibrating a real rig watches the live views to do that; here the stations are planned from the
rig's true cameras:

- per camera, a 3x3 grid of image positions at the distance where the board spans about 45 % of the
  image width, then a 2x2 grid a third further away, each tilted by about 30 degrees (directions vary
  over the grid) and facing the camera along its ray;
- shared stations in the middle of the volume, facing the rig, seen by all cameras.

The stations are interleaved (a shared one, then one per camera, and again), so that any first part
of the session already gives every camera views of its own and views shared with the others.

Session time is counted in stations, not in host time: the k-th synchronised view shows station k,
so what a capture sees depends neither on when the process started nor on how fast it renders.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Optional

import numpy as np

from calibration.boards import BoardSpec
from calibration.camera import CameraModel, RigCalibration
from simulator.errors import SimulatorError
from simulator.people import _rot_x, _rot_y, _rot_z
from simulator.scene import ROOM_HI, ROOM_LO, Scene
from simulator.sensor import SensorModel, SimRig

HOLD_S = 1.0  # scene seconds the board is held at each station (one view is taken in the middle)
SPAN = 0.45  # share of the image width the board's square grid spans at a camera's near stations
TILT_DEG = 30.0
SHARED_DEG = 15.0
# Per-camera stations: (column, row) of the image in fractions, (yaw, pitch) tilt signs.
NEAR_GRID = [((0.25, 0.28), (1, 0)), ((0.75, 0.72), (-1, 0)), ((0.5, 0.5), (0, 1)), ((0.75, 0.28), (0, -1)),
             ((0.25, 0.72), (1, 1)), ((0.5, 0.28), (-1, 1)), ((0.5, 0.72), (1, -1)), ((0.25, 0.5), (-1, -1)),
             ((0.75, 0.5), (1, 0))]
FAR_GRID = [((0.35, 0.35), (-1, 1)), ((0.65, 0.65), (1, -1)), ((0.65, 0.35), (1, 1)), ((0.35, 0.65), (-1, -1))]
FAR_FACTOR = 1.35
# Rigs of few cameras get a third grid per camera: a camera of a large rig also sees many of its
# neighbours' stations, one of a two-camera rig almost none.
MID_GRID = [((0.3, 0.3), (1, 1)), ((0.7, 0.7), (-1, -1)), ((0.5, 0.4), (-1, 0)), ((0.3, 0.7), (0, 1)), ((0.7, 0.3), (0, -1)),
            ((0.5, 0.65), (1, 0)), ((0.2, 0.5), (0, -1)), ((0.8, 0.5), (0, 1)), ((0.5, 0.2), (1, -1))]
MID_FACTOR = 1.15
FEW_CAMERAS = 3
# Shared stations: (across, up) offsets in metres from the middle of the volume, (yaw, pitch) signs.
SHARED = [((0.0, 0.25), (0, 1)), ((-0.45, 0.55), (1, 0)), ((0.45, -0.05), (-1, 0)), ((0.45, 0.55), (0, -1)),
          ((-0.45, -0.05), (1, 1)), ((0.0, 0.6), (-1, -1)), ((0.0, -0.1), (1, -1)), ((-0.6, 0.25), (-1, 1)),
          ((0.6, 0.25), (1, 0)), ((0.25, 0.4), (0, 1)), ((-0.25, 0.1), (-1, 0)), ((0.0, 0.25), (0, -1)),
          ((0.3, 0.1), (1, 1))]
SHARED_DEPTHS = (0.5, 0.45, 0.4, 0.35, 0.3, 0.25, 0.2, 0.15, 0.1, 0.05, 0.0)  # from the volume's middle towards the cameras
SHARED_MAX_ANGLE_DEG = 48.0  # beyond this the markers of a board seen from the side are no longer decoded
SHARED_SEEN = 0.9  # share of the corners every camera must see at a shared station
ROOM_MARGIN = 0.05


@dataclass
class Station:
    R: np.ndarray  # board-to-world rotation: X_world = R @ X_board + t
    t: np.ndarray
    purpose: str  # "shared" or the camera whose image it covers


def _face(z: np.ndarray, yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Board-to-camera rotation: board z along `z` (the board's printed face, its -z side, towards
    the camera), board x along the image's x as far as possible, then tilted."""
    z = z / np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1) @ _rot_y(yaw) @ _rot_x(pitch) @ _rot_z(roll)


def _placed(R_bw: np.ndarray, centre: np.ndarray, board: BoardSpec, purpose: str) -> Station:
    w, h = board.size_m
    return Station(R_bw, centre - R_bw @ np.array([w / 2, h / 2, 0.0]), purpose)


def _inside_room(st: Station, board: BoardSpec) -> bool:
    w, h = board.size_m
    m = board.margin_m
    corners = np.array([[-m, -m, 0], [w + m, -m, 0], [-m, h + m, 0], [w + m, h + m, 0]]) @ st.R.T + st.t
    lo = np.array(ROOM_LO) + ROOM_MARGIN
    hi = np.array(ROOM_HI) - ROOM_MARGIN
    return bool(np.all(corners >= lo) and np.all(corners <= hi))


def _camera_stations(cam: CameraModel, board: BoardSpec, few: bool) -> list[Station]:
    w, _h = board.size_m
    near = cam.fx * w / (SPAN * cam.width)  # distance at which the grid spans SPAN of the image width
    out = []
    grids = ((NEAR_GRID, 1.0), (FAR_GRID, FAR_FACTOR)) + (((MID_GRID, MID_FACTOR),) if few else ())
    for grid, factor in grids:
        for k, ((fu, fv), (sy, sp)) in enumerate(grid):
            depth = near * factor
            ray = cam.pixel_rays(np.array([fu * (cam.width - 1), fv * (cam.height - 1)]))  # through the lens
            R_cb = _face(ray, math.radians(TILT_DEG) * sy, math.radians(TILT_DEG) * sp, math.radians(10.0) * (1 if k % 2 else -1))
            centre = cam.center + cam.R.T @ (ray * depth)
            out.append(_placed(cam.R.T @ R_cb, centre, board, cam.name))
    return out


def _volume_middle(rig: RigCalibration) -> tuple[np.ndarray, np.ndarray]:
    """The point the cameras look at (nearest to all optical axes) and the unit direction from it
    towards the cameras (their mean)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in rig.cameras:
        d = c.R[2]  # optical axis in the world
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if len(rig.cameras) == 1 or np.linalg.matrix_rank(A) < 3:
        c = rig.cameras[0]
        target = c.center + 3.0 * c.R[2]
    else:
        target = np.linalg.solve(A, b)
    towards = np.mean([(c.center - target) / np.linalg.norm(c.center - target) for c in rig.cameras], axis=0)
    return target, towards / np.linalg.norm(towards)


def seen_fraction(st: Station, cam: CameraModel, board: BoardSpec, max_angle_deg: float = 60.0) -> float:
    """Share of the board's corners that `cam` sees inside its image (3 px in from the border),
    0 when the board's printed face is turned more than `max_angle_deg` away from the camera."""
    _ids, obj = board.object_points()
    world = obj @ st.R.T + st.t
    view = world.mean(axis=0) - cam.center
    if np.dot(st.R[:, 2], view) / np.linalg.norm(view) < math.cos(math.radians(max_angle_deg)):
        return 0.0
    uv, z = cam.project(world)
    inside = (z > 0) & (uv[:, 0] >= 3) & (uv[:, 1] >= 3) & (uv[:, 0] <= cam.width - 4) & (uv[:, 1] <= cam.height - 4)
    return float(inside.mean())


def _shared_stations(rig: RigCalibration, board: BoardSpec) -> list[Station]:
    target, towards = _volume_middle(rig)
    dist = float(np.mean([np.linalg.norm(c.center - target) for c in rig.cameras]))
    up = np.array([0.0, 1.0, 0.0])
    across = np.cross(up, towards)
    if np.linalg.norm(across) < 1e-6:
        across = np.array([1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    # Board axes in the world when facing the rig squarely: z away from the cameras, x across, y
    # down (as seen by the cameras: the printed face upright in their images).
    z = -towards
    x = across
    y = np.cross(z, x)
    if np.dot(y, up) > 0:
        x, y = -x, -y
    base = np.stack([x, y, z], axis=1)
    out = []
    for k, ((dx, dy), (sy, sp)) in enumerate(SHARED):
        # As close to the cameras as the board can come and still be seen whole, and not too
        # obliquely, by every one of them: the closer, the larger its squares in the images and the
        # better they are measured. A wide rig leaves less room to turn the board: the turn shrinks.
        for yaw, share in ((y, d) for y in (1.0, 0.5, 0.0) for d in SHARED_DEPTHS):
            R = base @ _rot_y(math.radians(SHARED_DEG) * sy * yaw) @ _rot_x(math.radians(SHARED_DEG) * sp) @ _rot_z(math.radians(8.0) * (1 if k % 2 else -1))
            st = _placed(R, target + towards * (dist * share) + across * dx + up * dy, board, "shared")
            if all(seen_fraction(st, c, board, SHARED_MAX_ANGLE_DEG) >= SHARED_SEEN for c in rig.cameras):
                out.append(st)
                break
    return out


def plan_stations(rig: RigCalibration, board: BoardSpec) -> list[Station]:
    """Every station of a session for `rig`'s cameras, in the order they are visited."""
    few = len(rig.cameras) <= FEW_CAMERAS
    per_camera = [[s for s in _camera_stations(c, board, few) if _inside_room(s, board)] for c in rig.cameras]
    shared = [s for s in _shared_stations(rig, board) if _inside_room(s, board)]
    order: list[Station] = []
    for k in range(max([len(shared)] + [len(p) for p in per_camera])):
        if k < len(shared):
            order.append(shared[k])
        order.extend(p[k] for p in per_camera if k < len(p))
    if not order:
        raise SimulatorError("no calibration station fits in the room for this rig and board")
    return order


class CalibrationSession:
    """The simulated rig of `config` during a calibration with `board`: the same cameras (the same
    true calibration) looking at a scene with no people and the board held at each station in turn.

    `sensor(name)` gives a camera's sensor (rendered live: the board is still at each station, so
    there is no motion to blur); `scene_time(k)` is the scene time of the k-th synchronised view.
    """

    def __init__(self, config, board: BoardSpec, hold_s: float = HOLD_S, views_per_station: int = 1):
        if not hold_s > 0:
            raise SimulatorError(f"hold_s must be positive, got {hold_s}")
        if not (isinstance(views_per_station, int) and views_per_station >= 1):
            raise SimulatorError(f"views_per_station must be a whole number >= 1, got {views_per_station!r}")
        # Views taken while the board is held at one station: a crew holds it still for a moment,
        # and a capture that keeps a view only once the board is still needs two or more.
        self.views_per_station = views_per_station
        rig = SimRig(config)
        self.board = board
        self.hold_s = float(hold_s)
        self.truth = rig.calibration
        self.cameras = {c.name: c for c in rig.cameras}
        self.options = dict(rig.options)
        self.stations = plan_stations(self.truth, board)
        self._scene: Optional[Scene] = None
        self._lock = threading.Lock()
        self._sensors: dict[str, SensorModel] = {}

    @property
    def sets(self) -> int:
        """Synchronised views in the session: one per station."""
        return len(self.stations)

    def describe(self) -> str:
        shared = sum(1 for s in self.stations if s.purpose == "shared")
        return (f"simulated calibration session: the board is held at {self.sets} stations "
                f"({shared} facing the whole rig, {self.sets - shared} covering each camera's image), no people")

    def board_pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        k = min(int(t // self.hold_s), self.sets - 1)
        st = self.stations[k]
        return st.R, st.t

    @property
    def views(self) -> int:
        """Synchronised views until the board has been at every station."""
        return self.sets * self.views_per_station

    def scene_time(self, view_index: int) -> float:
        """Scene time shown by the view_index-th synchronised view (0-based): the middle of its
        station's hold; past the last station the board stays there."""
        return (min(int(view_index) // self.views_per_station, self.sets - 1) + 0.5) * self.hold_s

    @property
    def scene(self) -> Scene:
        with self._lock:
            if self._scene is None:
                self._scene = Scene(seed=self.options["seed"], people=0, board=self.board, name=self.options["scene"],
                                    board_path=self.board_pose)
            return self._scene

    def sensor(self, name: str) -> SensorModel:
        with self._lock:
            if name not in self._sensors:
                cfg = self.cameras.get(name)
                if cfg is None:
                    raise SimulatorError(f"no sim camera named {name!r} (have: {', '.join(self.cameras)})")
                opts = dict(getattr(cfg, "sim", None) or {})
                opts["motion_blur"] = False  # the board is held still and nobody moves: one render is the exposure
                self._sensors[name] = SensorModel(lambda: self.scene, self.truth[name], opts,
                                                  gain_db=float(getattr(cfg, "gain", None) or 0.0), loop_frames=0)
            return self._sensors[name]
