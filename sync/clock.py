"""Board clock to host clock: a robust linear fit over time-query round trips.

The host sends `TIME n` at host time `send`, the board answers with its clock reading `board_us`, the
reply arrives at `recv`. The board read its clock somewhere in [send, recv]; the midpoint is the best
guess and is off by at most half the round trip. Slow round trips (a busy USB bus, a descheduled
thread) are the bad guesses, so, as strawlab's triggerbox does, the model keeps only the fast ones:
replies over an absolute limit are rejected outright, and of the recent window only the fastest
fraction enters the fit.

The fit uses what a round trip proves rather than only its midpoint: the board's reading was taken at
some host time in [send, recv], an interval that holds the truth whatever the delays. The slope
(drift) comes from a least-squares line through the midpoints of the kept round trips; the offset
centres that line in the band the intervals leave, which the fastest round trip on each side
decides, so a reply delay that sits after the board reads its clock (the usual case: the reply waits
for the USB poll) does not bias it as it biases a midpoint average (see `band_fit`).

Arithmetic is relative to a reference sample: host nanoseconds since boot and board microseconds do
not fit a float's 53 bits with sub-microsecond precision once squared.
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class TimeSample:
    host_send_ns: int
    board_us: int
    host_recv_ns: int

    @property
    def rtt_ns(self) -> int:
        return self.host_recv_ns - self.host_send_ns

    @property
    def host_mid_ns(self) -> int:
        return (self.host_send_ns + self.host_recv_ns) // 2


@dataclass(frozen=True)
class ClockFit:
    """host_ns = host_ref + offset_ns + slope * (board_us - board_ref)."""

    board_ref: int
    host_ref: int
    offset_ns: float
    slope: float  # host nanoseconds per board microsecond (1000 for a perfect board clock)
    samples: int
    span_us: int
    residual_p99_us: float  # of the round-trip midpoints around the line
    margin_us: float  # how deep the line lies inside every round trip's interval (negative: they conflict)

    def board_to_host_ns(self, board_us: float) -> int:
        return self.host_ref + int(round(self.offset_ns + self.slope * (board_us - self.board_ref)))

    def host_to_board_us(self, host_ns: int) -> float:
        return self.board_ref + (host_ns - self.host_ref - self.offset_ns) / self.slope

    @property
    def drift_ppm(self) -> float:
        """How fast the board clock runs relative to the host's, in parts per million."""
        return (1000.0 / self.slope - 1.0) * 1e6


class ClockModel:
    """Thread-safe: the board driver adds samples, grouping and recording threads map times.

    window_s: how much board time of recent samples is kept (a longer baseline gives a steadier
    slope; a shorter one follows temperature drift faster); max_rtt_us: replies slower than this
    are rejected outright;
    keep_fraction: the fastest share of the window that enters the fit; min_slope_span_s: below this
    much board time the slope is not fitted (a short span cannot tell drift from jitter) and the
    nominal rate is used.
    """

    def __init__(self, window_s: float = 30.0, max_rtt_us: float = 2000.0, keep_fraction: float = 0.3,
                 min_samples: int = 3, min_slope_span_s: float = 0.5, max_samples: int = 4000):
        self.window_us = int(window_s * 1e6)
        self.max_rtt_ns = int(max_rtt_us * 1000)
        self.keep_fraction = keep_fraction
        self.min_samples = min_samples
        self.min_slope_span_us = int(min_slope_span_s * 1e6)
        self._lock = threading.Lock()
        self._samples: deque[TimeSample] = deque(maxlen=max_samples)
        self._first_board_us: Optional[int] = None
        self._fit: Optional[ClockFit] = None
        self.added = 0
        self.rejected_slow = 0

    def reset(self) -> None:
        """Forget everything (the board restarted its clock)."""
        with self._lock:
            self._samples.clear()
            self._first_board_us = None
            self._fit = None
            self.added = self.rejected_slow = 0

    def add(self, host_send_ns: int, board_us: int, host_recv_ns: int) -> bool:
        """Record one round trip; returns False when it was too slow to use."""
        sample = TimeSample(int(host_send_ns), int(board_us), int(host_recv_ns))
        with self._lock:
            self.added += 1
            if sample.rtt_ns < 0 or sample.rtt_ns > self.max_rtt_ns:
                self.rejected_slow += 1
                return False
            self._samples.append(sample)
            if self._first_board_us is None:
                self._first_board_us = sample.board_us
            while self._samples[0].board_us < sample.board_us - self.window_us:
                self._samples.popleft()
            self._fit = self._refit()
            return True

    # --- reading ----------------------------------------------------------------------------------
    @property
    def fit(self) -> Optional[ClockFit]:
        return self._fit

    @property
    def ready(self) -> bool:
        return self._fit is not None

    def board_to_host_ns(self, board_us: float) -> int:
        fit = self._fit
        if fit is None:
            raise RuntimeError("clock model has no samples yet")
        return fit.board_to_host_ns(board_us)

    def host_to_board_us(self, host_ns: int) -> float:
        fit = self._fit
        if fit is None:
            raise RuntimeError("clock model has no samples yet")
        return fit.host_to_board_us(host_ns)

    @property
    def drift_ppm(self) -> Optional[float]:
        fit = self._fit
        return None if fit is None else fit.drift_ppm

    def span_s(self) -> float:
        """Board time covered by the samples of the current fit."""
        fit = self._fit
        return 0.0 if fit is None else fit.span_us / 1e6

    def age_s(self) -> float:
        """Board time since the first sample after the last reset."""
        with self._lock:
            if self._first_board_us is None or not self._samples:
                return 0.0
            return (self._samples[-1].board_us - self._first_board_us) / 1e6

    def stats(self) -> dict:
        fit = self._fit
        with self._lock:
            rtts = [s.rtt_ns / 1000.0 for s in self._samples]
        return {
            "samples": self.added,
            "rejected_slow": self.rejected_slow,
            "rtt_us_p50": float(np.percentile(rtts, 50)) if rtts else None,
            "rtt_us_min": float(min(rtts)) if rtts else None,
            "fit_samples": fit.samples if fit else 0,
            "span_s": fit.span_us / 1e6 if fit else 0.0,
            "drift_ppm": fit.drift_ppm if fit else None,
            "fit_residual_p99_us": fit.residual_p99_us if fit else None,
            "margin_us": fit.margin_us if fit else None,
        }

    # --- fitting ----------------------------------------------------------------------------------
    def _refit(self) -> Optional[ClockFit]:
        samples = self._samples
        if not samples:
            return None
        board_ref = samples[-1].board_us
        host_ref = samples[-1].host_send_ns
        arr = np.array([(s.board_us, s.host_send_ns, s.host_recv_ns) for s in samples], dtype=np.int64)
        x = (arr[:, 0] - board_ref).astype(np.float64)  # us
        lo = (arr[:, 1] - host_ref).astype(np.float64)  # ns
        hi = (arr[:, 2] - host_ref).astype(np.float64)
        keep_n = max(self.min_samples, int(np.ceil(len(x) * self.keep_fraction)))
        rtt = hi - lo
        limit = np.partition(rtt, keep_n - 1)[keep_n - 1] if keep_n < len(rtt) else np.inf
        fast = np.flatnonzero(rtt <= limit)  # the slope's samples: the fastest round trips (ties kept)
        span = int(np.ptp(x))
        fit_slope = np.ptp(x[fast]) >= self.min_slope_span_us and len(fast) >= 3
        offset, slope, margin = band_fit(x, lo, hi, fit_slope, slope_from=fast)
        resid = (lo[fast] + hi[fast]) / 2.0 - (offset + slope * x[fast])
        return ClockFit(
            board_ref=board_ref,
            host_ref=host_ref,
            offset_ns=float(offset),
            slope=float(slope),
            samples=len(x),
            span_us=span,
            residual_p99_us=float(np.percentile(np.abs(resid), 99) / 1000.0),
            margin_us=float(margin / 1000.0),
        )


def band_fit(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, fit_slope: bool,
             slope_from: Optional[np.ndarray] = None) -> tuple[float, float, float]:
    """A line y = offset + slope * x through the intervals [lo_i, hi_i] of round trips.

    Every interval holds the truth, so every one is a valid bound, slow or not. The line is the one
    that lies deepest inside all of them: for a given slope the offset centres it between the
    highest lower bound and the lowest upper bound, and the slope is the one leaving the widest
    margin, found by a golden-section search started from a least-squares line through the
    midpoints of the fastest round trips (`slope_from`). The fastest outbound and return legs decide
    the line, so a delay on one side only (the reply waiting for the USB poll after the board read
    its clock) does not shift it, as it shifts a midpoint average; over a long window the extreme
    samples lie far apart and pin the slope. (Measured on the emulator, a least-squares slope drifted
    by half a ppm as the host's load changed during a run; the max-margin slope did not.)
    Returns (offset, slope, margin); margin is how deep the line lies inside every interval (negative
    when the intervals do not all admit one line).
    """
    idx = slice(None) if slope_from is None else slope_from
    xs, mid = x[idx], (lo[idx] + hi[idx]) / 2.0
    if fit_slope and len(xs) >= 3 and np.ptp(xs) > 0:
        xm = xs.mean()
        slope = float(np.sum((xs - xm) * (mid - mid.mean())) / np.sum((xs - xm) ** 2))
        slope = _max_margin_slope(x, lo, hi, slope)
    else:
        slope = 1000.0  # too short a span to tell drift from jitter: assume a nominal clock
    top = float(np.min(hi - slope * x))
    bottom = float(np.max(lo - slope * x))
    return (top + bottom) / 2.0, slope, (top - bottom) / 2.0


def _margin(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, slope: float) -> float:
    return float(np.min(hi - slope * x) - np.max(lo - slope * x)) / 2.0


def _max_margin_slope(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, guess: float, width_ppm: float = 500.0) -> float:
    """Golden-section search, around the least-squares guess, of the slope that leaves the widest
    margin. The margin is concave in the slope (a minimum of lines minus a maximum of lines)."""
    a, b = guess * (1 - width_ppm * 1e-6), guess * (1 + width_ppm * 1e-6)
    g = (np.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = _margin(x, lo, hi, c), _margin(x, lo, hi, d)
    while b - a > guess * 1e-9:
        if fc > fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = _margin(x, lo, hi, c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = _margin(x, lo, hi, d)
    return (a + b) / 2.0
