"""ges-kalman's noise means (U5)-(U5a) skip exp when the cap provably does not bind: the
skip must give exactly the bits of the plain formula, sample after sample."""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators import detmath
from sinewatch.estimators.ges_kalman import LOG_CHI2_MEAN, NOISE_MEMORY, ROBUST_CAP, TINY, _noise_means


def _plain(u: float, w: float, m_u: float, m_l: float, lam: float) -> tuple[float, float, float]:
    """(U5)-(U5a) as written in the module docstring, exp taken every time (Python's math
    calls the same C library as the kernel's exp); the log is the kernel's own
    (:func:`sinewatch.estimators.detmath.log`, plain arithmetic, not the C library's)."""
    w = lam * w + (1.0 - lam)
    m_u = lam * m_u + (1.0 - lam) * u
    m_l = lam * m_l + (1.0 - lam) * detmath.log(max(u, TINY))
    m_u = min(m_u, ROBUST_CAP * w * math.exp(m_l / w - LOG_CHI2_MEAN))
    return w, m_u, m_l


def _sequence() -> np.ndarray:
    """Squared Gaussian innovations whose variance steps by decades up and down (the exponent
    moves far from the last exp's), with outliers that make the cap bind, exact zeros (log of
    TINY) and values near the smallest normal double."""
    rng = np.random.default_rng(11)
    scale = np.repeat([1.0, 1e-6, 1e4, 1e-3, 1e2, 1.0], 700)
    u = rng.standard_normal(scale.size) ** 2 * scale
    u[rng.integers(0, u.size, 8)] *= 1e4  # outliers: the cap (U5a) binds
    u[rng.integers(0, u.size, 20)] = 0.0
    u[rng.integers(0, u.size, 20)] = 1e-305
    return u


def test_skipping_exp_gives_the_plain_formulas_bits_and_skips_it_where_the_cap_does_not_bind() -> None:
    lam = 1.0 - 1.0 / NOISE_MEMORY
    w, m_u, m_l = 0.0, 0.0, 0.0
    pw, pm_u, pm_l = 0.0, 0.0, 0.0
    x_ref, e_ref = 0.0, 0.0
    taken = capped = 0
    for k, u in enumerate(_sequence()):
        w, m_u, m_l, new_x, new_e = _noise_means(float(u), w, m_u, m_l, lam, x_ref, e_ref)
        taken += (new_x, new_e) != (x_ref, e_ref)
        x_ref, e_ref = new_x, new_e
        before_cap = lam * pm_u + (1.0 - lam) * float(u)
        pw, pm_u, pm_l = _plain(float(u), pw, pm_u, pm_l, lam)
        capped += pm_u != before_cap
        got = np.array([w, m_u, m_l]).tobytes()
        assert got == np.array([pw, pm_u, pm_l]).tobytes(), f"sample {k}: {(w, m_u, m_l)} != {(pw, pm_u, pm_l)}"
    n = _sequence().size
    assert capped > 20, "the sequence should make the cap bind"
    # exp is needed where the cap binds; elsewhere the bound skips it on all but a few samples
    assert capped <= taken < capped + n // 20, f"exp taken on {taken} of {n} samples, the cap bound {capped}"
