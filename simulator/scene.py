"""The synthetic scene: a textured room with props, one to three moving people, and optionally a
calibration board carried through the volume. A pure function of (seed, time).

World frame: metres, y up, floor at y = 0, the actors around the origin. The rig looks at them from
the +z side (see simulator.rig), so people face +z by default and the board turns its printed face
(its -z axis, OpenCV's board convention) towards +z.
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict
from typing import Callable, Optional, Union

import numpy as np

from calibration.boards import BoardSpec, CharucoSpec, ChessboardSpec
from simulator.errors import SimulatorError
from simulator.people import (
    MOTIONS,
    PersonSpec,
    _rot_x,
    _rot_y,
    _rot_z,
    person_ground,
    person_primitives,
)
from simulator.primitives import BoardFace, Box, Capsule, Ellipsoid, Primitive, Room
from simulator.textures import (
    AtlasBuilder,
    board_texture,
    fabric_texture,
    hair_texture,
    plank_texture,
    skin_texture,
    speckle_texture,
    wall_texture,
)

SCENES = ("studio", "empty")
MOTION_NAMES = MOTIONS + ("mixed",)
BOARD_NAMES = ("none", "charuco", "chessboard")
ROOM_LO = (-5.0, 0.0, -5.0)
ROOM_HI = (5.0, 3.2, 5.0)

SKIN_TONES = [(0.93, 0.76, 0.64), (0.85, 0.64, 0.50), (0.72, 0.52, 0.38), (0.55, 0.37, 0.25), (0.40, 0.27, 0.19), (0.96, 0.82, 0.72)]
HAIR_COLOURS = [(0.08, 0.06, 0.05), (0.25, 0.15, 0.08), (0.55, 0.38, 0.2), (0.75, 0.62, 0.38), (0.35, 0.33, 0.32), (0.5, 0.17, 0.08)]
PATTERNS = ("stripes", "checks", "plaid", "dots", "plain")


def default_board(kind: str) -> BoardSpec:
    """The boards a sim config names by `board = "charuco" | "chessboard"`."""
    if kind == "charuco":
        # 0.8 x 0.6 m with 4x4-bit markers: every marker bit spans ~4 px at 3.5 m in a 1280x720 view
        return CharucoSpec(squares_x=8, squares_y=6, square_size=0.1, marker_size=0.075, dictionary="DICT_4X4_50")
    if kind == "chessboard":
        return ChessboardSpec(cols=9, rows=6, square_size=0.06)
    raise SimulatorError(f"unknown board {kind!r} (allowed: {', '.join(BOARD_NAMES)})")


def check_time(t: float) -> float:
    try:
        t = float(t)
    except (TypeError, ValueError):
        raise SimulatorError(f"time must be a number of seconds, got {t!r}") from None
    if not math.isfinite(t) or t < 0:
        raise SimulatorError(f"time must be a finite number of seconds >= 0, got {t}")
    return t


class Scene:
    """Room, props, people and board, deterministic for a given seed and time.

    Scene(seed=0, people=2, motion="mixed", board=None) -- `motion` is one of walk, wave, dance,
    jump, still, or mixed (each person its own); `board` a calibration.boards spec, or "charuco" /
    "chessboard" for the default boards; `name` "studio" (with props) or "empty". `board_path`, when
    given, replaces the board's loop through the volume: a function of time giving the board-to-world
    pose (R, t), as `simulator.calibration_session` makes for a calibration session.
    """

    def __init__(self, seed: int = 0, people: int = 2, motion: str = "mixed",
                 board: Union[BoardSpec, str, None] = None, name: str = "studio", board_period: float = 20.0,
                 board_path: Optional[Callable[[float], tuple[np.ndarray, np.ndarray]]] = None):
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
            raise SimulatorError(f"seed must be an integer >= 0, got {seed!r}")
        if name not in SCENES:
            raise SimulatorError(f"unknown scene {name!r} (allowed: {', '.join(SCENES)})")
        if motion not in MOTION_NAMES:
            raise SimulatorError(f"unknown motion {motion!r} (allowed: {', '.join(MOTION_NAMES)})")
        if not isinstance(people, (int, np.integer)) or isinstance(people, bool) or not 0 <= people <= 3:
            raise SimulatorError(f"people must be an integer from 0 to 3, got {people!r}")
        if isinstance(board, str):
            board = None if board == "none" else default_board(board)
        if board is not None and not isinstance(board, (ChessboardSpec, CharucoSpec)):
            raise SimulatorError(f"board must be a ChessboardSpec or CharucoSpec, got {type(board).__name__}")
        if not board_period > 0:
            raise SimulatorError(f"board_period must be positive, got {board_period}")
        self.seed = int(seed)
        self.name = name
        self.motion = motion
        self.board = board
        self.board_period = float(board_period)
        self.board_path = board_path
        self.room = Room("room", "", False, np.array(ROOM_LO), np.array(ROOM_HI),
                         ("wall_xneg", "wall_xpos", "floor", "ceiling", "wall_zneg", "wall_zpos"))
        atlas = AtlasBuilder()
        self._room_textures(atlas, np.random.default_rng([self.seed, 1]))
        self.props: list[Primitive] = self._props(atlas, np.random.default_rng([self.seed, 2])) if name == "studio" else []
        self.persons = self._people(atlas, np.random.default_rng([self.seed, 3]), int(people), motion)
        if board is not None:
            self._board_textures(atlas, np.random.default_rng([self.seed, 4]))
        self.atlas = atlas.build()
        # Lambertian lighting: (direction towards the light, intensity) in the world, plus ambient.
        self.lights = [(np.array([0.35, 1.0, 0.55]) / np.linalg.norm([0.35, 1.0, 0.55]), 0.55),
                       (np.array([-0.6, 0.45, 0.35]) / np.linalg.norm([-0.6, 0.45, 0.35]), 0.22)]
        self.ambient = 0.38
        self._cache: OrderedDict = OrderedDict()
        self.static_layers: OrderedDict = OrderedDict()  # the renderer's per-camera drawing of room and props
        self.lock = threading.RLock()  # cameras may render from several threads

    @property
    def static_count(self) -> int:
        """primitives(t)[:static_count] (room and props) never move."""
        return 1 + len(self.props)

    @classmethod
    def from_options(cls, options: dict) -> "Scene":
        """A scene from a config's [sim] table (see simulator.options.SCENE_OPTIONS)."""
        from simulator.options import validate_options

        try:
            o = validate_options(dict(options), "scene")
        except ValueError as exc:
            raise SimulatorError(f"sim.{exc}") from None
        return cls(seed=o["seed"], people=o["people"], motion=o["motion"], board=o["board"], name=o["scene"])

    # ---- content ----------------------------------------------------------------------------
    def _room_textures(self, atlas: AtlasBuilder, rng: np.random.Generator) -> None:
        hue = rng.uniform(0.55, 0.85, 3)
        walls = {
            "wall_xneg": wall_texture(rng, 512, hue * [1.0, 0.95, 0.85]),
            "wall_xpos": wall_texture(rng, 512, hue * [0.85, 0.95, 1.0]),
            "floor": plank_texture(rng, 512, rng.uniform([0.45, 0.3, 0.18], [0.65, 0.45, 0.3])),
            "ceiling": speckle_texture(rng, 512, (0.85, 0.85, 0.83), 0.08),
            "wall_zneg": wall_texture(rng, 512, hue),
            "wall_zpos": wall_texture(rng, 512, hue * [0.95, 1.0, 0.9]),
        }
        for name in self.room.face_materials:
            atlas.add(name, walls[name], (1.6, 1.6), group=0)

    def _props(self, atlas: AtlasBuilder, rng: np.random.Generator) -> list[Primitive]:
        atlas.add("crate", plank_texture(rng, 256, (0.62, 0.48, 0.3), planks=4), (0.6, 0.6))
        atlas.add("tabletop", plank_texture(rng, 256, (0.35, 0.22, 0.14), planks=6), (0.8, 0.8))
        atlas.add("metal", speckle_texture(rng, 256, (0.45, 0.47, 0.5), 0.12), (0.5, 0.5))
        atlas.add("concrete", speckle_texture(rng, 256, (0.62, 0.6, 0.57), 0.25), (1.0, 1.0))
        atlas.add("ball", fabric_texture(rng, 256, (0.9, 0.15, 0.1), (0.95, 0.9, 0.2), "checks"), (0.25, 0.25))
        atlas.add("cabinet", speckle_texture(rng, 256, rng.uniform(0.2, 0.7, 3), 0.15), (0.7, 0.7))
        props: list[Primitive] = []
        # crates along the back wall
        for k in range(3):
            s = rng.uniform(0.45, 0.8)
            x = -2.6 + 2.6 * k + rng.uniform(-0.5, 0.5)
            z = rng.uniform(-4.4, -3.6)
            props.append(Box(f"crate{k}", "crate", False, np.array([x, s / 2, z]), _rot_y(rng.uniform(-0.6, 0.6)), np.array([s, s, s]) / 2))
        props.append(Box("crate3", "crate", False, np.array([props[0].center[0] + 0.1, props[0].half[1] * 2 + 0.2, props[0].center[2]]),
                         _rot_y(rng.uniform(-0.6, 0.6)), np.array([0.2, 0.2, 0.2])))
        # a table with four legs
        tx, tz = rng.uniform(2.3, 3.0), rng.uniform(-2.8, -2.0)
        Rt = _rot_y(rng.uniform(-0.4, 0.4))
        props.append(Box("table", "tabletop", False, np.array([tx, 0.74, tz]), Rt, np.array([0.6, 0.025, 0.38])))
        for i, (sx, sz) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
            foot = np.array([tx, 0.0, tz]) + Rt @ np.array([sx * 0.54, 0.0, sz * 0.32])
            props.append(Capsule(f"table_leg{i}", "metal", False, foot + [0, 0.02, 0], foot + [0, 0.7, 0], 0.022, np.array([0.0, 0.0, 1.0])))
        # a pillar, a ball and a cabinet
        px = rng.uniform(-3.6, -3.0)
        props.append(Capsule("pillar", "concrete", False, np.array([px, -0.3, -2.6]), np.array([px, 3.5, -2.6]), 0.2, np.array([0.0, 0.0, 1.0])))
        props.append(Ellipsoid("ball", "ball", False, np.array([rng.uniform(-2.2, -1.6), 0.12, rng.uniform(-1.8, -1.2)]), _rot_y(rng.uniform(0, 6.28)), np.array([0.12, 0.12, 0.12])))
        props.append(Box("cabinet", "cabinet", False, np.array([4.6, 0.9, rng.uniform(-1.5, 0.0)]), np.eye(3), np.array([0.3, 0.9, 0.5])))
        return props

    def _people(self, atlas: AtlasBuilder, rng: np.random.Generator, n: int, motion: str) -> list[PersonSpec]:
        if motion == "mixed":
            motions = list(rng.permutation(["walk", "wave", "dance", "jump"]))
        else:
            motions = [motion] * 3
        # standing spots that keep clear of a walker circling at 1.45 m
        spots = [(0.0, 0.0), (-0.75, -0.35), (0.75, 0.3)]
        persons = []
        for i in range(n):
            name = f"person{i}"
            mats = {}
            skin = np.array(SKIN_TONES[int(rng.integers(len(SKIN_TONES)))]) * rng.uniform(0.95, 1.05)
            hair = np.array(HAIR_COLOURS[int(rng.integers(len(HAIR_COLOURS)))])
            shirt = rng.uniform(0.1, 0.9, 3)
            accent = np.clip(1.0 - shirt + rng.uniform(-0.2, 0.2, 3), 0.05, 0.95)
            pants = rng.uniform(0.08, 0.5, 3) * [0.8, 0.85, 1.1]
            shoes = rng.uniform(0.05, 0.6, 3)
            for part, img, tile in (
                ("skin", skin_texture(rng, 256, skin), (0.25, 0.25)),
                ("hair", hair_texture(rng, 256, hair), (0.2, 0.2)),
                ("shirt", fabric_texture(rng, 256, shirt, accent, str(rng.choice(PATTERNS))), (0.4, 0.4)),
                ("pants", fabric_texture(rng, 256, pants, pants * 0.6, str(rng.choice(["plain", "stripes", "checks"]))), (0.4, 0.4)),
                ("shoes", speckle_texture(rng, 256, shoes, 0.15), (0.2, 0.2)),
            ):
                mats[part] = f"{name}.{part}"
                atlas.add(mats[part], img, tile)
            m = motions[i % len(motions)]
            home = (0.0, 0.0) if m == "walk" else spots[i]
            persons.append(PersonSpec(
                name=name, height=float(rng.uniform(1.6, 1.9)), build=float(rng.uniform(0.9, 1.12)), motion=m,
                home=home, heading=float(rng.uniform(-0.4, 0.4)), phase=float(rng.uniform(0, 10)),
                short_sleeves=bool(rng.random() < 0.5), materials=mats))
        return persons

    def _board_textures(self, atlas: AtlasBuilder, rng: np.random.Generator) -> None:
        b = self.board
        # Squares of 2**k texels, about 1 mm per texel: corners sit on texel edges at every mip level.
        tps = int(2 ** round(math.log2(max(16.0, min(128.0, b.square_size * 1000.0)))))
        img, margin_tex, ppm = board_texture(b, tps)
        self._board_tex = (img.shape[1], img.shape[0], margin_tex, ppm)
        atlas.add("board", img, (img.shape[1] / ppm, img.shape[0] / ppm), wrap=False)
        atlas.add("board_back", speckle_texture(rng, 256, (0.55, 0.52, 0.48), 0.15), (0.4, 0.4))

    # ---- queries ----------------------------------------------------------------------------
    def board_pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Board-to-world (R_bw, t_bw) at time t: X_world = R_bw @ X_board + t_bw."""
        if self.board is None:
            raise SimulatorError("this scene has no calibration board (set board = \"charuco\" or \"chessboard\")")
        t = check_time(t)
        if self.board_path is not None:
            return self.board_path(t)
        u = 2 * math.pi * (t % self.board_period) / self.board_period
        centre = np.array([0.75 * math.sin(u), 1.35 + 0.32 * math.sin(2 * u + 0.6), 0.45 * math.sin(3 * u + 1.1)])
        facing = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # columns: board x, y, z in the world
        R = _rot_y(0.5 * math.sin(u + 0.3)) @ facing @ _rot_x(0.4 * math.sin(2 * u + 1.7)) @ _rot_z(0.3 * math.sin(3 * u + 0.4))
        w, h = self.board.size_m
        t_bw = centre - R @ np.array([w / 2, h / 2, 0.0])
        return R, t_bw

    def board_corners(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(ids, world points Nx3) of the board's inner corners at time t."""
        R, tb = self.board_pose(t)
        ids, pts = self.board.object_points()
        return ids, pts @ R.T + tb

    def primitives(self, t: float) -> list[Primitive]:
        """All primitives at time t; index 0 is the room."""
        t = check_time(t)
        with self.lock:
            hit = self._cache.get(t)
            if hit is not None:
                self._cache.move_to_end(t)
                return hit
        prims: list[Primitive] = [self.room, *self.props]
        if self.board is not None:
            R, tb = self.board_pose(t)
            b = self.board
            m = b.margin_m
            w, h = b.size_m
            W, Hh, margin_tex, ppm = self._board_tex
            ext = (-m, w + m, -m, h + m)
            prims.append(BoardFace("board", "board", False, R, tb, ext, True, ppm, margin_tex, (W, Hh)))
            prims.append(BoardFace("board_back", "board_back", False, R, tb, ext, False, ppm, margin_tex, (W, Hh)))
        for p in self.persons:
            prims.extend(person_primitives(p, t))
        with self.lock:
            self._cache[t] = prims
            while len(self._cache) > 8:
                self._cache.popitem(last=False)
        return prims

    def ground_positions(self, t: float) -> list[tuple[float, float]]:
        """Floor (x, z) of each person at time t."""
        t = check_time(t)
        return [person_ground(p, t) for p in self.persons]

    def __repr__(self) -> str:
        b = self.board.type if self.board is not None else "none"
        return f"Scene(seed={self.seed}, people={len(self.persons)}, motion={self.motion!r}, board={b!r}, name={self.name!r})"
