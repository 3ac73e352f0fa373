"""The compiled float formatter against CPython's own ``repr``, character for character: an
Estimate's bytes (and so every recording and replay) depend on it being the same."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from sinewatch.core.float_repr import MAX_CHARS, repr_floats

# the layout's and Ryu's corner cases: zeros, the switch to an exponent at 1e-4 and 1e16, the
# smallest subnormal and normal, the largest double, powers of two (a narrower gap below),
# exact halfway digits, integers past 2^53, and what repr writes for the non-finite
CORNERS = [
    0.0,
    -0.0,
    1.0,
    -1.0,
    50.0,
    0.1,
    0.3,
    2 / 3,
    1e-4,
    9.999999999999999e-5,
    1e-5,
    1e15,
    9999999999999998.0,
    1e16,
    1.5e-7,
    5e-324,
    -5e-324,
    1e-323,
    2.2250738585072014e-308,
    2.225073858507201e-308,
    sys.float_info.max,
    sys.float_info.epsilon,
    9007199254740993.0,
    1e22,
    1e23,
    5e-310,
    1e100,
    1e-100,
    123456.789,
    4.35,
    0.5,
    2.5,
    float("nan"),
    float("inf"),
    float("-inf"),
]


def _check(values: np.ndarray) -> None:
    got = repr_floats(values)
    want = [repr(v) for v in values.tolist()]
    bad = [(w, g) for w, g in zip(want, got, strict=True) if w != g]
    assert not bad, f"expected repr's text, got {len(bad)} different, first {bad[:5]}"


def test_corner_cases_are_written_as_repr_writes_them() -> None:
    _check(np.array(CORNERS))
    assert max(len(repr(v)) for v in CORNERS) <= MAX_CHARS


def test_every_binary_exponent_and_its_neighbours() -> None:
    """Each of the 2,046 binary exponents (and the subnormals) at its power of two, one ulp
    either side and a few random mantissas: every branch of Ryu's two halves (e2 >= 0, < 0)."""
    rng = np.random.default_rng(26)
    exps = np.arange(-1074, 1024)
    p2 = np.ldexp(1.0, exps)
    values = np.concatenate(
        [
            p2,
            np.nextafter(p2, np.inf),
            np.nextafter(p2, 0.0),
            p2 * rng.uniform(1.0, 2.0, exps.size),
            -p2 * rng.uniform(1.0, 2.0, exps.size),
        ]
    )
    _check(values[np.isfinite(values)])


def test_random_bit_patterns_and_estimate_like_values() -> None:
    rng = np.random.default_rng(7)
    bits = rng.integers(0, 2**64, 20_000, dtype=np.uint64).view(np.float64)
    _check(bits[np.isfinite(bits)])
    _check(50.0 + rng.standard_normal(5_000) * 1e-3)  # frequencies
    _check(rng.standard_normal(5_000) * 1e-6)  # standard deviations, offsets
    _check(np.round(rng.standard_normal(5_000) * 1000, 3))  # short decimals (ties in the last digit)
    _check(rng.integers(1, 10**6, 5_000) * 10.0 ** rng.integers(-330, 300, 5_000).astype(np.float64))


def test_no_values_and_one_value() -> None:
    assert repr_floats(np.zeros(0)) == []
    assert repr_floats(np.array([0.1])) == ["0.1"]


@pytest.mark.slow
def test_millions_of_random_doubles() -> None:
    """Ten million doubles of every kind (about a minute): no difference from repr."""
    rng = np.random.default_rng(2026)
    for _ in range(5):
        bits = rng.integers(0, 2**64, 1_000_000, dtype=np.uint64).view(np.float64)
        _check(bits[np.isfinite(bits)])
        _check(rng.standard_normal(1_000_000) * 10.0 ** rng.integers(-20, 20, 1_000_000))
