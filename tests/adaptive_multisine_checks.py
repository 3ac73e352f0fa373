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
