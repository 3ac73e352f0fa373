"""The arithmetic helpers compiled kernels share (sinewatch.estimators.base)."""

from __future__ import annotations

import math

import numba
import numpy as np

from sinewatch.estimators.base import fma


@numba.njit
def _fma_in_a_kernel(a: float, b: float, c: float) -> float:
    return fma(a, b, c)


@numba.njit
def _fma_loop(x: np.ndarray) -> np.ndarray:
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i] = fma(x[i], x[i], -1.0)
    return out


def test_fma_rounds_once():
    # (1 + 2^-30)(1 - 2^-30) - 1 = -2^-60 exactly: the product rounded first gives 1.0, then 0.0
    a, b = 1.0 + 2.0**-30, 1.0 - 2.0**-30
    assert a * b - 1.0 == 0.0
    assert _fma_in_a_kernel(a, b, -1.0) == -(2.0**-60)


def test_fma_agrees_with_exact_arithmetic_to_one_rounding():
    from fractions import Fraction

    rng = np.random.default_rng(3)
    x = 1.0 + rng.uniform(-1e-7, 1e-7, 2000)
    got = _fma_loop(x)
    exact = [float(Fraction(v) * Fraction(v) - 1) for v in x]  # the exact result, rounded once
    np.testing.assert_array_equal(got, exact)
    # while the unfused expression loses most digits of these small differences
    assert np.count_nonzero(x * x - 1.0 != got) > 1000


def test_fma_takes_integers_and_keeps_ieee_specials():
    assert _fma_in_a_kernel(2, 3, 1) == 7.0
    assert math.isnan(_fma_in_a_kernel(math.inf, 0.0, 1.0))
    assert _fma_in_a_kernel(1e308, 10.0, -math.inf) == -math.inf
