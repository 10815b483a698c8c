"""Board corner detection: the corners a camera sees in one image, each with its board corner id.

Chessboards: `findChessboardCorners` + `cornerSubPix` in either polarity, falling back to
`findChessboardCornersSB` (in either), then a canonical corner order. A chessboard with cols != rows looks the same after a half turn, so the
detector may return its corners in either order; we pick the order whose first corner is nearest the
image's top-left (first-to-last corner vector pointing right/down), so that cameras of a rig that stand
upright side by side agree on which corner is id 0.

ChArUco: `cv2.aruco.CharucoDetector`; the markers identify every corner, so partial views are used as
they are (any corners with ids, at least `min_corners`, not all on one line).
"""
from __future__ import annotations

import dataclasses

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.boards import BoardSpec, CharucoSpec, ChessboardSpec

# A view with fewer corners constrains a pose badly and is not worth its board pose parameters.
MIN_CHARUCO_CORNERS = 6


@dataclass
class Corners:
    """Corners found in one image: board corner ids (N,) and pixel positions (N, 2), OpenCV pixel centres."""

    ids: np.ndarray
    points: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.size)


def to_gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY if img.shape[2] == 3 else cv2.COLOR_RGBA2GRAY)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def canonical_chessboard_order(points: np.ndarray) -> np.ndarray:
    """Reverse the row-major corner list when its first corner is the bottom-right-most end."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    d = pts[-1] - pts[0]
    if d[0] + d[1] < 0:
        pts = pts[::-1].copy()
    return pts


def _subpix_window(points: np.ndarray, cols: int) -> int:
    """Half-size of the cornerSubPix window: up to 11 px, but under half the corner spacing."""
    grid = points.reshape(-1, cols, 2)
    spacing = np.linalg.norm(np.diff(grid, axis=1), axis=2).min() if cols > 1 else 20.0
    return int(np.clip(spacing * 0.45, 2, 11))


class ChessboardDetector:
    def __init__(self, board: ChessboardSpec):
        self.board = board
        self.pattern = (board.cols, board.rows)

    def __call__(self, image: np.ndarray) -> Corners | None:
        found = self.classic(image)
        return found if found is not None else self.sector(image)

    @property
    def passes(self):
        """The detectors in the order to try them, each over every face of the board first: the
        classic one refined by cornerSubPix is the more accurate where it finds the board, in either
        polarity (the sector one finds an inverted board the classic one misses, 0.8 px off)."""
        return (self.classic, self.sector)

    def classic(self, image: np.ndarray) -> Corners | None:
        gray = to_gray(image)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, pts = cv2.findChessboardCorners(gray, self.pattern, flags=flags)
        if not found:
            return None
        win = _subpix_window(pts.reshape(-1, 2), self.board.cols)
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.001)
        pts = cv2.cornerSubPix(gray, pts.astype(np.float32), (win, win), (-1, -1), crit)
        return Corners(np.arange(self.board.n_corners), canonical_chessboard_order(pts))

    def sector(self, image: np.ndarray) -> Corners | None:
        """The sector-based detector: it finds boards the classic one misses (blur, low contrast)."""
        found, pts = cv2.findChessboardCornersSB(to_gray(image), self.pattern, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        return Corners(np.arange(self.board.n_corners), canonical_chessboard_order(pts)) if found else None


class CharucoDetector:
    def __init__(self, board: CharucoSpec, min_corners: int = MIN_CHARUCO_CORNERS):
        self.board = board
        self.min_corners = max(4, min_corners)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        # Sample each marker cell with 8x8 pixels of the unwarped marker, not 4x4: small markers (2-3
        # image pixels per cell, a board across a room at 640x360) then decode ~10 % more often.
        params.perspectiveRemovePixelPerCell = 8
        charuco_params = cv2.aruco.CharucoParameters()
        charuco_params.minMarkers = 1  # a corner interpolated from one adjacent marker is still exact after subpixel refinement
        self._detector = cv2.aruco.CharucoDetector(board.cv_board(), charuco_params, params)
        _, self._object = board.object_points()
        cvb = board.cv_board()
        self._marker_xy = {int(i): np.asarray(o, dtype=np.float64).reshape(4, 3)[:, :2]
                           for i, o in zip(np.asarray(cvb.getIds()).reshape(-1), cvb.getObjPoints())}

    def __call__(self, image: np.ndarray) -> Corners | None:
        gray = to_gray(image)
        corners, ids, marker_corners, marker_ids = self._detector.detectBoard(gray)
        if ids is None or corners is None or len(ids) < self.min_corners:
            return None
        ids = ids.reshape(-1).astype(np.int64)
        pts = corners.reshape(-1, 2).astype(np.float64)
        order = np.argsort(ids)
        ids, pts = ids[order], pts[order]
        pts = refine_small_corners(gray, pts)
        ids, pts = self._drop_displaced(ids, pts, marker_corners, marker_ids)
        if len(ids) < self.min_corners or _collinear(self._object[ids, :2]):
            return None  # a single row of corners fixes no homography
        return Corners(ids, pts)

    def _drop_displaced(self, ids, pts, marker_corners, marker_ids):
        """Remove corners that the subpixel refinement pulled off the board's geometry.

        A ChArUco corner is placed from its adjacent markers and refined to the nearest corner-like
        feature; when the corner itself is hidden (an arm across the board, a glare) the refinement lands
        on the occluder's edge, pixels away. Each adjacent marker's four corners give an exact local
        homography of the board plane; a corner further than max(1.5 px, 8% of the square) from where
        its markers put it is dropped.
        """
        if marker_ids is None or len(marker_ids) == 0:
            return ids, pts
        square = self.board.square_size
        reach = 0.75 * square  # centres of the (up to 4) markers touching a corner are 0.71 squares away
        keep = np.ones(len(ids), dtype=bool)  # corners with no adjacent marker found stay
        mids = np.asarray(marker_ids).reshape(-1)
        known = np.array([int(m) in self._marker_xy for m in mids])
        if not known.any():
            return ids, pts
        src = np.stack([self._marker_xy[int(m)] for m in mids[known]])
        dst = np.stack([np.asarray(mc, dtype=np.float64).reshape(4, 2) for mc, k in zip(marker_corners, known) if k])
        H = _homographies(src, dst)
        ok = np.all(np.isfinite(H.reshape(len(H), -1)), axis=1)
        H, centres = H[ok], src[ok].mean(axis=1)
        if len(H) == 0:
            return ids, pts
        xy = self._object[ids, :2]
        near = np.linalg.norm(xy[:, None, :] - centres[None, :, :], axis=2) < reach  # (corners, markers)
        # Every corner through every marker's homography (cheap), then the median over adjacent markers.
        def through(points):
            q = np.einsum("kij,nj->nki", H, np.c_[points, np.ones(len(points))])
            return q[..., :2] / q[..., 2:3]
        pred = through(xy)  # (corners, markers, 2)
        step = np.linalg.norm(through(xy + [square, 0.0]) - pred, axis=2)
        has = near.any(axis=1)
        if not has.any():
            return ids, pts
        with np.errstate(all="ignore"):
            p = np.nanmedian(np.where(near[:, :, None], pred, np.nan)[has], axis=1)
            scale = np.nanmedian(np.where(near, step, np.nan)[has], axis=1)
        limit = np.maximum(1.5, 0.08 * scale)
        keep[np.flatnonzero(has)] = np.linalg.norm(p - pts[has], axis=1) <= limit
        return ids[keep], pts[keep]


def _homographies(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Exact homographies (K, 3, 3) mapping 4 points src[k] (K, 4, 2) onto dst[k] (batched DLT with
    h33 = 1 on coordinates centred and scaled per quad, for conditioning; NaN where degenerate)."""
    K = len(src)

    def normaliser(p):
        c = p.mean(axis=1)
        s = np.sqrt(2) / np.maximum(np.linalg.norm(p - c[:, None, :], axis=2).mean(axis=1), 1e-12)
        T = np.zeros((K, 3, 3))
        T[:, 0, 0] = s
        T[:, 1, 1] = s
        T[:, 0, 2] = -s * c[:, 0]
        T[:, 1, 2] = -s * c[:, 1]
        T[:, 2, 2] = 1
        return T, (p - c[:, None, :]) * s[:, None, None]

    Ts, ps = normaliser(src)
    Td, pd = normaliser(dst)
    A = np.zeros((K, 8, 8))
    b = np.zeros((K, 8))
    x, y = ps[..., 0], ps[..., 1]
    u, v = pd[..., 0], pd[..., 1]
    A[:, 0::2, 0] = x
    A[:, 0::2, 1] = y
    A[:, 0::2, 2] = 1
    A[:, 0::2, 6] = -u * x
    A[:, 0::2, 7] = -u * y
    A[:, 1::2, 3] = x
    A[:, 1::2, 4] = y
    A[:, 1::2, 5] = 1
    A[:, 1::2, 6] = -v * x
    A[:, 1::2, 7] = -v * y
    b[:, 0::2] = u
    b[:, 1::2] = v
    H = np.full((K, 3, 3), np.nan)
    good = np.abs(np.linalg.det(A)) > 1e-9
    if good.any():
        h = np.linalg.solve(A[good], b[good][..., None])[..., 0]
        Hn = np.concatenate([h, np.ones((len(h), 1))], axis=1).reshape(-1, 3, 3)
        H[good] = np.linalg.inv(Td[good]) @ Hn @ Ts[good]
    return H


def refine_small_corners(gray: np.ndarray, pts: np.ndarray, factor: float = 0.10) -> np.ndarray:
    """cornerSubPix with a window sized to each corner's square.

    A ChArUco corner's clean neighbourhood ends where the marker's inner bits begin, about a quarter of
    a square away; a larger window lets the bits' edges pull the corner (often by a pixel or more when
    squares are 10-20 px). The half-window is `factor` (10 %) of the distance to the nearest other corner
    (2 to 11 px), which measured best on rendered boards with known corners.
    """
    if len(pts) < 2:
        return pts
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    win = np.clip((factor * d.min(axis=1)).astype(int), 2, 11)
    out = pts.astype(np.float32).copy()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    for w in np.unique(win):
        m = win == w
        out[m] = cv2.cornerSubPix(gray, out[m].reshape(-1, 1, 2), (int(w), int(w)), (-1, -1), crit).reshape(-1, 2)
    return out.astype(np.float64)


def _collinear(xy: np.ndarray) -> bool:
    c = xy - xy.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    return bool(s.size < 2 or s[1] < 1e-6 * max(s[0], 1e-12) or s[1] < 1e-9)


class AnyFaceDetector:
    """Finds the board whichever way it faces the camera: in the polarity the board file states
    first, then in the other one (a white-on-black board, or a file that does not say so); a ChArUco
    board also seen from the back (printed on film, or the camera behind it), where its markers read
    mirrored. The corners found in a flipped image are mapped back to the image's own pixels; the
    corner ids name the same physical corners either way."""

    def __init__(self, board: BoardSpec, inner, back=None):
        self.board = board
        self.inner = inner
        # a double-sided board's back face: its own detector, its corner ids after the front's
        self.sides = [(inner, 0)] + ([(back, board.n_corners)] if back is not None else [])
        self.faces = [(inv, False) for inv in (board.inverted, not board.inverted)]
        if isinstance(board, CharucoSpec):  # a chessboard is symmetric: its back cannot be told from its front
            self.faces += [(inv, True) for inv in (board.inverted, not board.inverted)]
        self.found_as: dict[tuple[bool, bool], int] = {}  # how often each face was the one found

    def tried(self) -> str:
        """What a search that found nothing tried, for the error message."""
        b = self.board
        what = (f"a ChArUco board of {b.squares_x}x{b.squares_y} squares with {b.dictionary} markers" if isinstance(b, CharucoSpec)
                else f"a chessboard of {b.cols}x{b.rows} inner corners")
        faces = "black on white and white on black" + (", front and back (mirrored)" if isinstance(b, CharucoSpec) else "")
        if isinstance(b, CharucoSpec) and b.double_sided:
            faces += f", and its back face's markers from id {b.back_first_marker}"
        return f"{what}, {faces}"

    def __call__(self, image: np.ndarray) -> Corners | None:
        gray = to_gray(image)
        passes = max(len(getattr(d, "passes", (d,))) for d, _ in self.sides)
        for k in range(passes):  # a detector's first pass over every face before its second
            found = self._find(gray, k)
            if found is not None:
                return found
        return None

    def _find(self, gray: np.ndarray, k: int) -> Corners | None:
        for inverted, mirrored in self.faces:
            img = 255 - gray if inverted else gray
            if mirrored:
                img = img[:, ::-1]
            img = np.ascontiguousarray(img)
            for detector, first_id in self.sides:
                passes = getattr(detector, "passes", (detector,))
                found = passes[k](img) if k < len(passes) else None
                if found is None:
                    continue
                self.found_as[(inverted, mirrored)] = self.found_as.get((inverted, mirrored), 0) + 1
                pts = found.points
                if mirrored:
                    pts = pts.copy()
                    pts[:, 0] = (gray.shape[1] - 1) - pts[:, 0]
                return Corners(found.ids + first_id, pts)
        return None


def make_detector(board: BoardSpec):
    """A callable image -> Corners | None for the board (built once: the ArUco detector is not free)."""
    if isinstance(board, ChessboardSpec):
        return AnyFaceDetector(board, ChessboardDetector(board))
    if isinstance(board, CharucoSpec):
        return AnyFaceDetector(board, CharucoDetector(dataclasses.replace(board, back_first_marker=None, thickness=0.0)),
                               CharucoDetector(board.back_face()) if board.double_sided else None)
    raise TypeError(f"unknown board type {type(board).__name__}")


def detect(board: BoardSpec, image: np.ndarray) -> Corners | None:
    """Corners of `board` in `image` (grey or RGB), or None when the board is not found."""
    return make_detector(board)(image)
