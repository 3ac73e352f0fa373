"""Cramer-Rao bound for the parameters of a biased real sinusoid in white Gaussian noise.

Model (the estimator output convention), N samples ``n = 0 .. N-1`` at ``fs``::

    y[n] = B + A sin(w (n - n_ref) + phi) + v[n],   v ~ N(0, sigma^2) white

with ``w`` in radians per sample (``f = w fs / 2 pi`` in Hz) and ``phi`` the phase at the
reference sample ``n_ref``. A tracker reports at sample n the instantaneous phase of
that sample, so the bench uses ``n_ref = N - 1`` (the last sample seen): that is the
default here.

Exact bound (finite N)
----------------------
Fisher information of theta = (w, A, phi, B) for Gaussian noise::

    I = (1/sigma^2) sum_n g[n] g[n]^T,
    g[n] = ds/dtheta = (A m cos psi, sin psi, A cos psi, 1),  psi = w m + phi_c

computed with the time index *centred* (``m = n - (N-1)/2``, ``phi_c`` the phase at the
centre of the record): the w-column then carries ``m`` rather than ``n`` and the matrix
is far better conditioned. It is inverted after a symmetric diagonal scaling (Jacobi),
which keeps the inverse accurate up to N ~ 1e7. The bound on the phase at another
reference sample follows from ``phi_ref = phi_c + w (n_ref - c)``::

    var(phi_ref) = var(phi_c) + d^2 var(w) + 2 d cov(w, phi_c),   d = n_ref - (N-1)/2

Asymptotic closed form (large N, w not near 0 or pi)
----------------------------------------------------
The cross terms average out and the centred matrix is diagonal::

    I_ww = A^2 N (N^2 - 1) / (24 sigma^2),  I_AA = N / (2 sigma^2),
    I_phiphi = A^2 N / (2 sigma^2),         I_BB = N / sigma^2

hence, with SNR eta = A^2 / (2 sigma^2)::

    var(w)       >= 24 sigma^2 / (A^2 N (N^2 - 1))    (rad/sample)^2; twice the complex tone's
    var(A)       >= 2 sigma^2 / N
    var(B)       >= sigma^2 / N
    var(phi_c)   >= 2 sigma^2 / (A^2 N)               phase at the centre
    var(phi_0) = var(phi_{N-1}) >= 4 sigma^2 (2N - 1) / (A^2 N (N + 1))   first or last sample

which are Kay's (Fundamentals of Statistical Signal Processing I, Example 3.14) bounds for
the real sinusoid, plus the offset.

The module also holds :func:`least_squares_fit`, the maximum-likelihood (nonlinear least
squares) estimator of the same four parameters, which attains the bound at high SNR; the
tests use it to check the bound by Monte Carlo.
"""

from __future__ import annotations

import sinewatch.host_arithmetic  # noqa: F401  # first, before numpy loads (its docstring says why)

# isort: split

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

__all__ = [
    "Bound",
    "crlb",
    "crlb_asymptotic",
    "crlb_tones",
    "fisher_information",
    "least_squares_fit",
]


@dataclass(frozen=True)
class Bound:
    """Variances (the bound) of unbiased estimators; the ``*_std`` properties give the
    square roots. Frequency in Hz^2, phase in rad^2 (at the reference sample)."""

    frequency_hz: float
    amplitude: float
    phase_rad: float
    offset: float

    frequency_hz_std = property(lambda self: math.sqrt(self.frequency_hz), doc="sqrt of the frequency bound, Hz")
    amplitude_std = property(lambda self: math.sqrt(self.amplitude), doc="sqrt of the amplitude bound")
    phase_rad_std = property(lambda self: math.sqrt(self.phase_rad), doc="sqrt of the phase bound, rad")
    offset_std = property(lambda self: math.sqrt(self.offset), doc="sqrt of the offset bound")

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


def _check(n: int, amplitude: float, noise_std: float, sample_rate_hz: float) -> None:
    if n < 4:
        raise ValueError(f"n: expected at least 4 samples (4 unknowns), got {n}")
    if not amplitude > 0:
        raise ValueError(f"amplitude: expected > 0, got {amplitude}")
    if not noise_std > 0:
        raise ValueError(f"noise_std: expected > 0, got {noise_std}")
    if not sample_rate_hz > 0:
        raise ValueError(f"sample_rate_hz: expected > 0, got {sample_rate_hz}")


def fisher_information(
    n: int,
    frequency_hz: float,
    amplitude: float,
    phase_centre_rad: float,
    noise_std: float,
    sample_rate_hz: float = 1.0,
) -> np.ndarray:
    """The 4x4 Fisher information of (w [rad/sample], A, phi_c [rad], B) for ``n`` samples,
    with the time index centred: ``phi_c`` is the phase at sample (n-1)/2."""
    _check(n, amplitude, noise_std, sample_rate_hz)
    w = 2.0 * math.pi * frequency_hz / sample_rate_hz
    m = np.arange(n, dtype=np.float64) - 0.5 * (n - 1)
    psi = w * m + phase_centre_rad
    c, s = np.cos(psi), np.sin(psi)
    g = np.stack([amplitude * m * c, s, amplitude * c, np.ones(n)])  # (4, n)
    fim: np.ndarray = (g @ g.T) / noise_std**2
    return fim


def _inverse(fim: np.ndarray) -> np.ndarray:
    d = 1.0 / np.sqrt(np.diag(fim))
    scaled = fim * d[:, None] * d[None, :]
    return np.linalg.inv(scaled) * d[:, None] * d[None, :]


def crlb(
    n: int,
    frequency_hz: float,
    amplitude: float,
    phase_rad: float,
    noise_std: float,
    sample_rate_hz: float = 1.0,
    reference: int | None = None,
) -> Bound:
    """Exact bound for ``n`` samples. ``phase_rad`` is the true phase at sample ``reference``
    (default ``n - 1``, the last sample), and the phase bound is for that sample too."""
    _check(n, amplitude, noise_std, sample_rate_hz)
    ref = n - 1 if reference is None else int(reference)
    w = 2.0 * math.pi * frequency_hz / sample_rate_hz
    d = ref - 0.5 * (n - 1)
    phase_centre = phase_rad - w * d
    cov = _inverse(fisher_information(n, frequency_hz, amplitude, phase_centre, noise_std, sample_rate_hz))
    var_w = cov[0, 0]
    var_phi = cov[2, 2] + d * d * var_w + 2.0 * d * cov[0, 2]
    hz_per_rad = sample_rate_hz / (2.0 * math.pi)
    return Bound(
        frequency_hz=float(var_w * hz_per_rad**2),
        amplitude=float(cov[1, 1]),
        phase_rad=float(var_phi),
        offset=float(cov[3, 3]),
    )


def crlb_asymptotic(
    n: int,
    amplitude: float,
    noise_std: float,
    sample_rate_hz: float = 1.0,
    reference: str = "last",
) -> Bound:
    """Large-N closed form (see the module docstring). ``reference`` is where the phase
    is taken: "last" or "first" sample (same bound), or "centre"."""
    _check(n, amplitude, noise_std, sample_rate_hz)
    s2, a2 = noise_std**2, amplitude**2
    var_w = 24.0 * s2 / (a2 * n * (n * n - 1.0))
    if reference in ("last", "first"):
        var_phi = 4.0 * s2 * (2.0 * n - 1.0) / (a2 * n * (n + 1.0))
    elif reference == "centre":
        var_phi = 2.0 * s2 / (a2 * n)
    else:
        raise ValueError(f"reference: expected 'last', 'first' or 'centre', got {reference!r}")
    hz_per_rad = sample_rate_hz / (2.0 * math.pi)
    return Bound(
        frequency_hz=var_w * hz_per_rad**2,
        amplitude=2.0 * s2 / n,
        phase_rad=var_phi,
        offset=s2 / n,
    )


def crlb_tones(
    n: int,
    frequency_hz: list[float],
    amplitude: list[float],
    phase_rad: list[float],
    noise_std: float,
    sample_rate_hz: float = 1.0,
    trend: bool = False,
) -> list[Bound]:
    """Exact bound for K tones plus an offset (and, with ``trend``, a linear trend) in
    ``n`` samples: ``y[n] = B [+ D m] + sum_k A_k sin(w_k m + phi_k,c) + v[n]``.

    Same construction as :func:`crlb` (centred time, Jacobi-scaled inverse) on the
    3K + 1 (+ 1) parameters; one :class:`Bound` per tone, phases at the last sample, the
    offset bound (at the last sample too) repeated in each. With K = 1 and no trend it
    equals :func:`crlb`.
    """
    k = len(frequency_hz)
    if not (len(amplitude) == len(phase_rad) == k) or k == 0:
        raise ValueError(f"tones: expected equal, non-empty lists, got {k}, {len(amplitude)}, {len(phase_rad)}")
    for a in amplitude:
        _check(n, a, noise_std, sample_rate_hz)
    d = 0.5 * (n - 1)  # last sample, from the centre
    m = np.arange(n, dtype=np.float64) - d
    cols = []
    for f, a, ph in zip(frequency_hz, amplitude, phase_rad, strict=True):
        w = 2.0 * math.pi * f / sample_rate_hz
        psi = w * m + (ph - w * d)
        cols += [a * m * np.cos(psi), np.sin(psi), a * np.cos(psi)]
    cols.append(np.ones(n))
    if trend:
        cols.append(m / d)
    g = np.stack(cols)
    cov = _inverse((g @ g.T) / noise_std**2)
    hz_per_rad = sample_rate_hz / (2.0 * math.pi)
    off = 3 * k
    var_b = cov[off, off] + (cov[off + 1, off + 1] + 2.0 * cov[off, off + 1] if trend else 0.0)
    out = []
    for j in range(k):
        i = 3 * j
        var_w = cov[i, i]
        var_phi = cov[i + 2, i + 2] + d * d * var_w + 2.0 * d * cov[i, i + 2]
        out.append(
            Bound(
                frequency_hz=float(var_w * hz_per_rad**2),
                amplitude=float(cov[i + 1, i + 1]),
                phase_rad=float(var_phi),
                offset=float(var_b),
            )
        )
    return out


# ---- the maximum-likelihood estimator (reference for the Monte Carlo check) -------------


def _linear_fit(y: np.ndarray, m: np.ndarray, w: float) -> tuple[np.ndarray, float]:
    h = np.stack([np.sin(w * m), np.cos(w * m), np.ones_like(m)], axis=1)
    coef, *_ = np.linalg.lstsq(h, y, rcond=None)
    r = y - h @ coef
    return coef, float(r @ r)


def least_squares_fit(
    y: np.ndarray, sample_rate_hz: float = 1.0, zero_pad: int = 16
) -> tuple[float, float, float, float]:
    """Maximum-likelihood fit of ``B + A sin(w n + phi)`` to ``y`` (white Gaussian noise).

    Coarse search on the zero-padded periodogram of the de-meaned record, then the exact
    concentrated cost (``w`` alone; A, phi, B by linear least squares) minimised in a
    bracket of one padded bin, then Gauss-Newton on all four parameters.
    Returns (frequency_hz, amplitude, phase_rad at the last sample, offset).
    """
    y = np.asarray(y, dtype=np.float64)
    n = y.size
    if n < 4:
        raise ValueError(f"y: expected at least 4 samples, got {n}")
    m = np.arange(n, dtype=np.float64) - 0.5 * (n - 1)
    nfft = zero_pad * (1 << math.ceil(math.log2(n)))
    spec = np.abs(np.fft.rfft(y - y.mean(), nfft))
    spec[0] = 0.0
    k = int(np.argmax(spec))
    bin_w = 2.0 * math.pi / nfft
    lo, hi = max((k - 1) * bin_w, 1e-9), min((k + 1) * bin_w, math.pi - 1e-9)
    res = minimize_scalar(
        lambda w: _linear_fit(y, m, w)[1], bounds=(lo, hi), method="bounded", options={"xatol": 1e-12}
    )
    w = float(res.x)
    coef, _ = _linear_fit(y, m, w)
    # coef: a sin(wm) + b cos(wm) + B = A sin(wm + phi_c), A cos(phi_c) = a, A sin(phi_c) = b
    amp, phi_c, off = math.hypot(coef[0], coef[1]), math.atan2(coef[1], coef[0]), coef[2]
    theta = np.array([w, amp, phi_c, off])
    for _ in range(5):  # Gauss-Newton polish on the full model
        psi = theta[0] * m + theta[2]
        r = y - (theta[3] + theta[1] * np.sin(psi))
        g = np.stack([theta[1] * m * np.cos(psi), np.sin(psi), theta[1] * np.cos(psi), np.ones(n)], axis=1)
        step, *_ = np.linalg.lstsq(g, r, rcond=None)
        theta = theta + step
        if np.all(np.abs(step) < 1e-14 * (1.0 + np.abs(theta))):
            break
    w, amp, phi_c, off = theta
    if amp < 0:
        amp, phi_c = -amp, phi_c + math.pi
    phase_last = phi_c + w * 0.5 * (n - 1)
    phase_last = math.pi - float(np.mod(math.pi - phase_last, 2.0 * math.pi))  # (-pi, pi]
    return float(w * sample_rate_hz / (2.0 * math.pi)), float(amp), float(phase_last), float(off)
