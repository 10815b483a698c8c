"""Scene primitives and their ray intersection and surface geometry, vectorised over rays.

A primitive lives in the world frame as a small dataclass. For one camera, all primitives of a kind
become one `Batch` in the camera frame, whose methods take many (ray, primitive) pairs at once: the
rays as their undistorted directions (x, y, 1) from the camera centre, so that the ray parameter of
a hit is its depth z along the optical axis, and `j`, the primitive of each pair within the batch.
Evaluating a whole kind in one go keeps the Python overhead per frame independent of the number of
primitives.

- `spheres`: camera-frame spheres enclosing each primitive (from which the renderer finds the
  pixels worth testing);
- `intersect(x, y, j)`: the depth of the first hit (NaN, negative or +inf where the ray misses);
- `surface(x, y, t, j)`: at hit points, the camera-frame unit normal and the texture coordinates
  (u, v) in tiles of the primitive's material.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

TWO_PI = 2.0 * math.pi
F32 = np.float32


def fast_atan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """atan2 to about 1e-5 rad (numpy's own is ~20x slower on float32); texture angles only."""
    ax = np.abs(x)
    ay = np.abs(y)
    mx = np.maximum(ax, ay)
    mn = np.minimum(ax, ay)
    a = mn / (mx + 1e-30)
    s = a * a
    r = a * (0.99997726 + s * (-0.33262347 + s * (0.19354346 + s * (-0.11643287 + s * (0.05265332 + s * -0.01172120)))))
    r = r + (ay > ax) * (math.pi / 2 - 2 * r)
    r = r + (x < 0) * (math.pi - 2 * r)
    return np.copysign(r, y)


def cross3(a, b) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross is slow on tiny arrays)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _orthonormal(axis: np.ndarray, hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to `axis`, the first as close to `hint` as possible."""
    e1 = hint - axis * float(hint @ axis)
    n = math.sqrt(float(e1 @ e1))
    if n < 1e-6:
        e1 = cross3(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        n = math.sqrt(float(e1 @ e1))
    e1 = e1 / n
    return e1, cross3(axis, e1)


def _cols(a: np.ndarray) -> list[np.ndarray]:
    """Columns of an (n, m) table as contiguous float32 arrays (gathered per pair with [j])."""
    a = np.asarray(a, dtype=np.float64).reshape(len(a), -1)
    return [np.ascontiguousarray(a[:, i], dtype=F32) for i in range(a.shape[1])]


@dataclass
class Primitive:
    name: str
    material: str
    person: bool = False


@dataclass
class Ellipsoid(Primitive):
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axes: np.ndarray = field(default_factory=lambda: np.eye(3))  # columns: local x, y, z in the world
    radii: np.ndarray = field(default_factory=lambda: np.ones(3))


@dataclass
class Capsule(Primitive):
    a: np.ndarray = field(default_factory=lambda: np.zeros(3))
    b: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    radius: float = 0.05
    ref: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # side of the texture seam (world)


@dataclass
class Box(Primitive):
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axes: np.ndarray = field(default_factory=lambda: np.eye(3))
    half: np.ndarray = field(default_factory=lambda: np.ones(3) * 0.5)


@dataclass
class BoardFace(Primitive):
    """One face of a thin flat board; board frame as in calibration.boards (z into the board).

    The printed face is seen from the side the board's -z axis points to (`front`); the back face
    from the other side. `extent` = (x0, x1, y0, y1) in board metres; the printed texture maps board
    point (bx, by) to tile coordinates ((bx * ppm + margin_tex) / w, (by * ppm + margin_tex) / h)."""

    R_bw: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_bw: np.ndarray = field(default_factory=lambda: np.zeros(3))
    extent: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)
    front: bool = True
    ppm: float = 1.0
    margin_tex: float = 0.0
    tex_size: tuple[int, int] = (1, 1)


@dataclass
class Room(Primitive):
    """Floor (y = lo), ceiling and four walls, seen from inside (a camera outside sees the far faces
    through the near ones, as in a cut-away set). The renderer solves it in closed form."""

    lo: np.ndarray = field(default_factory=lambda: np.array([-5.0, 0.0, -5.0]))
    hi: np.ndarray = field(default_factory=lambda: np.array([5.0, 3.2, 5.0]))
    # faces in the order -x, +x, floor, ceiling, -z, +z; materials in one atlas shelf at equal stride
    face_materials: tuple[str, ...] = ()


# ---- camera-frame batches -----------------------------------------------------------------------

class Batch:
    """All primitives of one kind in one camera's frame. `ks`: their indices in the scene list."""

    def __init__(self, ks: list[int]):
        self.ks = np.asarray(ks, dtype=np.int64)
        self.sphere_j = np.zeros(0, np.int64)  # which primitive each bounding sphere belongs to
        self.sphere_c = np.zeros((0, 3))
        self.sphere_r = np.zeros(0)


class EllipsoidBatch(Batch):
    def __init__(self, ks, prims: list[Ellipsoid], R, tc, tile_m):
        super().__init__(ks)
        c = np.array([R @ p.center + tc for p in prims])
        Q = np.einsum("ij,njk->nik", R, np.array([p.axes for p in prims]))
        r = np.array([p.radii for p in prims], dtype=np.float64)
        M = np.transpose(Q, (0, 2, 1)) / r[:, :, None]  # camera -> unit-sphere coordinates
        o = np.einsum("nij,nj->ni", M, c)
        self.M = _cols(M.reshape(-1, 9))
        self.o = _cols(o)
        self.cu = _cols((o * o).sum(1) - 1.0)[0]
        self.N = _cols((Q / r[:, None, :]).reshape(-1, 9))  # unit-sphere point -> camera normal
        tu = np.array([t[0] for t in tile_m])
        tv = np.array([t[1] for t in tile_m])
        reps = np.maximum(1, np.round(TWO_PI * np.sqrt(r[:, 0] * r[:, 2]) / tu))
        self.uscale = _cols(reps / TWO_PI)[0]
        self.vscale = _cols(-r[:, 1] / tv)[0]
        self.sphere_j = np.arange(len(prims))
        self.sphere_c = c
        self.sphere_r = r.max(axis=1)

    def _dirs(self, x, y, j):
        M = [m[j] for m in self.M]
        d0 = M[0] * x + M[1] * y + M[2]
        d1 = M[3] * x + M[4] * y + M[5]
        d2 = M[6] * x + M[7] * y + M[8]
        return d0, d1, d2

    def intersect(self, x, y, j):
        d0, d1, d2 = self._dirs(x, y, j)
        o0, o1, o2 = (o[j] for o in self.o)
        a = d0 * d0 + d1 * d1 + d2 * d2
        b = d0 * o0 + d1 * o1 + d2 * o2
        disc = b * b - a * self.cu[j]
        return (b - np.sqrt(disc)) / a

    def surface(self, x, y, t, j):
        d0, d1, d2 = self._dirs(x, y, j)
        q0 = t * d0 - self.o[0][j]
        q1 = t * d1 - self.o[1][j]
        q2 = t * d2 - self.o[2][j]
        N = [n[j] for n in self.N]
        nx = N[0] * q0 + N[1] * q1 + N[2] * q2
        ny = N[3] * q0 + N[4] * q1 + N[5] * q2
        nz = N[6] * q0 + N[7] * q1 + N[8] * q2
        inv = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz)
        u = fast_atan2(q0, q2) * self.uscale[j]
        v = q1 * self.vscale[j]
        return nx * inv, ny * inv, nz * inv, u, v


class CapsuleBatch(Batch):
    def __init__(self, ks, prims: list[Capsule], R, tc, tile_m):
        super().__init__(ks)
        pa = np.array([R @ p.a + tc for p in prims])
        pb = np.array([R @ p.b + tc for p in prims])
        r = np.array([p.radius for p in prims], dtype=np.float64)
        ba = pb - pa
        L = np.linalg.norm(ba, axis=1)
        baba = (ba * ba).sum(1)
        baoa = (ba * -pa).sum(1)
        papa = (pa * pa).sum(1)
        self.ba = _cols(ba)
        self.oa = _cols(-pa)
        self.baba, self.baoa = _cols(baba)[0], _cols(baoa)[0]
        self.c_cyl = _cols(baba * papa - baoa ** 2 - r ** 2 * baba)[0]
        self.c_a = _cols(papa - r ** 2)[0]
        self.c_b = _cols((pb * pb).sum(1) - r ** 2)[0]
        axis = ba / np.maximum(L, 1e-12)[:, None]
        e1, e2 = zip(*(_orthonormal(axis[i], R @ p.ref) for i, p in enumerate(prims)))
        self.pa, self.axis, self.e1, self.e2 = _cols(pa), _cols(axis), _cols(np.array(e1)), _cols(np.array(e2))
        self.L = _cols(L)[0]
        tu = np.array([t[0] for t in tile_m])
        tv = np.array([t[1] for t in tile_m])
        self.uscale = _cols(np.maximum(1, np.round(TWO_PI * r / tu)) / TWO_PI)[0]
        self.vscale = _cols(1.0 / tv)[0]
        n = len(prims)
        self.sphere_j = np.concatenate([np.arange(n), np.arange(n)])
        self.sphere_c = np.concatenate([pa, pb])
        self.sphere_r = np.concatenate([r, r])

    def intersect(self, x, y, j):
        bx, by, bz = (v[j] for v in self.ba)
        ox, oy, oz = (v[j] for v in self.oa)
        baba, baoa = self.baba[j], self.baoa[j]
        rdrd = x * x + y * y + 1.0
        bard = bx * x + by * y + bz
        rdoa = ox * x + oy * y + oz
        a = baba * rdrd - bard * bard
        b = baba * rdoa - baoa * bard
        h = b * b - a * self.c_cyl[j]
        t_cyl = (-b - np.sqrt(h)) / a
        yax = baoa + t_cyl * bard
        t_body = np.where((yax > 0) & (yax < baba), t_cyl, np.nan)
        # end spheres |t d - p|^2 = r^2, with d.(-pa) = rdoa and d.(-pb) = rdoa - bard
        t_a = (-rdoa - np.sqrt(rdoa * rdoa - rdrd * self.c_a[j])) / rdrd
        rdob = rdoa - bard
        t_b = (-rdob - np.sqrt(rdob * rdob - rdrd * self.c_b[j])) / rdrd
        return np.fmin(np.fmin(t_a, t_b), t_body)

    def surface(self, x, y, t, j):
        wx = t * x - self.pa[0][j]
        wy = t * y - self.pa[1][j]
        wz = t - self.pa[2][j]
        ax, ay, az = (v[j] for v in self.axis)
        along = wx * ax + wy * ay + wz * az
        c = np.clip(along, 0.0, self.L[j])
        rx = wx - c * ax
        ry = wy - c * ay
        rz = wz - c * az
        inv = 1.0 / np.sqrt(rx * rx + ry * ry + rz * rz)
        e1x, e1y, e1z = (v[j] for v in self.e1)
        e2x, e2y, e2z = (v[j] for v in self.e2)
        u = fast_atan2(rx * e2x + ry * e2y + rz * e2z, rx * e1x + ry * e1y + rz * e1z) * self.uscale[j]
        v = along * self.vscale[j]
        return rx * inv, ry * inv, rz * inv, u, v


class BoxBatch(Batch):
    def __init__(self, ks, prims: list[Box], R, tc, tile_m):
        super().__init__(ks)
        c = np.array([R @ p.center + tc for p in prims])
        Q = np.einsum("ij,njk->nik", R, np.array([p.axes for p in prims]))
        QT = np.transpose(Q, (0, 2, 1))  # rows: local axes in the camera frame
        self.QT = _cols(QT.reshape(-1, 9))
        self.o = _cols(np.einsum("nij,nj->ni", QT, -c))  # camera centre in box coordinates
        half = np.array([p.half for p in prims], dtype=np.float64)
        self.h = _cols(half)
        self.ih = _cols(1.0 / half)
        self.tu = _cols(1.0 / np.array([t[0] for t in tile_m]))[0]
        self.tv = _cols(-1.0 / np.array([t[1] for t in tile_m]))[0]
        self.sphere_j = np.arange(len(prims))
        self.sphere_c = c
        self.sphere_r = np.linalg.norm(half, axis=1)

    def _local_dirs(self, x, y, j):
        q = [v[j] for v in self.QT]
        return [q[3 * i] * x + q[3 * i + 1] * y + q[3 * i + 2] for i in range(3)]

    def intersect(self, x, y, j):
        tn = tf = None
        with np.errstate(divide="ignore", invalid="ignore"):
            for d, o, h in zip(self._local_dirs(x, y, j), self.o, self.h):
                inv = 1.0 / d
                oj, hj = o[j], h[j]
                t1 = (-hj - oj) * inv
                t2 = (hj - oj) * inv
                lo = np.minimum(t1, t2)
                hi = np.maximum(t1, t2)
                tn = lo if tn is None else np.maximum(tn, lo)
                tf = hi if tf is None else np.minimum(tf, hi)
        return np.where(tn <= tf, tn, np.nan)

    def surface(self, x, y, t, j):
        d = self._local_dirs(x, y, j)
        p = [t * di + o[j] for di, o in zip(d, self.o)]
        a = [np.abs(pi) * ih[j] for pi, ih in zip(p, self.ih)]
        on_x = (a[0] >= a[1]) & (a[0] >= a[2])
        on_y = ~on_x & (a[1] >= a[2])
        on_z = ~(on_x | on_y)
        sx = np.sign(p[0]) * on_x
        sy = np.sign(p[1]) * on_y
        sz = np.sign(p[2]) * on_z
        q = [v[j] for v in self.QT]  # normal = sum_i s_i * (local axis i in camera) = QT rows
        nx = sx * q[0] + sy * q[3] + sz * q[6]
        ny = sx * q[1] + sy * q[4] + sz * q[7]
        nz = sx * q[2] + sy * q[5] + sz * q[8]
        u = (p[0] + (p[2] - p[0]) * on_x) * self.tu[j]
        v = (p[1] + (p[2] - p[1]) * on_y) * self.tv[j]
        return nx, ny, nz, u, v


class BoardBatch(Batch):
    def __init__(self, ks, prims: list[BoardFace], R, tc, tile_m):
        super().__init__(ks)
        Rb = np.array([R @ p.R_bw for p in prims])
        pos = np.array([R @ p.t_bw + tc for p in prims])
        e1, e2, n = Rb[:, :, 0], Rb[:, :, 1], Rb[:, :, 2]
        self.e1, self.e2, self.n = _cols(e1), _cols(e2), _cols(n)
        self.np_ = _cols((n * pos).sum(1))[0]
        self.e1p = _cols((e1 * pos).sum(1))[0]
        self.e2p = _cols((e2 * pos).sum(1))[0]
        ext = np.array([p.extent for p in prims], dtype=np.float64)
        self.ext = _cols(ext)
        self.front = np.array([p.front for p in prims])
        self.side = _cols(np.where(self.front, 1.0, -1.0))[0]
        # printed face: u = (bx * ppm + margin) / w; back face: u = bx / tile
        su = np.array([p.ppm / p.tex_size[0] if p.front else 1.0 / t[0] for p, t in zip(prims, tile_m)])
        sv = np.array([p.ppm / p.tex_size[1] if p.front else 1.0 / t[1] for p, t in zip(prims, tile_m)])
        ou = np.array([p.margin_tex / p.tex_size[0] if p.front else 0.0 for p in prims])
        ov = np.array([p.margin_tex / p.tex_size[1] if p.front else 0.0 for p in prims])
        self.su, self.sv, self.ou, self.ov = (_cols(a)[0] for a in (su, sv, ou, ov))
        corners = np.stack([ext[:, [0, 2]], ext[:, [1, 2]], ext[:, [0, 3]], ext[:, [1, 3]]], axis=1)  # (n, 4, 2)
        mid = corners.mean(axis=1)
        self.sphere_j = np.arange(len(prims))
        self.sphere_c = pos + e1 * mid[:, :1] + e2 * mid[:, 1:]
        self.sphere_r = np.linalg.norm(corners[:, 0] - mid, axis=1)

    def _plane(self, x, y, j):
        n0, n1, n2 = (v[j] for v in self.n)
        denom = n0 * x + n1 * y + n2
        with np.errstate(divide="ignore", invalid="ignore"):
            t = self.np_[j] / denom
        a0, a1, a2 = (v[j] for v in self.e1)
        b0, b1, b2 = (v[j] for v in self.e2)
        bx = t * (a0 * x + a1 * y + a2) - self.e1p[j]
        by = t * (b0 * x + b1 * y + b2) - self.e2p[j]
        return t, bx, by, denom

    def intersect(self, x, y, j):
        t, bx, by, denom = self._plane(x, y, j)
        x0, x1, y0, y1 = (v[j] for v in self.ext)
        ok = (bx >= x0) & (bx <= x1) & (by >= y0) & (by <= y1) & (denom * self.side[j] > 0)
        return np.where(ok, t, np.nan)

    def surface(self, x, y, t, j):
        _t, bx, by, _d = self._plane(x, y, j)
        s = -self.side[j]  # the face's outward normal is -z for the printed face, +z for the back
        n0, n1, n2 = (v[j] for v in self.n)
        u = bx * self.su[j] + self.ou[j]
        v = by * self.sv[j] + self.ov[j]
        return s * n0, s * n1, s * n2, u, v


_BATCHES = ((Ellipsoid, EllipsoidBatch), (Capsule, CapsuleBatch), (Box, BoxBatch), (BoardFace, BoardBatch))


def camera_batches(prims: list[Primitive], R: np.ndarray, tc: np.ndarray, materials: dict) -> list[Batch]:
    """One batch per primitive kind (the room, at index 0, is handled by the renderer)."""
    out = []
    for kind, cls in _BATCHES:
        ks = [k for k in range(1, len(prims)) if type(prims[k]) is kind]
        if ks:
            sel = [prims[k] for k in ks]
            out.append(cls(ks, sel, R, tc, [materials[p.material].tile_m for p in sel]))
    return out
