"""The clock line through the flashes and the uncertainty it states: an onset off by its stated
uncertainty moves every frame's place by at most what error_at says, also beyond the flashes."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from rig.storage.flash_fit import fit_clock

RATE_HZ = 30.0
PERIOD_NS = 1e9 / RATE_HZ


def _points(onsets_ns, places, unc_ns):
    return [(float(o), float(p), float(u)) for o, p, u in zip(onsets_ns, places, unc_ns)]


@pytest.mark.parametrize("n", [2, 3])
def test_stated_uncertainty_covers_every_onset_error_beyond_the_flashes(n):
    places = np.linspace(60.0, 200.0, n)
    onsets = 5e8 + (places - places[0]) * PERIOD_NS * (1 + 40e-6)  # a clock 40 ppm slow against the board
    unc = np.array([0.3e6, 2.2e6, 0.5e6][:n])  # the second flash pinned only to 2.2 ms (a frame missing at its edge)
    exact = fit_clock(_points(onsets, places, np.zeros(n)), RATE_HZ)
    stated = fit_clock(_points(onsets, places, unc), RATE_HZ)
    ends = (onsets[0] - 2.0e9, onsets[-1] + 1.5e9)  # frames up to 2 s before the first flash and 1.5 s after the last
    worst_seen = {t: 0.0 for t in ends}
    for signs in itertools.product((-1.0, 1.0), repeat=n):  # every onset off by its whole uncertainty, either way
        fit = fit_clock(_points(onsets + np.array(signs) * unc, places, unc), RATE_HZ)
        for t in ends:
            worst_seen[t] = max(worst_seen[t], abs(float(fit.position(t)) - float(exact.position(t))))
    for t in ends:
        assert worst_seen[t] <= stated.error_at(t) + 1e-4, (t, worst_seen[t], stated.error_at(t))
        assert worst_seen[t] >= 0.5 * stated.error_at(t)  # and it is not a bound far above what can happen
    # beyond the flashes the rate's uncertainty grows, and a span's is never under the flashes' own
    middle = 0.5 * (onsets[0] + onsets[-1])
    assert min(stated.error_at(t) for t in ends) > stated.error_at(middle)
    assert stated.error_over(*ends) >= max(stated.error_periods, *(stated.error_at(t) for t in ends))


@pytest.mark.parametrize("n", [2, 3])
def test_the_stated_rate_error_covers_every_onset_error(n):
    # A clock that keeps perfect time, two or three flashes 3.3 s apart, each pinned to 0.3-2.2 ms:
    # its fitted rate may be tens of ppm off, and says by how much (before: a bare "+42 ppm")
    places = np.linspace(60.0, 160.0, n)
    onsets = 5e8 + (places - places[0]) * PERIOD_NS
    unc = np.array([0.3e6, 2.2e6, 0.5e6][:n])
    stated = fit_clock(_points(onsets, places, unc), RATE_HZ)
    assert stated.rate_ppm == pytest.approx(0.0, abs=0.05)
    seen = [abs(fit_clock(_points(onsets + np.array(signs) * unc, places, unc), RATE_HZ).rate_ppm)
            for signs in itertools.product((-1.0, 1.0), repeat=n)]
    assert max(seen) <= stated.rate_ppm_error + 0.1, (max(seen), stated.rate_ppm_error)
    assert max(seen) >= 0.9 * stated.rate_ppm_error  # the bound is reached: not far above what can happen
    if n == 2:  # (u0 + u1) / D
        assert stated.rate_ppm_error == pytest.approx(1e6 * (unc[0] + unc[1]) / (onsets[1] - onsets[0]), rel=0.01)
    assert fit_clock(_points(onsets, places, np.zeros(n)), RATE_HZ).rate_ppm_error == 0.0


def test_one_flash_states_its_onset_uncertainty_everywhere():
    fit = fit_clock([(1e9, 30.0, 1.5e6)], RATE_HZ)
    assert fit.rate_ppm is None
    assert fit.error_at(1e9) == fit.error_at(9e9) == pytest.approx(1.5e6 / PERIOD_NS, abs=1e-4)
