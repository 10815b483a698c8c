"""How far a calibration can be trusted, from the data rather than from the fit's own covariance.

`focal_spread`: the fit is repeated leaving out a part of the views at a time (a grouped jackknife:
each view alone below 10 views, else 10 interleaved groups), and the standard deviation of the
focal length over those fits is the uncertainty reported. A covariance from one fit assumes the
model is right and the views independent; a resampling shows what some views more or less do to the
answer, which is what goes wrong with a handful of views or a board in one part of the image.

`verdict`: "good", "weak" (usable, with the reasons) or "unusable".
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

SPREAD_WARN = 0.01  # a relative focal spread above this makes the camera "weak"
COVERAGE_WEAK = 0.25  # board coverage of the image under this makes it "weak"
RMS_UNUSABLE_PX = 2.0  # an RMS above this: no lens model explains the corners
# A camera the joint rig fit leaves fewer views than this (the rest rejected as outliers) is unusable:
# its pose rests on what survived of a set that mostly did not fit (views paired with the wrong
# instants, a lens that is not its own), however small its RMS over those few.
MIN_JOINT_VIEWS = 4
MIN_RESAMPLED_VIEWS = 5  # below this the spread is not measured
MAX_GROUPS = 10


def focal_spread(views: Sequence[str], fit_fx: Callable[[list[str]], float]) -> float | None:
    """Relative jackknife standard deviation of the focal length; `fit_fx(views)` fits on a subset."""
    views = list(views)
    if len(views) < MIN_RESAMPLED_VIEWS:
        return None
    g = min(len(views), MAX_GROUPS)
    groups = [views[i::g] for i in range(g)]
    fx = np.array([fit_fx([v for v in views if v not in set(out)]) for out in groups])
    std = float(np.sqrt((g - 1) / g * np.sum((fx - fx.mean()) ** 2)))
    return std / float(np.mean(fx))


def spread_reason(spread: float | None, n_views: int) -> str | None:
    if spread is None:
        return f"{n_views} views: too few to measure how well the focal length is pinned down (use 10 or more)"
    if spread > SPREAD_WARN:
        return (f"focal length moves {100 * spread:.1f} % between subsets of the views (limit {100 * SPREAD_WARN:g} %): "
                f"show the board tilted and in more parts of the image")
    return None


def verdict(rms_px: float | None, reasons: list[str], too_few_views: bool = False) -> str:
    if rms_px is None or rms_px > RMS_UNUSABLE_PX or too_few_views:
        return "unusable"
    return "weak" if reasons else "good"
