"""``sinewatch.estimators.detmath`` against numpy (the C library): ulps over dense grids and the
special arguments. The kernels replaced the C library's sin/tan/log with these so that a bank's
lanes vectorise and stay the single channel's bits; these tests hold their accuracy."""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np
import pytest

from sinewatch.estimators import detmath

RNG_SEED = 20261127


def _apply(fn: Callable[[float], float]) -> Callable[[np.ndarray], np.ndarray]:
    @numba.njit(cache=True)
    def run(x: np.ndarray) -> np.ndarray:
        out = np.empty_like(x)
        for i in range(x.size):
            out[i] = fn(x[i])
        return out

    return run


def _ulps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| in units in the last place: the distance of their bit patterns on one line."""

    def line(x: np.ndarray) -> np.ndarray:
        i = x.view(np.int64)
        return np.where(i < 0, np.int64(-(2**63)) - i, i)

    return np.asarray(np.abs(line(a) - line(b)))


_RNG = np.random.default_rng(RNG_SEED)
# (function, reference, max ulps from numpy's value, grids): tan is the quotient of two kernels
CASES = {
    "sin": (detmath.sin, np.sin, 1, [np.linspace(-10.0, 10.0, 400_001), _RNG.uniform(-1.6e6, 1.6e6, 200_000),
                                      np.geomspace(1e-300, 1.0, 20_000)]),
    "cos": (detmath.cos, np.cos, 1, [np.linspace(-10.0, 10.0, 400_001), _RNG.uniform(-1.6e6, 1.6e6, 200_000)]),
    "tan": (detmath.tan, np.tan, 3, [np.linspace(-10.0, 10.0, 400_001), _RNG.uniform(-1.6e6, 1.6e6, 200_000),
                                      np.geomspace(1e-300, 1.57, 20_000)]),
    "log": (detmath.log, np.log, 1, [np.geomspace(5e-324, 1.7e308, 200_000), np.linspace(0.5, 2.0, 400_001),
                                      _RNG.uniform(0.0, 1e6, 200_000)]),
    "exp": (detmath.exp, np.exp, 1, [np.linspace(-746.0, 710.0, 400_001), np.linspace(-1.0, 1.0, 200_001)]),
}  # fmt: skip
SPECIAL = np.array([0.0, -0.0, np.pi, -np.pi, 0.5 * np.pi, 1.0, 5e-324, -5e-324, 2.2250738585072014e-308,
                    np.inf, -np.inf, np.nan, 700.0, -740.0, 1e300, -1e300])  # fmt: skip


@pytest.mark.parametrize("name", sorted(CASES))
def test_within_ulps_of_the_c_library(name: str) -> None:
    fn, ref, max_ulps, grids = CASES[name]
    run = _apply(fn)
    for grid in grids:
        ours, theirs = run(grid), ref(grid)
        finite = np.isfinite(theirs)
        assert np.array_equal(np.isfinite(ours), finite), f"{name}: finite where numpy is not, or back"
        worst = _ulps(ours[finite], theirs[finite]).max()
        assert worst <= max_ulps, f"{name} on [{grid.min():g}, {grid.max():g}]: {worst} ulps, expected <= {max_ulps}"


@pytest.mark.parametrize("name", sorted(CASES))
def test_special_arguments(name: str) -> None:
    """Signed zeros, infinities, NaN, subnormals and the range limits as the C library gives them,
    except trigonometric arguments beyond TRIG_MAX: NaN (a reduction this module does not do)."""
    fn, ref, _, _ = CASES[name]
    with np.errstate(all="ignore"):
        theirs = ref(SPECIAL)
    if name in ("sin", "cos", "tan"):
        theirs = np.where(np.abs(SPECIAL) <= detmath.TRIG_MAX, theirs, np.nan)
    ours = _apply(fn)(SPECIAL)
    both_nan = np.isnan(ours) & np.isnan(theirs)
    close = _ulps(ours, theirs) <= CASES[name][2]
    assert np.all(both_nan | close), f"{name}: {ours} against {theirs}"
    assert np.array_equal(np.signbit(ours[:2]), np.signbit(theirs[:2])), f"{name} of +-0: sign"


def test_trig_limit_is_where_the_reduction_stays_exact() -> None:
    """Just inside TRIG_MAX the values are the C library's within 1 ulp, just outside NaN."""
    x = np.array([detmath.TRIG_MAX, np.nextafter(detmath.TRIG_MAX, 0.0), np.nextafter(detmath.TRIG_MAX, np.inf)])
    s = _apply(detmath.sin)(x)
    assert np.all(_ulps(s[:2], np.sin(x[:2])) <= 1)
    assert np.isnan(s[2])


def test_sincos_is_sin_and_cos() -> None:
    @numba.njit(cache=True)
    def both(x: np.ndarray) -> np.ndarray:
        out = np.empty((x.size, 2))
        for i in range(x.size):
            out[i, 0], out[i, 1] = detmath.sincos(x[i])
        return out

    x = np.linspace(-20.0, 20.0, 10_001)
    sc = both(x)
    assert sc[:, 0].tobytes() == _apply(detmath.sin)(x).tobytes()
    assert sc[:, 1].tobytes() == _apply(detmath.cos)(x).tobytes()
