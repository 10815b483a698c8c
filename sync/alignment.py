"""Offline alignment of cameras that cannot be triggered, by a flash they all saw.

The trigger board flashes its LED (FLASH command); every camera films it. In each camera's frames
the LED's brightness is a step function of time seen through the camera's exposures: frame i,
exposing over [s_i, s_i + E], gets the light of the part of its exposure the flash covers. So

    brightness_i = baseline + amplitude * overlap([s_i, s_i + E], [onset, onset + duration]) / E

and fitting onset (and duration) to the frames near the flash finds the onset on the camera's own
timeline with sub-frame accuracy: a frame the flash starts halfway through is half as bright.
Where the onset falls between two exposures (the sensor's dead time) no frame can tell where, and
the estimate is the middle of that gap, with the gap's half-width as its uncertainty; a flash
whose other edge falls inside an exposure pins it anyway when its duration is known.

    trace = brightness_trace(images)                          # mean of the pixels that flash
    flash = find_flash(times_ns, trace, exposure_ns, duration_ns=250e6)
    offsets = camera_offsets({"gopro1": flash1, "gopro2": flash2}, reference="gopro1")
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional, Sequence, Union

import numpy as np

from sync.errors import SyncError


LINEARITY = 0.01  # how far a frame's brightness may depart from its share of the flash, as a fraction


@dataclass(frozen=True)
class FlashEstimate:
    onset_ns: float  # on the timeline of the frame timestamps given
    duration_ns: float
    baseline: float
    amplitude: float
    uncertainty_ns: float  # half-width of the onsets that fit equally well
    frames: int  # frames around the flash the fit used


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, dtype=np.float32)
    return img.mean(axis=2) if img.ndim == 3 else img


def brightness_trace(images: Sequence[np.ndarray], region: Optional[tuple] = None, max_width: int = 320) -> np.ndarray:
    """Brightness per frame of what flashed: the mean of `region` (a (rows, cols) pair of slices)
    or, by default, of the pixels where the flash stands out most.

    A flash is a rare, bright event at a pixel: most frames show the pixel at its usual level and a
    few far above it. So each pixel is scored by how far its brightest frame rises above its median,
    in units of its typical variation (median absolute deviation): the LED scores high, a moving
    person (whose pixels vary all the time) low. Frames wider than `max_width` are averaged down
    in blocks first."""
    if len(images) == 0:
        raise SyncError("no frames to look for a flash in")
    if region is not None:
        return np.array([float(_gray(img)[region].mean()) for img in images])
    first = _gray(images[0])
    k = max(1, int(np.ceil(first.shape[1] / max_width)))
    h, w = first.shape[0] // k, first.shape[1] // k

    def small(img: np.ndarray) -> np.ndarray:
        g = _gray(img)[: h * k, : w * k]
        return g.reshape(h, k, w, k).mean(axis=(1, 3)) if k > 1 else g

    stack = np.stack([small(img) for img in images])
    median = np.median(stack, axis=0)
    spread = np.median(np.abs(stack - median), axis=0) * 1.4826 + 1.0  # 1 DN: the quantisation floor
    rise = stack.max(axis=0) - median
    score = rise / spread
    mask = score >= 0.5 * float(score.max())
    return stack[:, mask].mean(axis=1).astype(np.float64)


def _overlap(starts: np.ndarray, exposure: np.ndarray, onset: np.ndarray, duration: np.ndarray) -> np.ndarray:
    """Fraction of each exposure (columns) covered by each flash (rows)."""
    a = np.maximum(starts[None, :], onset[:, None])
    b = np.minimum(starts[None, :] + exposure[None, :], onset[:, None] + duration[:, None])
    return np.clip(b - a, 0.0, None) / exposure[None, :]


def _sse(y: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares y ~ c0 + c1 * x for each row of x: (sse, c0, c1)."""
    xm = x.mean(axis=1, keepdims=True)
    ym = y.mean()
    sxx = ((x - xm) ** 2).sum(axis=1)
    sxy = ((x - xm) * (y - ym)[None, :]).sum(axis=1)
    syy = float(((y - ym) ** 2).sum())
    with np.errstate(divide="ignore", invalid="ignore"):
        c1 = np.where(sxx > 0, sxy / sxx, 0.0)
        sse = np.where(sxx > 0, np.maximum(syy - sxy * c1, 0.0), syy)  # an exact fit rounds to just under 0
    c0 = ym - c1 * xm[:, 0]
    return sse, c0, c1


def find_flash(times_ns: Sequence[float], trace: Sequence[float], exposure_ns: Union[float, Sequence[float]],
               duration_ns: Optional[float] = None, min_contrast: float = 8.0) -> FlashEstimate:
    """Onset (and duration) of the flash in a brightness trace; `times_ns` are the frames'
    exposure starts, `exposure_ns` their exposure time(s). Raises SyncError when there is no flash."""
    t_abs = np.asarray(times_ns, dtype=np.float64)
    y_all = np.asarray(trace, dtype=np.float64)
    if t_abs.size != y_all.size or t_abs.size < 3:
        raise SyncError("a flash needs at least 3 frames with one timestamp each")
    order = np.argsort(t_abs)
    t_abs, y_all = t_abs[order], y_all[order]
    exp_all = np.broadcast_to(np.asarray(exposure_ns, dtype=np.float64), t_abs.shape)[order] if np.ndim(exposure_ns) else np.full(t_abs.shape, float(exposure_ns))
    t0 = t_abs[0]
    t = t_abs - t0

    dark = y_all[y_all <= np.median(y_all)]  # a flash lights fewer than half the frames
    base = float(np.median(dark))
    peak_i = int(np.argmax(y_all))
    contrast = y_all[peak_i] - base
    noise = float(np.median(np.abs(dark - base))) * 1.4826 + 1e-6
    if contrast < max(min_contrast, 6 * noise):
        raise SyncError(f"no flash in these frames (brightest frame {contrast:.1f} above the rest)")
    lit = y_all > base + 0.5 * contrast
    a = peak_i
    while a > 0 and lit[a - 1]:
        a -= 1
    b = peak_i
    while b + 1 < len(lit) and lit[b + 1]:
        b += 1
    lo, hi = max(0, a - 3), min(len(t), b + 4)
    ts, ys, es = t[lo:hi], y_all[lo:hi], exp_all[lo:hi]
    period = float(np.median(np.diff(t))) if len(t) > 1 else float(exp_all[0])

    # each edge lies between the start of the last frame before it and the end of the first after it
    on_lo = t[a - 1] if a > 0 else t[a] - period
    on_hi = t[a] + exp_all[a]
    off_lo = t[b]
    off_hi = (t[b + 1] + exp_all[b + 1]) if b + 1 < len(t) else t[b] + exp_all[b] + period
    onsets = np.linspace(on_lo, on_hi, 500)
    if duration_ns is not None:
        grid_on, grid_off = onsets, onsets + float(duration_ns)
    else:
        # the two edges vary independently: where an edge falls in the dead time between two
        # exposures the fit is flat along that edge's axis only, and its run of equal fits shows
        ends = np.linspace(off_lo, off_hi, 400)
        grid_on, grid_off = np.repeat(onsets, len(ends)), np.tile(ends, len(onsets))
        keep = grid_off > grid_on
        grid_on, grid_off = grid_on[keep], grid_off[keep]
    sse, c0, c1 = _sse(ys, _overlap(ts, es, grid_on, grid_off - grid_on))
    sse = np.where(c1 > 0, sse, np.inf)  # a flash brightens
    best = int(np.argmin(sse))
    # Fits within three standard deviations of the best are as good as the best (delta chi-square
    # 9): a flash edge in the dead time between exposures then shows as a run of equal onsets. The
    # noise: the largest of what the dark frames, the fully lit ones (shot noise grows with the
    # light) and the best fit's residuals say.
    def spread(v: np.ndarray) -> float:
        return float(np.median(np.abs(v - np.median(v)))) * 1.4826 if v.size >= 3 else 0.0

    away = np.ones(len(t), bool)
    away[max(0, a - 1):b + 2] = False
    sigma = max(spread(y_all[away]), spread(y_all[a + 1:b]), float(np.sqrt(sse[best] / max(1, len(ys) - 3))), noise, 0.1)
    ok = sse <= sse[best] + 9.0 * sigma ** 2
    onset = 0.5 * (grid_on[ok].min() + grid_on[ok].max())
    # never under the grid's step, nor under what a 1 % departure from a linear response (the
    # codec's rounding, a gamma left in the pixels) moves the onset by: 1 % of the exposure
    uncertainty = max(0.5 * (grid_on[ok].max() - grid_on[ok].min()), float(onsets[1] - onsets[0]),
                      LINEARITY * float(exp_all[a]))
    end_t = 0.5 * (grid_off[ok].min() + grid_off[ok].max())
    d_best = float(duration_ns) if duration_ns is not None else float(end_t - onset)
    return FlashEstimate(
        onset_ns=float(t0 + onset),
        duration_ns=d_best,
        baseline=float(c0[best]),
        amplitude=float(c1[best]),
        uncertainty_ns=float(uncertainty),
        frames=int(hi - lo),
    )


def flash_in_frames(frames: Iterable, duration_ns: Optional[float] = None, region: Optional[tuple] = None) -> FlashEstimate:
    """The flash in one camera's Frames (sync.frames.Frame), on its device clock."""
    frames = sorted(frames, key=lambda f: f.device_ts_ns)
    if not frames:
        raise SyncError("no frames to look for a flash in")
    missing = [f.frame_id for f in frames if f.exposure_us is None]
    if missing:
        raise SyncError(f"frames {missing[:5]} carry no exposure time: the sub-frame fit needs it")
    trace = brightness_trace([f.image for f in frames], region=region)
    return find_flash([f.device_ts_ns for f in frames], trace, [f.exposure_us * 1000.0 for f in frames], duration_ns)


def camera_offsets(flashes: dict[str, FlashEstimate], reference: Optional[str] = None) -> dict[str, float]:
    """Each camera's clock minus the reference camera's clock at the same instant, in ns: subtract it
    from a camera's timestamps to put them on the reference's timeline."""
    if not flashes:
        raise SyncError("no flashes to align")
    reference = reference or next(iter(flashes))
    if reference not in flashes:
        raise SyncError(f"reference camera {reference!r} has no flash estimate")
    ref = flashes[reference].onset_ns
    return {name: f.onset_ns - ref for name, f in flashes.items()}
