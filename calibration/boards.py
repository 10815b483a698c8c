"""Calibration boards (chessboard and ChArUco): description, 3D corner layout, and a true-size image.

Board frame: origin at the top-left outer corner of the square grid, x to the right along the
columns, y down along the rows, z = 0 on the board surface (OpenCV's object-point convention).
Metres throughout. Board images include a white margin; pixel (i, j) of an image made at `ppm`
pixels per metre covers board coordinates [i/ppm - margin, (i+1)/ppm - margin) in x (likewise y).
"""
from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Union

import cv2
import numpy as np

from calibration.camera import CalibrationError

ARUCO_DICTIONARIES = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))


@dataclass(frozen=True)
class ChessboardSpec:
    """A chessboard of `cols` x `rows` inner corners and square edge `square_size` metres."""

    cols: int
    rows: int
    square_size: float
    margin: float | None = None
    inverted: bool = False  # white squares on black (the printed colours swapped)

    type = "chessboard"

    @property
    def squares(self) -> tuple[int, int]:
        return self.cols + 1, self.rows + 1

    @property
    def margin_m(self) -> float:
        return self.square_size if self.margin is None else self.margin

    @property
    def size_m(self) -> tuple[float, float]:
        """Physical size of the square grid (without margin)."""
        sx, sy = self.squares
        return sx * self.square_size, sy * self.square_size

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    def object_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Corner ids (row-major, as findChessboardCorners orders them) and their board-frame points."""
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        pts = np.stack([(i.ravel() + 1) * self.square_size, (j.ravel() + 1) * self.square_size, np.zeros(i.size)], axis=1)
        return np.arange(self.n_corners), pts.astype(np.float64)

    def image(self, ppm: float) -> np.ndarray:
        """The board (with margin) as a uint8 grey image at `ppm` pixels per metre."""
        m = self.margin_m
        w_m, h_m = self.size_m
        W = int(round((w_m + 2 * m) * ppm))
        H = int(round((h_m + 2 * m) * ppm))
        # Sample square parity at pixel centres, in board coordinates.
        x = (np.arange(W) + 0.5) / ppm - m
        y = (np.arange(H) + 0.5) / ppm - m
        ix = np.floor(x / self.square_size).astype(int)
        iy = np.floor(y / self.square_size).astype(int)
        sx, sy = self.squares
        inside = (ix[None, :] >= 0) & (ix[None, :] < sx) & (iy[:, None] >= 0) & (iy[:, None] < sy)
        black = ((ix[None, :] + iy[:, None]) % 2 == 0) & inside
        img = np.where(black, 0, 255).astype(np.uint8)
        return 255 - img if self.inverted else img

    def to_dict(self) -> dict[str, Any]:
        d = {"type": "chessboard", "cols": self.cols, "rows": self.rows, "square_size": self.square_size}
        if self.margin is not None:
            d["margin"] = self.margin
        if self.inverted:
            d["inverted"] = True
        return d


@dataclass(frozen=True)
class CharucoSpec:
    """A ChArUco board of `squares_x` x `squares_y` squares with ArUco markers in the white squares."""

    squares_x: int
    squares_y: int
    square_size: float
    marker_size: float
    dictionary: str = "DICT_5X5_100"
    margin: float | None = None
    inverted: bool = False  # white markers and squares on black (the printed colours swapped)
    first_marker: int = 0  # this face's marker ids start here (0: OpenCV's default board)
    back_first_marker: int | None = None  # a double-sided board: the back face's marker ids start here
    thickness: float = 0.0  # a double-sided board: metres between its two printed faces

    type = "charuco"

    @property
    def squares(self) -> tuple[int, int]:
        return self.squares_x, self.squares_y

    @property
    def margin_m(self) -> float:
        return self.square_size * 0.5 if self.margin is None else self.margin

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares_x * self.square_size, self.squares_y * self.square_size

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    def cv_dictionary(self):
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    @property
    def n_markers(self) -> int:
        return (self.squares_x * self.squares_y) // 2

    @property
    def double_sided(self) -> bool:
        return self.back_first_marker is not None

    def cv_board(self):
        if self.first_marker:
            ids = np.arange(self.first_marker, self.first_marker + self.n_markers, dtype=np.int32)
            return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_size, self.marker_size, self.cv_dictionary(), ids)
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_size, self.marker_size, self.cv_dictionary())

    def back_face(self) -> "CharucoSpec":
        """The back face of a double-sided board as a board of its own (its own corner ids 0..N-1)."""
        if not self.double_sided:
            raise ValueError("not a double-sided board")
        return dataclasses.replace(self, first_marker=self.back_first_marker, back_first_marker=None, thickness=0.0)

    def object_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Corner ids and their board-frame points. A double-sided board's back corners follow the
        front's (ids N..2N-1): the back face is the same layout turned about the board's vertical axis,
        so its own point (x, y) lies at (width - x, y, thickness) in the front face's frame."""
        pts = np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        if self.double_sided:
            back = pts.copy()
            back[:, 0] = self.size_m[0] - back[:, 0]
            back[:, 2] = self.thickness
            pts = np.concatenate([pts, back])
        return np.arange(len(pts)), pts

    def image(self, ppm: float) -> np.ndarray:
        m = self.margin_m
        w_m, h_m = self.size_m
        gw, gh = int(round(w_m * ppm)), int(round(h_m * ppm))
        grid = self.cv_board().generateImage((gw, gh), marginSize=0, borderBits=1)
        mp = int(round(m * ppm))
        img = cv2.copyMakeBorder(grid, mp, mp, mp, mp, cv2.BORDER_CONSTANT, value=255)
        return 255 - img if self.inverted else img

    def to_dict(self) -> dict[str, Any]:
        d = {
            "type": "charuco",
            "squares_x": self.squares_x,
            "squares_y": self.squares_y,
            "square_size": self.square_size,
            "marker_size": self.marker_size,
            "dictionary": self.dictionary,
        }
        if self.margin is not None:
            d["margin"] = self.margin
        if self.inverted:
            d["inverted"] = True
        if self.first_marker:
            d["first_marker"] = self.first_marker
        if self.double_sided:
            d["back"] = {"first_marker": self.back_first_marker, "thickness": self.thickness}
        return d


BoardSpec = Union[ChessboardSpec, CharucoSpec]


ANIPOSE_KEYS = {"board_x", "board_y", "square_length", "marker_length", "marker_bits", "dict_size"}


def _from_anipose(d: dict[str, Any], where: str) -> dict[str, Any]:
    """A ChArUco board file as (sleap-)anipose writes it: board_x/board_y squares, square_length and
    marker_length in the user's unit (no unit is stored: values of 1 or more are taken as millimetres,
    since no calibration square is a metre wide), marker_bits and dict_size naming the ArUco dictionary."""
    unknown = set(d) - ANIPOSE_KEYS
    if unknown:
        raise CalibrationError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} in an anipose board file (keys: {', '.join(sorted(ANIPOSE_KEYS))})")
    missing = ANIPOSE_KEYS - set(d)
    if missing:
        raise CalibrationError(f"{where}: missing key(s) {', '.join(sorted(missing))} of an anipose board file")
    for key in ("square_length", "marker_length"):
        if not isinstance(d[key], (int, float)) or isinstance(d[key], bool) or not d[key] > 0:
            raise CalibrationError(f"{where}: '{key}' must be a positive number, got {d[key]!r}")
    scale = 1e-3 if d["square_length"] >= 1.0 else 1.0
    return {"type": "charuco", "squares_x": d["board_x"], "squares_y": d["board_y"],
            "square_size": float(d["square_length"]) * scale, "marker_size": float(d["marker_length"]) * scale,
            "dictionary": f"DICT_{d['marker_bits']}X{d['marker_bits']}_{d['dict_size']}"}


def board_from_dict(d: dict[str, Any], where: str = "board") -> BoardSpec:
    """Validate a board description; every problem is one CalibrationError naming the key."""
    if not isinstance(d, dict):
        raise CalibrationError(f"{where}: expected a table")
    if "type" not in d and ANIPOSE_KEYS & set(d):
        d = _from_anipose(d, where)
    kind = d.get("type")
    if isinstance(kind, str):  # "ChArUco", "Chessboard": as other tools write them
        kind = kind.strip().lower()
    if kind == "chessboard":
        allowed = {"type": None, "cols": int, "rows": int, "square_size": float, "margin": float, "inverted": bool}
    elif kind == "charuco":
        allowed = {
            "type": None,
            "squares_x": int,
            "squares_y": int,
            "square_size": float,
            "marker_size": float,
            "dictionary": str,
            "margin": float,
            "inverted": bool,
            "first_marker": int,
            "back": dict,
        }
    else:
        raise CalibrationError(f"{where}: 'type' must be \"chessboard\" or \"charuco\", not {kind!r}")
    vals = _typed_values(d, allowed, where)
    if kind == "chessboard":
        return _chessboard(vals, where)
    return _charuco(vals, where)


def _typed_values(d: dict[str, Any], allowed: dict[str, Any], where: str) -> dict[str, Any]:
    """The description's values, each of its key's type; unknown and missing keys refused."""
    for key in d:
        if key not in allowed:
            raise CalibrationError(f"{where}: unknown key '{key}' (allowed: {', '.join(allowed)})")
    vals: dict[str, Any] = {}
    for key, typ in allowed.items():
        if typ is None:
            continue
        if key not in d:
            if key in ("margin", "dictionary", "inverted", "first_marker", "back"):
                continue
            raise CalibrationError(f"{where}: missing key '{key}'")
        v = d[key]
        if typ is int and (not isinstance(v, int) or isinstance(v, bool)):
            raise CalibrationError(f"{where}: '{key}' must be an integer, got {v!r}")
        if typ is float and (not isinstance(v, (int, float)) or isinstance(v, bool)):
            raise CalibrationError(f"{where}: '{key}' must be a number, got {v!r}")
        if typ is str and not isinstance(v, str):
            raise CalibrationError(f"{where}: '{key}' must be a string, got {v!r}")
        if typ is bool and not isinstance(v, bool):
            raise CalibrationError(f"{where}: '{key}' must be true or false, got {v!r}")
        if typ is dict and not isinstance(v, dict):
            raise CalibrationError(f"{where}: '{key}' must be a table ([board.{key}] or {key} = {{...}}), got {v!r}")
        vals[key] = float(v) if typ is float else v
    return vals


def _chessboard(vals: dict[str, Any], where: str) -> ChessboardSpec:
    """A chessboard's values, checked."""
    if vals["cols"] < 2 or vals["rows"] < 2:
        raise CalibrationError(f"{where}: 'cols' and 'rows' count inner corners and must be at least 2")
    if vals["cols"] == vals["rows"]:
        raise CalibrationError(f"{where}: a square chessboard ({vals['cols']}x{vals['rows']}) is ambiguous in orientation; use cols != rows")
    if not 0 < vals["square_size"] < 10:
        raise CalibrationError(f"{where}: 'square_size' must be in metres, between 0 and 10, got {vals['square_size']}")
    return ChessboardSpec(**vals)


def _charuco(vals: dict[str, Any], where: str) -> CharucoSpec:
    """A ChArUco board's values, checked (its dictionary holds its markers, a back face its own)."""
    if vals["squares_x"] < 2 or vals["squares_y"] < 2:
        raise CalibrationError(f"{where}: 'squares_x' and 'squares_y' must be at least 2")
    if not 0 < vals["square_size"] < 10:
        raise CalibrationError(f"{where}: 'square_size' must be in metres, between 0 and 10, got {vals['square_size']}")
    if not 0 < vals["marker_size"] < vals["square_size"]:
        raise CalibrationError(
            f"{where}: 'marker_size' ({vals['marker_size']}) must be positive and smaller than 'square_size' ({vals['square_size']})"
        )
    dic = vals.get("dictionary", "DICT_5X5_100")
    if dic not in ARUCO_DICTIONARIES:
        raise CalibrationError(f"{where}: unknown 'dictionary' {dic!r} (e.g. DICT_4X4_50, DICT_5X5_100, DICT_6X6_250)")
    n_markers = (vals["squares_x"] * vals["squares_y"]) // 2
    capacity = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dic)).bytesList.shape[0]
    first = vals.get("first_marker", 0)
    if first < 0:
        raise CalibrationError(f"{where}: 'first_marker' must be 0 or more, got {first}")
    if first + n_markers > capacity:
        raise CalibrationError(f"{where}: a {vals['squares_x']}x{vals['squares_y']} board needs {n_markers} markers"
                               f"{f' from id {first}' if first else ''} but {dic} has {capacity}")
    _back_face(vals, where, first, n_markers, capacity, dic)
    vals["dictionary"] = dic
    return CharucoSpec(**vals)


def _back_face(vals: dict[str, Any], where: str, first: int, n_markers: int, capacity: int, dic: str) -> None:
    """A two-sided board's back face (`back`), checked and moved into `vals` as the spec's fields."""
    back = vals.pop("back", None)
    if back is not None:
        unknown = set(back) - {"first_marker", "thickness"}
        if unknown or "first_marker" not in back:
            raise CalibrationError(f"{where}: 'back' takes first_marker (required) and thickness (metres)"
                                   + (f"; unknown: {', '.join(sorted(unknown))}" if unknown else ""))
        bfirst, thick = back["first_marker"], back.get("thickness", 0.0)
        if not isinstance(bfirst, int) or isinstance(bfirst, bool) or bfirst < 0 or bfirst + n_markers > capacity:
            raise CalibrationError(f"{where}: back.first_marker must be an id from 0 to {capacity - n_markers} ({dic} has {capacity} markers), got {bfirst!r}")
        if bfirst < first + n_markers and first < bfirst + n_markers:
            raise CalibrationError(f"{where}: the back face's markers {bfirst}..{bfirst + n_markers - 1} overlap the front's "
                                   f"{first}..{first + n_markers - 1}: each face needs its own ids")
        if not isinstance(thick, (int, float)) or isinstance(thick, bool) or not 0 <= thick < 0.1:
            raise CalibrationError(f"{where}: back.thickness must be in metres, from 0 to 0.1, got {thick!r}")
        vals["back_first_marker"] = bfirst
        vals["thickness"] = float(thick)


def load_board(path: str | Path) -> BoardSpec:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no such board file") from None
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"{path}: not valid TOML ({exc})") from None
    if "board" in data and isinstance(data["board"], dict):
        data = data["board"]
    return board_from_dict(data, where=str(path))
