"""Board corner detection: the corners a camera sees in one image, each with its board corner id.

Chessboards: `findChessboardCorners` + `cornerSubPix` (falling back to `findChessboardCornersSB`),
then a canonical corner order. A chessboard with cols != rows looks the same after a half turn, so the
detector may return its corners in either order; we pick the order whose first corner is nearest the
image's top-left (first-to-last corner vector pointing right/down), so that cameras of a rig that stand
upright side by side agree on which corner is id 0.

ChArUco: `cv2.aruco.CharucoDetector`; the markers identify every corner, so partial views are used as
they are (any corners with ids, at least `min_corners`, not all on one line).
"""
from __future__ import annotations

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
        gray = to_gray(image)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, pts = cv2.findChessboardCorners(gray, self.pattern, flags=flags)
        if found:
            win = _subpix_window(pts.reshape(-1, 2), self.board.cols)
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.001)
            pts = cv2.cornerSubPix(gray, pts.astype(np.float32), (win, win), (-1, -1), crit)
        else:
            # The sector-based detector finds boards the classic one misses (blur, low contrast).
            found, pts = cv2.findChessboardCornersSB(gray, self.pattern, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
            if not found:
                return None
        pts = canonical_chessboard_order(pts)
        return Corners(np.arange(self.board.n_corners), pts)


class CharucoDetector:
    def __init__(self, board: CharucoSpec, min_corners: int = MIN_CHARUCO_CORNERS):
        self.board = board
        self.min_corners = max(4, min_corners)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
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
        keep = np.ones(len(ids), dtype=bool)
        homographies = []
        for mc, mid in zip(marker_corners, np.asarray(marker_ids).reshape(-1)):
            obj = self._marker_xy[int(mid)]
            H, _ = cv2.findHomography(obj, np.asarray(mc, dtype=np.float64).reshape(4, 2), 0)
            if H is not None:
                homographies.append((obj.mean(axis=0), H))
        if not homographies:
            return ids, pts
        centres = np.array([c for c, _ in homographies])
        for k, (cid, p) in enumerate(zip(ids, pts)):
            xy = self._object[cid, :2]
            near = np.flatnonzero(np.linalg.norm(centres - xy, axis=1) < reach)
            if len(near) == 0:
                continue
            preds = []
            scale = []
            for m in near:
                H = homographies[m][1]
                q = H @ np.array([xy[0], xy[1], 1.0])
                q2 = H @ np.array([xy[0] + square, xy[1], 1.0])
                preds.append(q[:2] / q[2])
                scale.append(np.linalg.norm(q2[:2] / q2[2] - q[:2] / q[2]))
            pred = np.median(np.array(preds), axis=0)
            limit = max(1.5, 0.08 * float(np.median(scale)))
            if np.linalg.norm(pred - p) > limit:
                keep[k] = False
        return ids[keep], pts[keep]


def _collinear(xy: np.ndarray) -> bool:
    c = xy - xy.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    return bool(s.size < 2 or s[1] < 1e-6 * max(s[0], 1e-12) or s[1] < 1e-9)


def make_detector(board: BoardSpec):
    """A callable image -> Corners | None for the board (built once: the ArUco detector is not free)."""
    if isinstance(board, ChessboardSpec):
        return ChessboardDetector(board)
    if isinstance(board, CharucoSpec):
        return CharucoDetector(board)
    raise TypeError(f"unknown board type {type(board).__name__}")


def detect(board: BoardSpec, image: np.ndarray) -> Corners | None:
    """Corners of `board` in `image` (grey or RGB), or None when the board is not found."""
    return make_detector(board)(image)
