"""Checks shared by the adaptive-multisine tests: the explicit-gain mode
(``test_adaptive_multisine.py``) and the automatic mode (``test_adaptive_multisine_auto.py``)
reproduce the same figures of the paper, each with its own measured tolerances."""

from __future__ import annotations

import math

import numpy as np


def settle_time(t, w, target, rel_tol, t0=0.0) -> float:
    """First time after which |w - target| <= rel_tol * target for good (from t0 on)."""
    bad = ((np.abs(w - target) > rel_tol * target) | ~np.isfinite(w)) & (t >= t0)
    idx = np.flatnonzero(bad)
    if idx.size == 0:
        return t0
    return float(t[idx[-1] + 1]) if idx[-1] + 1 < t.size else math.inf


def assert_settles_and_holds(t, tr, w, frequencies, amplitudes, *, within, hold_from, atol_w, atol_amp):
    """Each frequency estimate within 1 % of its value (rad/s) for good less than ``within`` s
    from the start; from ``hold_from`` on, the means of the frequencies and of the amplitudes
    at their values. Returns the mask of that steady part."""
    for i, target in enumerate(frequencies):
        assert settle_time(t, w[:, i], target, 0.01) < within
    ss = t >= hold_from
    np.testing.assert_allclose(w[ss].mean(axis=0), frequencies, atol=atol_w)
    np.testing.assert_allclose(tr.amplitude[ss].mean(axis=0), amplitudes, atol=atol_amp)
    return ss


def assert_example_1(t, tr, w, *, within, atol_w, atol_amp, converged_from) -> None:
    """Example 1 (Figs. 3, 6): sin 2t + sin 5t, both frequencies and unit amplitudes held over
    60-100 s, converged from ``converged_from`` on, and the reconstruction sum A_i sin(phi_i)
    (eq. 10) following the signal."""
    ss = assert_settles_and_holds(
        t, tr, w, [2.0, 5.0], [1.0, 1.0], within=within, hold_from=60.0, atol_w=atol_w, atol_amp=atol_amp
    )
    assert tr.converged[t >= converged_from].all()
    assert np.max(np.abs(tr.reconstruct()[ss] - (np.sin(2 * t) + np.sin(5 * t))[ss])) < 5e-3


def assert_example_3_step(t, w, *, pre_from, post_from, atol_pre, rel_tol, within) -> list[float]:
    """Example 3 (Fig. 10): w1: 2 -> 3 rad/s and w2: 5 -> 4.5 rad/s at t = 70 s. The means before
    the step (from ``pre_from``) and after it (from ``post_from``) at the frequencies, each
    estimate within ``rel_tol`` of its new value less than ``within`` s after the step; returns
    those settling times."""
    pre, post = (t >= pre_from) & (t < 70), t >= post_from
    np.testing.assert_allclose(w[pre].mean(axis=0), [2.0, 5.0], atol=atol_pre)
    np.testing.assert_allclose(w[post].mean(axis=0), [3.0, 4.5], atol=0.03)
    after = [settle_time(t, w[:, i], v, rel_tol, 70.0) - 70.0 for i, v in enumerate((3.0, 4.5))]
    assert max(after) < within
    print(f"\nEX3: within {rel_tol:.0%} {after} s after the step; errors after {w[post].mean(axis=0) - (3, 4.5)}")
    return after
