"""Choosing calibration views while the board is shown to the rig: keep a view only when it adds
something: a part of some camera's image the board has not covered yet, or a board pose unlike every
view kept so far (a different place, size, or tilt in the image), whether one camera sees it or
several."""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calibration.detect import Corners

GRID = (8, 6)


@dataclass
class _CameraState:
    size: tuple[int, int]
    seen: np.ndarray  # (rows, cols) bool: grid cells the board has covered
    kept: list[Corners] = field(default_factory=list)


@dataclass
class Verdict:
    keep: bool
    reason: str
    cameras: list[str]  # cameras that saw the board
    new_cells: dict[str, int]  # cells added per camera (when kept)


class ViewSelector:
    """Decides, one synchronised view at a time, whether the view is worth keeping.

    `novelty` is the mean corner displacement, as a fraction of the image diagonal, that makes a view
    different from a kept one (compared on the corners both share; a view sharing under half of its
    corners with a kept one differs from it too).
    """

    def __init__(self, sizes: dict[str, tuple[int, int]], novelty: float = 0.05, min_corners: int = 6):
        self.cams = {name: _CameraState(size, np.zeros((GRID[1], GRID[0]), bool)) for name, size in sizes.items()}
        self.novelty = novelty
        self.min_corners = min_corners
        self.kept = 0
        self.views: list[list[str]] = []  # the cameras that saw the board, per kept view

    def _cells(self, name: str, corners: Corners) -> np.ndarray:
        w, h = self.cams[name].size
        scale = 8
        mask = np.zeros((max(1, h // scale), max(1, w // scale)), np.uint8)
        hull = cv2.convexHull((corners.points / scale).astype(np.float32))
        cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
        gx, gy = GRID
        mh, mw = mask.shape
        cells = np.zeros((gy, gx), bool)
        for j in range(gy):
            for i in range(gx):
                block = mask[j * mh // gy : (j + 1) * mh // gy, i * mw // gx : (i + 1) * mw // gx]
                cells[j, i] = block.size > 0 and block.mean() >= 0.5
        return cells

    def _is_novel(self, name: str, corners: Corners) -> bool:
        st = self.cams[name]
        diag = float(np.hypot(*st.size))
        for old in st.kept:
            common, ia, ib = np.intersect1d(corners.ids, old.ids, return_indices=True)
            if len(common) < 0.5 * len(corners):
                continue
            shift = float(np.mean(np.linalg.norm(corners.points[ia] - old.points[ib], axis=1)))
            if shift < self.novelty * diag:
                return False
        return True

    def consider(self, detections: dict[str, Corners | None], force: bool = False) -> Verdict:
        """Keep the view when it adds something; `force` keeps any view in which the board is seen
        (a view taken by hand: the operator knows why)."""
        seen = {n: c for n, c in detections.items() if c is not None and len(c) >= self.min_corners and n in self.cams}
        if not seen:
            return Verdict(False, "board not seen", [], {})
        new_cells = {n: int((self._cells(n, c) & ~self.cams[n].seen).sum()) for n, c in seen.items()}
        novel = [n for n, c in seen.items() if self._is_novel(n, c)]
        adds_cells = [n for n, k in new_cells.items() if k > 0]
        # A view one camera sees alone still pins down that camera's lens (a new place in its image,
        # or a new tilt, which separates focal length from distance); it is kept like a shared one.
        if adds_cells or novel:
            reason = "new coverage in " + ", ".join(adds_cells) if adds_cells else "new board pose in " + ", ".join(novel)
        elif force:
            reason = "kept by hand"
        else:
            return Verdict(False, "nothing new", sorted(seen), {})
        for n, c in seen.items():
            self.cams[n].seen |= self._cells(n, c)
            self.cams[n].kept.append(c)
        self.kept += 1
        self.views.append(sorted(seen))
        return Verdict(True, reason, sorted(seen), new_cells)

    def coverage(self) -> dict[str, float]:
        """Share of each camera's image (GRID cells) the kept views' boards have covered."""
        return {n: round(float(st.seen.mean()), 3) for n, st in self.cams.items()}

    def cells(self) -> dict[str, list[list[bool]]]:
        """Each camera's covered GRID cells (rows of columns), as a coverage map shows them."""
        return {n: st.seen.tolist() for n, st in self.cams.items()}

    def views_per_camera(self) -> dict[str, int]:
        return {n: len(st.kept) for n, st in self.cams.items()}

    def pairs(self) -> dict[tuple[str, str], int]:
        """Kept views each pair of cameras saw together (what ties their poses to each other)."""
        names = list(self.cams)
        return {(a, b): sum(1 for v in self.views if a in v and b in v) for i, a in enumerate(names) for b in names[i + 1:]}
