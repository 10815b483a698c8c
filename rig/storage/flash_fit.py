"""What `rig record align` does with the LED flashes once a camera's frames are read: the take's
flashes, the check that what brightened was a flash, and the line from a camera's own clock to the
trigger axis (rig.storage.align for frames in the index, rig.storage.align_video for card videos).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from rig.storage.layout import FLASHES, SequenceError
from sync.errors import SyncError

MAX_RATE_ERROR = 0.01  # a fitted clock rate further than 1 % from nominal means a flash was mismatched


def read_flashes(root: Path) -> list[dict[str, Any]]:
    path = root / FLASHES
    if not path.is_file():
        raise SequenceError(f"{root}: no {FLASHES}: the take has no LED flashes to align by "
                            "(record with a trigger board and free-running cameras; the LED must be in their view)")
    flashes = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        try:
            f = json.loads(line)
            flashes.append({"trigger": float(f["trigger"]), "host_ns": int(f["host_ns"]), "ms": float(f["ms"])})
        except (ValueError, KeyError, TypeError):
            continue  # a torn last line (the recorder died writing it) or a flash without a time
    if not flashes:
        raise SequenceError(f"{path}: no usable flash in it")
    return sorted(flashes, key=lambda f: f["trigger"])


def check_flash_shape(trace: np.ndarray, times: list, est, ms: float) -> None:
    """Something brightened: was it the flash? Its frames must form one run as long as the flash
    (a person's arm passing a bright pixel does not), else SyncError."""
    lit = np.asarray(trace) > est.baseline + 0.5 * est.amplitude
    runs = int(np.sum(np.diff(lit.astype(np.int8)) == 1) + lit[0])
    period = float(np.median(np.diff(times)))
    expected = ms * 1e6 / period
    if runs != 1 or abs(int(lit.sum()) - expected) > 1.5:
        raise SyncError(f"what brightened ({int(lit.sum())} frames in {runs} runs) is not a {ms:g} ms flash "
                        f"(about {expected:.1f} frames)")


@dataclass(frozen=True)
class ClockFit:
    """A camera's clock on the trigger axis: position(t) = at_onset + slope * (t - onset_ns)."""

    onset_ns: float  # the first flash's onset on the camera's clock
    at_onset: float  # its place on the trigger axis (pulse periods)
    slope: float  # pulse periods per ns of the camera's clock
    rate_ppm: Optional[float]  # how fast the camera's clock runs against the board's (None: one flash, nominal)
    error_periods: float  # the fit's uncertainty between the flashes, in pulse periods
    onsets_ns: tuple[float, ...] = ()  # every flash's onset on the camera's clock
    uncertainties_ns: tuple[float, ...] = ()  # and how far off it may be
    residual_periods: float = 0.0  # the flashes' largest distance from the line (three or more)
    rate_ppm_error: Optional[float] = None  # how far rate_ppm may be off: the onsets' uncertainties through the line

    def position(self, t_ns):
        return self.at_onset + self.slope * (np.asarray(t_ns, dtype=np.float64) - self.onset_ns)

    def error_at(self, t_ns: float) -> float:
        """The uncertainty of position(t_ns), in pulse periods: each flash's onset uncertainty
        carried through the line to t (a time beyond the flashes moves with the rate, so its
        uncertainty grows with the distance), plus the fit's residual."""
        x = np.asarray(self.onsets_ns, dtype=np.float64) - self.onset_ns
        u = np.asarray(self.uncertainties_ns, dtype=np.float64)
        if x.size < 2 or np.ptp(x) == 0:
            weights = np.ones(1)  # one flash: the offset only, at the nominal rate
            u = u[:1]
        else:  # the least-squares line's position at t is sum(w_i * place_i)
            dx = float(t_ns) - self.onset_ns - x.mean()
            weights = 1.0 / x.size + (x - x.mean()) * dx / float(((x - x.mean()) ** 2).sum())
        return round(float(np.abs(weights) @ u) * self.slope + self.residual_periods, 4)

    def error_over(self, t0_ns: float, t1_ns: float) -> float:
        """The largest uncertainty over a span of the camera's clock (at one of its ends: the
        uncertainty is convex in t) and never under the one between the flashes."""
        return max(self.error_at(t0_ns), self.error_at(t1_ns), self.error_periods)


def fit_clock(points: list[tuple[float, float, float]], rate_hz: float) -> ClockFit:
    """The line through the flashes' (onset on the camera's clock, place on the trigger axis,
    onset uncertainty ns): two or more give offset and rate, one gives the offset at the nominal
    rate. SyncError when the rate is off by more than MAX_RATE_ERROR (a flash mismatched)."""
    period_ns = 1e9 / rate_hz
    onsets = np.array([p[0] for p in points])
    places = np.array([p[1] for p in points])
    nominal = rate_hz / 1e9  # pulse periods per ns of the camera's clock, if it kept time perfectly
    rate_ppm = rate_error = None
    if len(points) >= 2 and np.ptp(onsets) > 0:
        slope, icpt = np.polyfit(onsets - onsets[0], places, 1)
        if abs(nominal / slope - 1) > MAX_RATE_ERROR:
            raise SyncError(f"the flashes give a clock rate {1e6 * (nominal / slope - 1):+.0f} ppm from nominal: "
                            "a flash was matched to the wrong one")
        rate_ppm = round(1e6 * (nominal / slope - 1), 1)  # > 0: the camera's clock runs fast
        rate_error = _rate_error_ppm(onsets, np.array([p[2] for p in points]))
    else:
        slope, icpt = nominal, places[0]
    fit = icpt + slope * (onsets - onsets[0])
    residual = float(np.max(np.abs(fit - places))) if len(points) > 2 else 0.0
    error = round(max(p[2] for p in points) / period_ns + residual, 4)
    return ClockFit(float(onsets[0]), float(icpt), float(slope), rate_ppm, error,
                    tuple(float(o) for o in onsets), tuple(float(p[2]) for p in points), residual, rate_error)


def _rate_error_ppm(onsets_ns: np.ndarray, uncertainties_ns: np.ndarray) -> float:
    """The most the fitted rate moves, in ppm, when each onset is off by up to its uncertainty.

    The places are exact and the onsets (the fit's abscissae) off by e_i: with a = x - mean(x) and
    A = sum(a^2), the slope becomes slope * (1 + p) / (1 + 2p + q), p = sum(a_i e_i) / A and
    q = sum((e_i - mean e)^2) / A, so the rate moves by (p + q) / (1 + p). With |p| <= P =
    sum(|a_i| u_i) / A and q <= Q = sum(u_i^2) / A that is at most (P + Q) / (1 - P): two flashes D
    apart give about (u_0 + u_1) / D, so an onset pinned to 1 ms, 10 s from the other, is 100 ppm."""
    a = onsets_ns - onsets_ns.mean()
    A = float(a @ a)
    P = float(np.abs(a) @ uncertainties_ns) / A
    Q = float(uncertainties_ns @ uncertainties_ns) / A
    return round(1e6 * min((P + Q) / (1.0 - P), 1.0), 1) if P < 1.0 else 1e6  # JSON has no infinity: 100 % says it
