"""Procedural textures and the mip-mapped texture atlas the renderer samples.

Every texture is a tile that repeats seamlessly (periodic noise made in the Fourier domain, patterns
with a whole number of periods per tile), except the calibration board, which is placed once.

Atlas layout. All tiles sit in one level-0 image of size W0 x H0 at positions that are multiples of
2**LEVELS, each surrounded by PAD texels of its own wrapped content (white for the board), so that
bilinear sampling at a tile's edge reads the right neighbours. Level L is the 2x2 box average of
level L-1 (exact, because every position and size is a multiple of 2**LEVELS), and the levels are
stored side by side in one image: level 0 at (0, 0), level L >= 1 at (W0 * (1 - 2**(1-L)), H0).
A level-0 texel-centre coordinate a maps to (a + 0.5) * 2**-L - 0.5 at level L, so one pair of
coordinates per pixel addresses every level.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np

LEVELS = 6  # coarsest mip level
ALIGN = 2**LEVELS
PAD = ALIGN  # texels of wrapped border around each tile at level 0 (1 texel at the coarsest level)
ATLAS_WIDTH = 4096


@dataclass(frozen=True)
class Material:
    """Where a texture lives in the atlas and how big one tile is on the surface.

    x, y, w, h: the tile's texels at level 0 (without the border). `tile_m`: metres covered by one
    tile (u and v); `wrap`: repeat (True) or place once (the board, whose coordinates never leave
    the tile).
    """

    name: str
    x: int
    y: int
    w: int
    h: int
    tile_m: tuple[float, float]
    wrap: bool = True

    @property
    def texels_per_metre(self) -> float:
        return math.sqrt(self.w / self.tile_m[0] * self.h / self.tile_m[1])


# ---- procedural building blocks ------------------------------------------------------------------

def periodic_noise(rng: np.random.Generator, size: int | tuple[int, int], beta: float = 2.0,
                   min_period: float = 2.0, aniso: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Seamless 1/f**beta noise (mean 0, std 1) on a size x size tile; `min_period` in texels cuts the
    highest frequencies; `aniso` stretches the spectrum (e.g. wood grain)."""
    h, w = (size, size) if isinstance(size, int) else size
    fy = np.fft.fftfreq(h)[:, None] * aniso[1]
    fx = np.fft.rfftfreq(w)[None, :] * aniso[0]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2.0)
    amp[0, 0] = 0.0
    amp[f > 1.0 / min_period] = 0.0
    spec = (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape)) * amp
    img = np.fft.irfft2(spec, s=(h, w))
    img -= img.mean()
    img /= img.std() + 1e-12
    return img.astype(np.float32)


def _rgb(c) -> np.ndarray:
    return np.asarray(c, dtype=np.float32).reshape(1, 1, 3)


def _to_uint8(img: np.ndarray) -> np.ndarray:
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _tint(base, noise: np.ndarray, amount: float) -> np.ndarray:
    return _rgb(base) * (1.0 + amount * noise[..., None])


def _blur_wrapped(img: np.ndarray, sigma: float) -> np.ndarray:
    p = int(math.ceil(4 * sigma))
    big = cv2.copyMakeBorder(img, p, p, p, p, cv2.BORDER_WRAP)
    return cv2.GaussianBlur(big, (0, 0), sigma)[p:-p, p:-p]


def _draw_wrapped(img: np.ndarray, draw) -> None:
    """Draw shapes so they wrap around the tile: draw at the 9 periodic copies."""
    h, w = img.shape[:2]
    for dy in (-h, 0, h):
        for dx in (-w, 0, w):
            draw(img, dx, dy)


def wall_texture(rng: np.random.Generator, size: int, base) -> np.ndarray:
    """Plaster with fine grain, mid-scale blotches and posters/tiles: detail at every scale."""
    img = _tint(base, 0.10 * periodic_noise(rng, size, 2.2, 2.0) + 0.06 * periodic_noise(rng, size, 0.6, 2.0), 1.0)
    canvas = np.zeros((size, size, 3), np.float32)
    for _ in range(int(rng.integers(5, 9))):
        cx, cy = rng.uniform(0, size, 2)
        ww, hh = rng.uniform(0.08, 0.28, 2) * size
        col = rng.uniform(0.1, 0.95, 3)
        kind = rng.integers(0, 3)

        def draw(im, dx, dy, cx=cx, cy=cy, ww=ww, hh=hh, col=col, kind=kind):
            p0 = (int(cx - ww / 2 + dx), int(cy - hh / 2 + dy))
            p1 = (int(cx + ww / 2 + dx), int(cy + hh / 2 + dy))
            c = tuple(float(v) for v in col)
            if kind == 0:
                cv2.rectangle(im, p0, p1, c, -1, cv2.LINE_AA)
            elif kind == 1:
                cv2.ellipse(im, (int(cx + dx), int(cy + dy)), (int(ww / 2), int(hh / 2)), 0, 0, 360, c, -1, cv2.LINE_AA)
            else:
                for k in range(6):
                    y = int(cy - hh / 2 + dy + k * hh / 6)
                    cv2.line(im, (p0[0], y), (p1[0], y), c, max(1, int(size / 128)), cv2.LINE_AA)

        layer = np.zeros((size, size, 3), np.float32)
        _draw_wrapped(layer, lambda im, dx, dy: draw(im, dx, dy))
        cover = (cv2.cvtColor(layer, cv2.COLOR_RGB2GRAY) > 0)[..., None]
        np.copyto(canvas, layer, where=cover)
        img[cover[..., 0]] *= 0.15
    img = img + 0.85 * canvas * (1.0 + 0.15 * periodic_noise(rng, size, 1.0, 2.0)[..., None])
    return _to_uint8(img)


def plank_texture(rng: np.random.Generator, size: int, base, planks: int = 8) -> np.ndarray:
    """Wooden floor: planks with their own shade, along-grain noise and dark joints."""
    grain = periodic_noise(rng, size, 2.0, 2.0, aniso=(0.08, 1.0))
    fine = periodic_noise(rng, size, 0.8, 2.0)
    img = _tint(base, 0.18 * grain + 0.05 * fine, 1.0)
    ph = size // planks
    shades = rng.uniform(0.75, 1.2, planks)
    rows = np.arange(size) // ph
    img *= shades[np.minimum(rows, planks - 1)][:, None, None]
    joints = (np.arange(size) % ph) < max(1, size // 256)
    img[joints] *= 0.35
    for r in range(planks):  # butt joints, staggered
        x = int(rng.integers(0, size))
        img[r * ph:(r + 1) * ph, x:x + max(1, size // 256)] *= 0.35
    return _to_uint8(img)


def fabric_texture(rng: np.random.Generator, size: int, base, accent, pattern: str) -> np.ndarray:
    """Clothing: a weave at the finest scale under stripes, checks, plaid, dots or plain cloth."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    n = int(rng.integers(4, 12))
    if pattern == "stripes":
        m = (np.sin(2 * np.pi * n * yy) > 0.3).astype(np.float32)
    elif pattern == "checks":
        m = ((np.floor(xx * n) + np.floor(yy * n)) % 2).astype(np.float32)
    elif pattern == "plaid":
        m = 0.5 * ((np.sin(2 * np.pi * n * xx) > 0.5).astype(np.float32) + (np.sin(2 * np.pi * n * yy) > 0.5))
    elif pattern == "dots":
        fx, fy = (xx * n) % 1 - 0.5, (yy * n) % 1 - 0.5
        m = (fx * fx + fy * fy < 0.09).astype(np.float32)
    else:
        m = np.zeros((size, size), np.float32)
    m = _blur_wrapped(m, 0.6)
    img = _rgb(base) * (1 - m[..., None]) + _rgb(accent) * m[..., None]
    weave = np.sin(2 * np.pi * xx * size / 4) * np.sin(2 * np.pi * yy * size / 4)
    img *= 1.0 + 0.08 * weave[..., None] + 0.12 * periodic_noise(rng, size, 1.5, 2.0)[..., None]
    return _to_uint8(img)


def skin_texture(rng: np.random.Generator, size: int, base) -> np.ndarray:
    img = _tint(base, 0.06 * periodic_noise(rng, size, 2.5, 4.0) + 0.04 * periodic_noise(rng, size, 0.5, 2.0), 1.0)
    return _to_uint8(img)


def hair_texture(rng: np.random.Generator, size: int, base) -> np.ndarray:
    strands = periodic_noise(rng, size, 1.2, 2.0, aniso=(1.0, 0.05))
    img = _tint(base, 0.35 * strands + 0.1 * periodic_noise(rng, size, 2.0, 2.0), 1.0)
    return _to_uint8(img)


def speckle_texture(rng: np.random.Generator, size: int, base, amount: float = 0.2) -> np.ndarray:
    """Generic matte surface with blotches and fine speckle (props, ceiling, board back)."""
    img = _tint(base, amount * (0.7 * periodic_noise(rng, size, 2.5, 2.0) + 0.5 * periodic_noise(rng, size, 0.3, 2.0)), 1.0)
    return _to_uint8(img)


def board_texture(board, texels_per_square: int) -> tuple[np.ndarray, int, float]:
    """The board's printed face at `texels_per_square`, with its white margin.

    Returns (RGB image, margin in texels, texels per metre). Board-frame point (bx, by) lies at
    level-0 texel edge coordinate (bx * ppm + margin_texels, by * ppm + margin_texels): squares
    span whole texels, so every corner falls exactly on a texel boundary at every mip level.
    """
    ppm = texels_per_square / board.square_size
    grid = board.__class__(**{**dataclasses.asdict(board), "margin": 0.0}).image(ppm)
    sx, sy = board.squares
    if grid.shape != (sy * texels_per_square, sx * texels_per_square):
        raise ValueError(f"board image has shape {grid.shape}, expected squares of {texels_per_square} texels")
    margin_tex = int(math.ceil(board.margin_m * ppm - 1e-9))
    paper = 0 if getattr(board, "inverted", False) else 255
    img = cv2.copyMakeBorder(grid, margin_tex, margin_tex, margin_tex, margin_tex, cv2.BORDER_CONSTANT, value=paper)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB), margin_tex, ppm


# ---- atlas ---------------------------------------------------------------------------------------

def _round_up(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


class AtlasBuilder:
    """Collects tiles, then packs them into a mip-mapped `Atlas`."""

    def __init__(self) -> None:
        self._tiles: list[tuple[str, np.ndarray, tuple[float, float], bool, int]] = []

    def add(self, name: str, image: np.ndarray, tile_m: tuple[float, float], wrap: bool = True, group: int = -1) -> None:
        """Add a tile; tiles of the same non-negative `group` are placed side by side in one shelf at
        equal stride (so the renderer can address them by arithmetic instead of a table lookup)."""
        if wrap and (image.shape[0] % ALIGN or image.shape[1] % ALIGN):
            raise ValueError(f"texture {name}: a repeating tile must be a multiple of {ALIGN} texels")
        self._tiles.append((name, image, tile_m, wrap, group))

    def build(self) -> "Atlas":
        # Shelves: each group is one shelf; the other tiles fill shelves by height.
        placed: dict[str, tuple[int, int]] = {}
        slots = []
        for name, img, _tm, wrap, group in self._tiles:
            slots.append((name, _round_up(img.shape[1] + 2 * PAD), _round_up(img.shape[0] + 2 * PAD), group))
        y = 0
        groups = sorted({s[3] for s in slots if s[3] >= 0})
        for g in groups:
            members = [s for s in slots if s[3] == g]
            stride = max(s[1] for s in members)
            hmax = max(s[2] for s in members)
            for k, s in enumerate(members):
                placed[s[0]] = (k * stride, y)
            y += hmax
        rest = sorted((s for s in slots if s[3] < 0), key=lambda s: -s[2])
        x, shelf_h = 0, 0
        for name, w, h, _g in rest:
            if x + w > ATLAS_WIDTH:
                x, y, shelf_h = 0, y + shelf_h, 0
            placed[name] = (x, y)
            x += w
            shelf_h = max(shelf_h, h)
        y += shelf_h
        W0 = max(ATLAS_WIDTH, max(p[0] + s[1] for p, s in zip((placed[s[0]] for s in slots), slots)))
        H0 = _round_up(y)
        level0 = np.zeros((H0, W0, 3), np.uint8)
        materials = {}
        for (name, img, tile_m, wrap, _g) in self._tiles:
            px, py = placed[name]
            h, w = img.shape[:2]
            border = cv2.BORDER_WRAP if wrap else cv2.BORDER_REPLICATE
            padded = cv2.copyMakeBorder(img, PAD, PAD, PAD, PAD, border)
            level0[py:py + h + 2 * PAD, px:px + w + 2 * PAD] = padded
            materials[name] = Material(name, px + PAD, py + PAD, w, h, tile_m, wrap)
        return Atlas(level0, materials)


class Atlas:
    """All textures of a scene with their mip levels in one image (see the module docstring)."""

    def __init__(self, level0: np.ndarray, materials: dict[str, Material]):
        H0, W0 = level0.shape[:2]
        self.W0, self.H0 = W0, H0
        self.materials = materials
        image = np.zeros((H0 + H0 // 2, W0, 3), np.uint8)
        image[:H0] = level0
        lev = level0
        for L in range(1, LEVELS + 1):
            lev = cv2.resize(lev, (lev.shape[1] // 2, lev.shape[0] // 2), interpolation=cv2.INTER_AREA)
            x0 = int(W0 * (1 - 2.0 ** (1 - L)))
            image[H0:H0 + lev.shape[0], x0:x0 + lev.shape[1]] = lev
        self.image = image

    def sample(self, ax0: np.ndarray, ay0: np.ndarray, lod: np.ndarray) -> np.ndarray:
        """Trilinear lookup at level-0 texel-centre coordinates; returns float32 (..., 3) in [0, 1]."""
        lod = np.clip(lod, 0.0, float(LEVELS))
        lev = np.floor(lod)
        frac = lod - lev
        out = None
        for step in (0.0, 1.0):
            L = np.minimum(lev + step, float(LEVELS))
            scale = np.exp2(-L)
            coarse = (L >= 1.0).astype(np.float32)
            mx = coarse * (self.W0 * (1.0 - 2.0 * scale)) + (ax0 + 0.5) * scale - 0.5
            my = coarse * self.H0 + (ay0 + 0.5) * scale - 0.5
            tex = _remap(self.image, mx, my)
            w = (1.0 - frac) if step == 0.0 else frac
            contrib = tex.astype(np.float32) * (w * (1.0 / 255.0))[..., None]
            out = contrib if out is None else out + contrib
        return out


def _remap(image: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """cv2.remap for maps of any shape (remap wants each side of its output below 32767)."""
    shape = mx.shape
    if mx.ndim == 2 and max(shape) < 32767:
        out = cv2.remap(image, mx.astype(np.float32, copy=False), my.astype(np.float32, copy=False),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(shape + (image.shape[2],))
    n = mx.size
    cols = 1024
    rows = -(-n // cols)
    fx = np.zeros(rows * cols, np.float32)
    fy = np.zeros(rows * cols, np.float32)
    fx[:n] = mx.ravel()
    fy[:n] = my.ravel()
    out = cv2.remap(image, fx.reshape(rows, cols), fy.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, image.shape[2])[:n].reshape(shape + (image.shape[2],))
