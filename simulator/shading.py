"""Deferred shading of the renderer: lights, materials, texture lookups and contact shadows for one
(scene, camera, time), applied to flat arrays of the rays each primitive won in the z-buffer pass."""
from __future__ import annotations

import numpy as np

from calibration.camera import CameraModel
from simulator.rays import CameraRays
from simulator.scene import Scene

SHADOW_STRENGTH = 0.45
SHADOW_RADIUS = 0.75  # metres: extent of a person's contact shadow on the floor


class Shader:
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

    @staticmethod
    def _exit_t(D, lo, hi, c):
        """Ray parameter where the ray leaves the box through the walls of one axis: +inf for a ray
        parallel to them (D exactly 0), which the division alone would make -inf (then the nearest)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((lo - float(c)) + (hi - lo) * (D > 0)) / D
        return np.where(D == 0, np.inf, t)

    def room_intersect(self, x, y):
        ts = [self._exit_t(D, lo, hi, c) for D, lo, hi, c in zip(self._room_dirs(x, y), self.lo, self.hi, self.C)]
        return np.minimum(np.minimum(ts[0], ts[1]), ts[2])

    def room_shade(self, x, y, t, want_normals=False, shadows=True):
        Dx, Dy, Dz = self._room_dirs(x, y)
        ts = [self._exit_t(D, lo, hi, c) for D, lo, hi, c in zip((Dx, Dy, Dz), self.lo, self.hi, self.C)]
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
