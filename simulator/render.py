"""Ray-casting renderer with exact ground truth: RGB, depth (z along the optical axis), person mask.

How it stays fast in numpy:
- each pixel's ray is its exactly undistorted direction (x, y, 1), cached per camera, so the ray
  parameter of a hit is the depth itself and lens distortion costs nothing per frame;
- the room is solved in closed form; every other primitive is tested only on the pixels its
  bounding spheres can reach (a rectangle found from the per-column and per-row range of the
  cached rays, which holds under any distortion), all primitives of a kind in one vectorised call;
- shading is deferred: a z-buffer pass, then each primitive shades only the pixels it won;
- the room and props never move, so each camera draws them once and keeps the result; a frame
  draws only people and board over it;
- textures come from a mip-mapped atlas (cv2.remap, trilinear, level from the pixel footprint on
  the surface), so fine texture, the board's corners included, is filtered rather than aliased;
- anti-aliasing supersamples (s x s rays, box filter) only pixels on a silhouette, found where the
  primitive id changes between neighbours. Depth, ids and mask are those of the pixel centre.
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from calibration.camera import CameraModel
from simulator.errors import SimulatorError
from simulator.primitives import camera_batches
from simulator.scene import Scene, check_time

NEAR = 0.01  # metres: nothing closer to the camera is drawn
DEFAULT_ANTIALIAS = 3
DEFAULT_PSF = 0.5  # pixels: Gaussian sigma of the lens blur (real lenses are never perfectly sharp)
SHADOW_STRENGTH = 0.45
SHADOW_RADIUS = 0.75  # metres: extent of a person's contact shadow on the floor


@dataclass
class Render:
    """One rendered view. `ids` index `labels` (-1 where no surface); `radiance` is the linear image
    before quantisation (1.0 = 255), which the sensor model exposes; `normals` (camera frame, unit)
    only when asked for."""

    rgb: np.ndarray
    depth: np.ndarray
    mask: np.ndarray
    ids: np.ndarray
    labels: list
    radiance: np.ndarray
    normals: Optional[np.ndarray] = None


# ---- camera rays ---------------------------------------------------------------------------------

def check_camera(camera: CameraModel) -> None:
    """Raise SimulatorError for a camera the renderer cannot use."""
    if not isinstance(camera, CameraModel):
        raise SimulatorError(f"expected a CameraModel, got {type(camera).__name__}")
    if camera.width <= 0 or camera.height <= 0:
        raise SimulatorError(f"camera {camera.name}: image size must be positive, got {camera.width}x{camera.height}")
    if not np.all(np.isfinite(camera.K)) or camera.fx <= 0 or camera.fy <= 0:
        raise SimulatorError(f"camera {camera.name}: focal lengths must be positive and finite, got fx={camera.fx} fy={camera.fy}")
    if not (np.all(np.isfinite(camera.dist)) and np.all(np.isfinite(camera.R)) and np.all(np.isfinite(camera.t))):
        raise SimulatorError(f"camera {camera.name}: distortion and pose must be finite")
    if not np.allclose(camera.R @ camera.R.T, np.eye(3), atol=1e-6) or np.linalg.det(camera.R) < 0:
        raise SimulatorError(f"camera {camera.name}: R is not a rotation matrix")


def _distortion_jacobian(cam: CameraModel, x: np.ndarray, y: np.ndarray):
    d = np.zeros(5)
    d[: min(5, cam.dist.size)] = cam.dist[:5]
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    g = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d(rad)/d(r2)
    a = rad + 2 * x * x * g + 2 * p1 * y + 6 * p2 * x
    b = 2 * x * y * g + 2 * p1 * x + 2 * p2 * y
    d_ = rad + 2 * y * y * g + 6 * p1 * y + 2 * p2 * x
    return a, b, b, d_


class CameraRays:
    """Undistorted ray directions of every pixel centre of one camera, and their ranges."""

    def __init__(self, cam: CameraModel):
        H, W = cam.height, cam.width
        u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
        yd = (v - cam.cy) / cam.fy
        xd = (u - cam.cx - cam.K[0, 1] * yd) / cam.fx
        xy = np.stack([xd, yd], axis=-1)
        if cam.has_distortion:
            # Newton's method on the distortion polynomial: every ray exact to ~1e-12.
            for it in range(30):
                dxy = cam.distort_normalized(xy)
                ex, ey = dxy[..., 0] - xd, dxy[..., 1] - yd
                if it >= 3 and max(np.abs(ex).max(), np.abs(ey).max()) < 1e-13:
                    break
                a, b, c, d = _distortion_jacobian(cam, xy[..., 0], xy[..., 1])
                det = a * d - b * c
                xy[..., 0] -= (d * ex - b * ey) / det
                xy[..., 1] -= (a * ey - c * ex) / det
            res = np.abs(cam.distort_normalized(xy) - np.stack([xd, yd], axis=-1)).max()
            if not np.isfinite(res) or res * max(cam.fx, cam.fy) > 1e-6:
                raise SimulatorError(f"camera {cam.name}: the distortion cannot be inverted over the image "
                                     f"(residual {res * max(cam.fx, cam.fy):.2g} px); it folds over inside the frame")
        self.width, self.height = W, H
        self.X = np.ascontiguousarray(xy[..., 0], dtype=np.float32)
        self.Y = np.ascontiguousarray(xy[..., 1], dtype=np.float32)
        self.Xf, self.Yf = self.X.ravel(), self.Y.ravel()
        self.col_min = self.X.min(axis=0).astype(np.float64)
        self.col_max = self.X.max(axis=0).astype(np.float64)
        self.row_min = self.Y.min(axis=1).astype(np.float64)
        self.row_max = self.Y.max(axis=1).astype(np.float64)
        self.monotonic = all(np.all(np.diff(a) >= 0) for a in (self.col_min, self.col_max, self.row_min, self.row_max))
        self.f = math.sqrt(cam.fx * cam.fy)

    def _span(self, lo, hi, a0, a1):
        """Index ranges [i0, i1) of the entries whose [a0, a1] range meets [lo, hi]."""
        if self.monotonic:
            return np.searchsorted(a1, lo, "left"), np.searchsorted(a0, hi, "right")
        i0 = np.zeros(lo.shape, np.int64)
        i1 = np.zeros(lo.shape, np.int64)
        for n in range(lo.size):
            hit = np.flatnonzero((a1 >= lo[n]) & (a0 <= hi[n]))
            if hit.size:
                i0[n], i1[n] = hit[0], hit[-1] + 1
        return i0, i1

    def boxes(self, batch) -> np.ndarray:
        """Pixel rectangles (n, 4): v0, v1, u0, u1 (ends exclusive) holding every pixel whose ray can
        meet each primitive of the batch; empty rectangles (v0 >= v1) where none can."""
        return self.sphere_boxes(batch.sphere_c, batch.sphere_r, batch.sphere_j, len(batch.ks))

    def sphere_boxes(self, c, r, j, n) -> np.ndarray:
        """As `boxes`, for n objects each enclosed by the camera-frame spheres (c[i], r[i]) with j[i]
        naming the object."""
        c = np.asarray(c, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(r, dtype=np.float64).ravel()
        cx, cy, cz = c[:, 0], c[:, 1], c[:, 2]
        den = np.maximum(cz * cz - r * r, 1e-12)
        sx = r * np.sqrt(np.maximum(cx * cx + den, 0.0))
        sy = r * np.sqrt(np.maximum(cy * cy + den, 0.0))
        x0 = (cx * cz - sx) / den
        x1 = (cx * cz + sx) / den
        y0 = (cy * cz - sy) / den
        y1 = (cy * cz + sy) / den
        behind = cz + r <= NEAR
        crossing = ~behind & (cz - r <= NEAR)
        x0[behind] = y0[behind] = np.inf
        x1[behind] = y1[behind] = -np.inf
        x0[crossing] = y0[crossing] = -np.inf
        x1[crossing] = y1[crossing] = np.inf
        lo_x = np.full(n, np.inf)
        hi_x = np.full(n, -np.inf)
        lo_y = np.full(n, np.inf)
        hi_y = np.full(n, -np.inf)
        np.minimum.at(lo_x, j, x0)
        np.maximum.at(hi_x, j, x1)
        np.minimum.at(lo_y, j, y0)
        np.maximum.at(hi_y, j, y1)
        u0, u1 = self._span(lo_x, hi_x, self.col_min, self.col_max)
        v0, v1 = self._span(lo_y, hi_y, self.row_min, self.row_max)
        out = np.stack([v0, v1, u0, u1], axis=1).astype(np.int64)
        empty = (u0 >= u1) | (v0 >= v1)
        out[empty] = 0
        return out


_RAYS: OrderedDict = OrderedDict()
_RAYS_LOCK = threading.Lock()


def camera_rays(cam: CameraModel) -> CameraRays:
    """The cached rays of a camera (keyed by its intrinsics and size, not its pose)."""
    key = (cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes())
    with _RAYS_LOCK:
        rays = _RAYS.get(key)
        if rays is not None:
            _RAYS.move_to_end(key)
            return rays
    rays = CameraRays(cam)
    with _RAYS_LOCK:
        _RAYS[key] = rays
        while len(_RAYS) > 16:
            _RAYS.popitem(last=False)
    return rays


# ---- shading -------------------------------------------------------------------------------------

class _Shader:
    """Lights, materials and the room for one (scene, camera, time); shades flat arrays of rays."""

    def __init__(self, scene: Scene, cam: CameraModel, rays: CameraRays, prims: list, t: float):
        self.atlas = scene.atlas
        self.R = cam.R
        self.C = cam.center
        self.inv_f = 1.0 / rays.f
        self.ambient = float(scene.ambient)
        self.lights_w = [(np.asarray(d, float), float(k)) for d, k in scene.lights]
        self.lights_c = [([float(v) for v in cam.R @ d], k) for d, k in self.lights_w]
        self.shadows = scene.ground_positions(t)
        room = scene.room
        self.lo = [float(v) for v in room.lo]
        self.hi = [float(v) for v in room.hi]
        mats = [scene.atlas.materials[m] for m in room.face_materials]
        self.room_mat = mats[0]
        self.room_stride = mats[1].x - mats[0].x
        if any(m.x != mats[0].x + k * self.room_stride or m.y != mats[0].y or m.w != mats[0].w for k, m in enumerate(mats)):
            raise RuntimeError("room textures must share one atlas shelf at equal stride")
        # per-primitive material table (index k of the scene list; row 0, the room, unused)
        table = np.zeros((len(prims), 6), np.float64)
        for k, p in enumerate(prims[1:], 1):
            m = scene.atlas.materials[p.material]
            table[k] = (m.x - 0.5, m.y - 0.5, m.w, m.h, m.texels_per_metre * self.inv_f, 1.0 if m.wrap else 0.0)
        self.mat = [np.ascontiguousarray(table[:, i], dtype=np.float32) for i in range(6)]

    # the room: the exit point of each ray from the axis-aligned box
    def _room_dirs(self, x, y):
        R = self.R
        return [float(R[0, i]) * x + float(R[1, i]) * y + float(R[2, i]) for i in range(3)]

    def room_intersect(self, x, y):
        ts = []
        with np.errstate(divide="ignore", invalid="ignore"):
            for D, lo, hi, c in zip(self._room_dirs(x, y), self.lo, self.hi, self.C):
                ts.append(((lo - float(c)) + (hi - lo) * (D > 0)) / D)
        return np.minimum(np.minimum(ts[0], ts[1]), ts[2])

    def room_shade(self, x, y, t, want_normals=False, shadows=True):
        Dx, Dy, Dz = self._room_dirs(x, y)
        with np.errstate(divide="ignore", invalid="ignore"):
            ts = [((lo - float(c)) + (hi - lo) * (D > 0)) / D for D, lo, hi, c in zip((Dx, Dy, Dz), self.lo, self.hi, self.C)]
        on_x = (ts[0] <= ts[1]) & (ts[0] <= ts[2])
        on_y = ~on_x & (ts[1] <= ts[2])
        on_z = ~(on_x | on_y)
        fx, fy, fz = (a.astype(np.float32) for a in (on_x, on_y, on_z))
        Cx, Cy, Cz = (float(c) for c in self.C)
        Px = Cx + t * Dx
        Py = Cy + t * Dy
        Pz = Cz + t * Dz
        Dsel = Dx * fx + Dy * fy + Dz * fz
        positive = Dsel > 0
        fp = positive.astype(np.float32)
        code = fy * 2.0 + fz * 4.0 + fp  # -x, +x, floor, ceiling, -z, +z
        m = self.room_mat
        u = (Px + (Pz - Px) * fx) * (1.0 / m.tile_m[0])
        v = (Py + (Pz - Py) * fy) * (-1.0 / m.tile_m[1])
        u -= np.floor(u)
        v -= np.floor(v)
        ax = (m.x - 0.5) + self.room_stride * code + u * m.w
        ay = (m.y - 0.5) + v * m.h
        sgn = 1.0 - 2.0 * fp  # the face normal is -sign(D) along the face's axis
        lum = np.full(np.shape(x), self.ambient, np.float32)
        for (L, k) in self.lights_w:
            lum += k * np.maximum(sgn * (float(L[0]) * fx + float(L[1]) * fy + float(L[2]) * fz), 0.0)
        floor = on_y & ~positive
        if shadows and self.shadows:
            idx = np.flatnonzero(floor)
            if idx.size:
                lum.ravel()[idx] *= self.shadow_factor(Px.ravel()[idx], Pz.ravel()[idx])
        dd = x * x + y * y + 1.0
        nd = np.maximum(np.abs(Dsel), 0.05 * np.sqrt(dd))
        lod = self._lod(t, m.texels_per_metre * self.inv_f, nd, dd)
        normals = None
        if want_normals:
            nw = [sgn * fx, sgn * fy, sgn * fz]
            R = self.R
            normals = [float(R[i, 0]) * nw[0] + float(R[i, 1]) * nw[1] + float(R[i, 2]) * nw[2] for i in range(3)]
        return ax, ay, lod, lum, normals, floor

    def shadow_factor(self, px, pz, people=None):
        """Soft contact shadows of the people (default: all) on the floor at floor points (px, pz)."""
        shade = np.ones(px.shape, np.float32)
        k = 1.0 / SHADOW_RADIUS ** 2
        for (gx, gz) in (self.shadows if people is None else people):
            w = np.maximum(1.0 - ((px - gx) ** 2 + (pz - gz) ** 2) * k, 0.0)
            shade *= 1.0 - SHADOW_STRENGTH * (w * w)
        return shade

    def floor_points(self, x, y, t):
        Dx, _Dy, Dz = self._room_dirs(x, y)
        return float(self.C[0]) + t * Dx, float(self.C[2]) + t * Dz

    @staticmethod
    def _lod(t, tpf, nd, dd):
        # Texels per pixel: the pixel's footprint on the surface is t / (f |n.d|) along the tilt and
        # t / (f |d|) across it; the mip level uses their geometric mean. tpf = texels per metre / f.
        rho2 = (t * tpf) ** 2 / (nd * np.sqrt(dd))
        return 0.5 * np.log2(np.maximum(rho2, 1e-12))

    def surface_shade(self, nx, ny, nz, u, v, x, y, t, k):
        mx, my, mw, mh, tpf, wrap = (a[k] for a in self.mat)
        u = u - np.floor(u) * wrap
        v = v - np.floor(v) * wrap
        ax = mx + u * mw
        ay = my + v * mh
        dd = x * x + y * y + 1.0
        nd = np.maximum(np.abs(nx * x + ny * y + nz), 0.05 * np.sqrt(dd))
        lod = self._lod(t, tpf, nd, dd)
        lum = np.full(x.shape, self.ambient, np.float32)
        for (L, kk) in self.lights_c:
            lum += kk * np.maximum(nx * L[0] + ny * L[1] + nz * L[2], 0.0)
        return ax, ay, lod, lum


# ---- tracing -------------------------------------------------------------------------------------

def _box_pairs(batch, boxes, J, W):
    """(ray, primitive) pairs for every pixel in the rectangles of the batch's primitives J."""
    b = boxes[J]
    area = (b[:, 1] - b[:, 0]) * (b[:, 3] - b[:, 2])
    keep = area > 0
    J, b, area = J[keep], b[keep], area[keep]
    total = int(area.sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    jj = np.repeat(J, area)
    off = np.arange(total) - np.repeat(np.cumsum(area) - area, area)
    bw = np.repeat(b[:, 3] - b[:, 2], area)
    r = (np.repeat(b[:, 0], area) + off // bw) * W + np.repeat(b[:, 2], area) + off % bw
    return r, jj


def _trace(pairs, xs, ys, z, ids):
    """Z-buffer (ray, primitive) pairs [(batch, rays, js)] into z and ids (flat). Returns the pairs
    that won their ray, per batch."""
    hits = []
    for b, r, j in pairs:
        if r.size == 0:
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            t = b.intersect(xs[r], ys[r], j)
            ok = (t > NEAR) & (t < z[r])
        r, j, t = r[ok], j[ok], t[ok]
        np.minimum.at(z, r, t)
        hits.append((b, r, j, t))
    won = []
    for b, r, j, t in hits:
        w = t == z[r]
        r, j = r[w], j[w]
        ids[r] = b.ks[j]
        won.append((b, r, j))
    return won


def _shade_won(shader, won, xs, ys, z, nrm=None):
    """Colours of the rays each batch won: (rays, colours)."""
    parts = []
    for b, r, j in won:
        if r.size == 0:
            continue
        x, y, t = xs[r], ys[r], z[r]
        with np.errstate(invalid="ignore", divide="ignore"):
            nx, ny, nz, u, v = b.surface(x, y, t, j)
            parts.append((r, shader.surface_shade(nx, ny, nz, u, v, x, y, t, b.ks[j])))
        if nrm is not None:
            nrm[0, r], nrm[1, r], nrm[2, r] = nx, ny, nz
    if not parts:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
    r = np.concatenate([p[0] for p in parts])
    ax, ay, lod, lum = (np.concatenate([p[1][i] for p in parts]) for i in range(4))
    return r, shader.atlas.sample(ax, ay, lod) * lum[:, None]


def _edges(ids):
    edge = np.zeros(ids.shape, bool)
    dh = ids[:, 1:] != ids[:, :-1]
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    dv = ids[1:, :] != ids[:-1, :]
    edge[1:, :] |= dv
    edge[:-1, :] |= dv
    return edge


def _supersample(shader, batches, ids, rays, ep, s, kmax, shadows):
    """Box-filtered colour of pixels `ep` (flat indices) from s x s rays each, against the room and
    those of primitives 1 .. kmax-1 that the pixel-centre ids (flat) show around each pixel."""
    n_prims = max(int(b.ks.max()) for b in batches) + 1 if batches else 1
    batch_of = np.full(n_prims, -1, np.int64)
    local_of = np.zeros(n_prims, np.int64)
    for bi, b in enumerate(batches):
        batch_of[b.ks] = bi
        local_of[b.ks] = np.arange(len(b.ks))
    H, W = rays.height, rays.width
    Xf, Yf = rays.Xf, rays.Yf
    vp = ep // W
    up = ep % W
    # Local derivatives of the undistorted rays give the sub-pixel rays to first order (the
    # second-order term is ~1e-6 px for any realistic lens).
    ul = np.maximum(up - 1, 0)
    ur = np.minimum(up + 1, W - 1)
    vl = np.maximum(vp - 1, 0)
    vr = np.minimum(vp + 1, H - 1)
    du_n = np.maximum(ur - ul, 1).astype(np.float32)
    dv_n = np.maximum(vr - vl, 1).astype(np.float32)
    Xu = (Xf[vp * W + ur] - Xf[vp * W + ul]) / du_n
    Yu = (Yf[vp * W + ur] - Yf[vp * W + ul]) / du_n
    Xv = (Xf[vr * W + up] - Xf[vl * W + up]) / dv_n
    Yv = (Yf[vr * W + up] - Yf[vl * W + up]) / dv_n
    off = ((np.arange(s) + 0.5) / s - 0.5).astype(np.float32)
    ou = np.tile(off, s)
    ov = np.repeat(off, s)
    S = s * s
    xs = (Xf[ep][:, None] + Xu[:, None] * ou + Xv[:, None] * ov).ravel()
    ys = (Yf[ep][:, None] + Yu[:, None] * ou + Yv[:, None] * ov).ravel()
    with np.errstate(invalid="ignore", divide="ignore"):
        z = shader.room_intersect(xs, ys)
    sid = np.where(z > NEAR, 0, -1).astype(np.int16)
    z[sid < 0] = np.inf
    # Candidates of a pixel's sub-rays: the primitives seen at the centres of it and its eight
    # neighbours (a silhouette inside the pixel shows at a neighbouring centre).
    near = np.stack([ids[vv * W + uu] for vv in (vl, vp, vr) for uu in (ul, up, ur)], axis=1)
    near.sort(axis=1)
    first = np.ones(near.shape, bool)
    first[:, 1:] = near[:, 1:] != near[:, :-1]
    first &= (near > 0) & (near < kmax)
    pix, col = np.nonzero(first)
    cand = near[pix, col].astype(np.int64)
    pairs = []
    sub = np.arange(S)
    for bi, b in enumerate(batches):
        sel = np.flatnonzero(batch_of[cand] == bi)
        if sel.size:
            pairs.append((b, (pix[sel, None] * S + sub).ravel(), np.repeat(local_of[cand[sel]], S)))
    won = _trace(pairs, xs, ys, z, sid)
    N = xs.size
    colour = np.zeros((N, 3), np.float32)
    room = np.flatnonzero(sid == 0)
    if room.size:
        with np.errstate(invalid="ignore", divide="ignore"):
            ax, ay, lod, lum, _n, _f = shader.room_shade(xs[room], ys[room], z[room], shadows=shadows)
        colour[room] = shader.atlas.sample(ax, ay, lod) * lum[:, None]
    r, col = _shade_won(shader, won, xs, ys, z)
    colour[r] = col
    return colour.reshape(-1, S, 3).mean(axis=1)


# ---- rendering -----------------------------------------------------------------------------------

class _StaticLayer:
    """The room and props as one camera sees them: they never move, so they are drawn once."""

    def __init__(self, shader, batches, boxes, rays, nst, s, normals):
        H, W = rays.height, rays.width
        n = H * W
        X, Y = rays.X, rays.Y
        with np.errstate(invalid="ignore", divide="ignore"):
            t_room = shader.room_intersect(X, Y).ravel()
        ids = np.where(t_room > NEAR, 0, -1).astype(np.int16)
        z = np.where(ids >= 0, t_room, np.inf).astype(np.float32)
        pairs = []
        for b, bx in zip(batches, boxes):
            J = np.flatnonzero(b.ks < nst)
            if J.size:
                pairs.append((b, *_box_pairs(b, bx, J, W)))
        won = _trace(pairs, rays.Xf, rays.Yf, z, ids)
        nrm = np.zeros((3, n), np.float32) if normals else None
        with np.errstate(invalid="ignore", divide="ignore"):
            ax, ay, lod, lum, rn, floor = shader.room_shade(X, Y, t_room.reshape(H, W), normals, shadows=False)
        colour = shader.atlas.sample(ax, ay, lod).reshape(n, 3)
        colour *= np.where(ids == 0, lum.ravel(), 0.0)[:, None]
        if normals:
            for i in range(3):
                nrm[i] = rn[i].ravel()
        r, col = _shade_won(shader, won, rays.Xf, rays.Yf, z, nrm)
        colour[r] = col
        if s > 1:
            ep = np.flatnonzero(_edges(ids.reshape(H, W)))
            if ep.size:
                colour[ep] = _supersample(shader, batches, ids, rays, ep, s, nst, shadows=False)
        self.z, self.ids, self.colour, self.normals = z, ids, colour, nrm
        self.floor = floor.ravel() & (ids == 0)
        # world (x, z) of the floor seen at each pixel, where the people's contact shadows fall
        self.floor_x, self.floor_z = (a.ravel().astype(np.float32) for a in shader.floor_points(X, Y, t_room.reshape(H, W)))


def _static_layer(scene, camera, shader, batches, boxes, rays, s, normals) -> _StaticLayer:
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(), camera.R.tobytes(),
           camera.t.tobytes(), s, normals)
    cache = scene.static_layers
    with scene.lock:
        layer = cache.get(key)
        if layer is not None:
            cache.move_to_end(key)
            return layer
    layer = _StaticLayer(shader, batches, boxes, rays, scene.static_count, s, normals)
    with scene.lock:
        cache[key] = layer
        while len(cache) > 12:
            cache.popitem(last=False)
    return layer


def render(scene: Scene, camera: CameraModel, t: float, *, antialias: Optional[int] = None, normals: bool = False,
           psf: float = DEFAULT_PSF) -> Render:
    """Render `scene` at time `t` (seconds) through `camera`.

    antialias: s for s x s supersampling of silhouette pixels (1 = off; None = 3).
    normals: also return per-pixel camera-frame unit normals.
    psf: Gaussian sigma (pixels) of the lens blur applied to the image, not to depth, ids or mask.
    Without it, edges one pixel wide make sub-pixel corner detectors lock onto pixel positions.
    The static part of the scene (room, props) is drawn once per camera and kept in the scene.
    """
    check_camera(camera)
    t = check_time(t)
    s = DEFAULT_ANTIALIAS if antialias is None else antialias
    if not isinstance(s, (int, np.integer)) or isinstance(s, bool) or not 1 <= s <= 8:
        raise SimulatorError(f"antialias must be an integer from 1 to 8, got {antialias!r}")
    try:
        psf = float(psf)
    except (TypeError, ValueError):
        raise SimulatorError(f"psf must be a number of pixels, got {psf!r}") from None
    if not 0 <= psf <= 10:
        raise SimulatorError(f"psf must be between 0 and 10 pixels, got {psf}")
    rays = camera_rays(camera)
    H, W = camera.height, camera.width
    prims = scene.primitives(t)
    nst = scene.static_count
    shader = _Shader(scene, camera, rays, prims, t)
    batches = camera_batches(prims, camera.R, camera.t, scene.atlas.materials)
    boxes = [rays.boxes(b) for b in batches]
    static = _static_layer(scene, camera, shader, batches, boxes, rays, s, normals)

    z = static.z.copy()
    ids = static.ids.copy()
    pairs = []
    for b, bx in zip(batches, boxes):
        J = np.flatnonzero(b.ks >= nst)
        if J.size:
            pairs.append((b, *_box_pairs(b, bx, J, W)))
    won = _trace(pairs, rays.Xf, rays.Yf, z, ids)
    colour = static.colour.copy()
    nrm = static.normals.copy() if normals else None
    r, col = _shade_won(shader, won, rays.Xf, rays.Yf, z, nrm)
    colour[r] = col

    # contact shadows on the floor around each person
    # (each person darkens the floor within its own rectangle; where they overlap, the factors multiply)
    for gx, gz in shader.shadows:
        c = camera.R @ np.array([gx, 0.0, gz]) + camera.t
        v0, v1, u0, u1 = (int(a) for a in rays.sphere_boxes(c, [SHADOW_RADIUS], [0], 1)[0])
        if v0 >= v1:
            continue
        local = np.flatnonzero(static.floor.reshape(H, W)[v0:v1, u0:u1] & (ids.reshape(H, W)[v0:v1, u0:u1] == 0))
        bw = u1 - u0
        fi = (v0 + local // bw) * W + (u0 + local % bw)
        colour[fi] *= shader.shadow_factor(static.floor_x[fi], static.floor_z[fi], [(gx, gz)])[:, None]

    # re-filter the silhouettes the moving primitives changed (static ones are filtered already)
    dyn = [bx[b.ks >= nst] for b, bx in zip(batches, boxes)]
    dyn = np.concatenate(dyn) if dyn else np.zeros((0, 4), np.int64)
    dyn = dyn[dyn[:, 0] < dyn[:, 1]]
    if s > 1 and dyn.size:
        v0 = max(int(dyn[:, 0].min()) - 2, 0)
        v1 = min(int(dyn[:, 1].max()) + 2, H)
        u0 = max(int(dyn[:, 2].min()) - 2, 0)
        u1 = min(int(dyn[:, 3].max()) + 2, W)
        ids_r = ids.reshape(H, W)[v0:v1, u0:u1]
        changed = (ids_r != static.ids.reshape(H, W)[v0:v1, u0:u1]).view(np.uint8)
        changed = cv2.dilate(changed, np.ones((3, 3), np.uint8)).view(bool)
        local = np.flatnonzero(_edges(ids_r) & changed)
        if local.size:
            bw = u1 - u0
            ep = (v0 + local // bw) * W + (u0 + local % bw)
            colour[ep] = _supersample(shader, batches, ids, rays, ep, s, len(prims), shadows=True)

    ids = ids.reshape(H, W)
    colour = colour.reshape(H, W, 3)
    if psf > 0:
        colour = cv2.GaussianBlur(colour, (0, 0), psf, borderType=cv2.BORDER_REFLECT)
    depth = z.reshape(H, W)  # this frame's own copy
    depth[ids < 0] = 0.0
    first_person = next((k for k, p in enumerate(prims) if p.person), len(prims))
    mask = ids >= first_person  # people come last in the scene's list
    rgb = cv2.convertScaleAbs(colour, alpha=255.0)
    normal_img = None
    if normals:
        normal_img = np.where((ids >= 0)[..., None], nrm.T.reshape(H, W, 3), 0.0).astype(np.float32)
    return Render(rgb=rgb, depth=depth, mask=mask, ids=ids, labels=[p.name for p in prims],
                  radiance=colour, normals=normal_img)
