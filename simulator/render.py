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

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from calibration.camera import CameraModel
from simulator.errors import SimulatorError
from simulator.primitives import camera_batches
from simulator.rays import NEAR, camera_rays, check_camera
from simulator.scene import Scene, check_time
from simulator.shading import SHADOW_RADIUS, Shader

DEFAULT_ANTIALIAS = 3
DEFAULT_PSF = 0.5  # pixels: Gaussian sigma of the lens blur (real lenses are never perfectly sharp)


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
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(), camera.model, camera.R.tobytes(),
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


def _check_options(antialias, psf) -> tuple[int, float]:
    """render()'s supersampling factor and lens blur, checked."""
    s = DEFAULT_ANTIALIAS if antialias is None else antialias
    if not isinstance(s, (int, np.integer)) or isinstance(s, bool) or not 1 <= s <= 8:
        raise SimulatorError(f"antialias must be an integer from 1 to 8, got {antialias!r}")
    try:
        psf = float(psf)
    except (TypeError, ValueError):
        raise SimulatorError(f"psf must be a number of pixels, got {psf!r}") from None
    if not 0 <= psf <= 10:
        raise SimulatorError(f"psf must be between 0 and 10 pixels, got {psf}")
    return s, psf


def _contact_shadows(shader, camera: CameraModel, rays, static, ids: np.ndarray, colour: np.ndarray) -> None:
    """Darken the floor around each person, in place. Each person darkens the floor within its own
    rectangle; where they overlap, the factors multiply."""
    H, W = camera.height, camera.width
    for gx, gz in shader.shadows:
        c = camera.R @ np.array([gx, 0.0, gz]) + camera.t
        v0, v1, u0, u1 = (int(a) for a in rays.sphere_boxes(c, [SHADOW_RADIUS], [0], 1)[0])
        if v0 >= v1:
            continue
        local = np.flatnonzero(static.floor.reshape(H, W)[v0:v1, u0:u1] & (ids.reshape(H, W)[v0:v1, u0:u1] == 0))
        bw = u1 - u0
        fi = (v0 + local // bw) * W + (u0 + local % bw)
        colour[fi] *= shader.shadow_factor(static.floor_x[fi], static.floor_z[fi], [(gx, gz)])[:, None]


def _refilter_moving(shader, camera: CameraModel, batches, boxes, rays, static, ids: np.ndarray, colour: np.ndarray,
                     s: int, n_prims: int, n_static: int) -> None:
    """Supersample again, in place, the silhouette pixels the moving primitives changed (the static
    ones are filtered already)."""
    H, W = camera.height, camera.width
    dyn = [bx[b.ks >= n_static] for b, bx in zip(batches, boxes)]
    dyn = np.concatenate(dyn) if dyn else np.zeros((0, 4), np.int64)
    dyn = dyn[dyn[:, 0] < dyn[:, 1]]
    if not dyn.size:
        return
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
        colour[ep] = _supersample(shader, batches, ids, rays, ep, s, n_prims, shadows=True)


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
    s, psf = _check_options(antialias, psf)
    rays = camera_rays(camera)
    H, W = camera.height, camera.width
    prims = scene.primitives(t)
    nst = scene.static_count
    shader = Shader(scene, camera, rays, prims, t)
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

    _contact_shadows(shader, camera, rays, static, ids, colour)
    if s > 1:
        _refilter_moving(shader, camera, batches, boxes, rays, static, ids, colour, s, len(prims), nst)

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
