"""``ges-kalman``'s maths as compiled kernels: the Kalman filter on the paper's eq. (6), the
recovery of the parameters from its state (eq. 20-21, Section III-E, and the amplitude and
phase derived in :mod:`sinewatch.estimators.ges_kalman`, whose docstring states the paper's
model, eq. 1 and 4-6), and the actual-error covariance behind the reported standard
deviations (U1-U6, below), and the second-order bias that the reported parameters are
corrected for (B1-B4, below). Pure functions: block + state -> outputs + new state. The thin
class and its parameters are :mod:`sinewatch.estimators.ges_kalman`; the bank of channels
:mod:`sinewatch.estimators._ges_kalman_bank`.

Reported standard deviations (``Track.std``; derived here, not in the paper)
--------------------------------------------------------------------------
Not the filter's own P: P is the covariance the filter would have if its model held (a
random walk of the state with covariance Q per sample, white measurement noise of
variance R). On a stationary tone neither holds, and the measured sample also enters the
transition matrix A(k) (eq. 6), so its noise drives the state too; mapped to the
parameters, P overstates their errors 2 to 40 times. Instead the actual error
``e(k) = x_hat(k) - x(k)`` is propagated to first order in the noise, with the filter's own
gains K(k). Let v be the noise on sample s = y(k+1), variance sigma^2. It enters A(k)
(``A(k) - A_true(k) = v e12``) and the measurement ``y(k+1) = C x(k+1) + v``::

    e-(k+1) = A(k) e(k) + g(k) v,      g(k) = (0, x3_hat(k), 0, 0)^T           (U1)
    e(k+1)  = (I - K C) e-(k+1) + K v = F(k) e(k) + h(k) v,
              F(k) = (I - K C) A(k),   h(k) = g(k) + K     (C g = 0)            (U2)

Its covariance splits into the start's part and the noise's part, ``Pa = T + sigma^2 U``::

    T(k+1) = F(k) T(k) F(k)^T,                   T(0) = p0 I                     (U3)
    U(k+1) = F(k) U(k) F(k)^T + h(k) h(k)^T,     U(0) = 0                        (U4)

sigma^2 is estimated from the innovations e = y(k+1) - C x_pred, whose variance is
``C A T A^T C^T + sigma^2 (1 + C A U A^T C^T)``; the start's term is left out (p0 I
overstates the actual initial error). With u = e^2 / (1 + C A U A^T C^T) and
exponentially weighted means of time constant N_sigma = 128 samples (``NOISE_MEMORY``),
started at zero and divided by their weight w (so that no initial guess, such as R,
lingers: R is often far from sigma^2)::

    <z>(k+1) = l <z>(k) + (1 - l) z,  w(k+1) = l w(k) + (1 - l),  l = 1 - 1/N_sigma
    sigma_hat^2 = <u> / w                                                        (U5)

The innovations of the start's transient are far larger than the noise and an exponential
mean forgets them only as l^k (at 60 dB SNR, sigma_hat would still be 9 times too large
after 1,000 samples); their logarithms are forgotten as fast but exceed log sigma^2 only by
a few units, so ``<u>`` is capped by the estimate the mean of log u gives for Gaussian
noise (E log z^2 = psi(1/2) + log 2 for z ~ N(0, 1)), times ``ROBUST_CAP`` = 4 so that
heavier-tailed noise is not cut::

    <u> <- min(<u>, 4 w exp(<log u> / w - psi(1/2) - log 2))                     (U5a)

The reported parameters p = (f, A, theta, B) are the functions of x_hat of eq. (21),
Section III-E and the amplitude and phase recovery of :mod:`sinewatch.estimators.ges_kalman`;
their covariance follows by the delta method with J = dp/dx at the reported state (x_hat
less its bias, B4; written out in ``_parameter_std``)::

    sd(p_i) = sqrt( (J (T + sigma_hat^2 U) J^T)_ii )                             (U6)

The recursion only reads the filter's quantities (its state is the separate ``unc``
array): the filter's state is bit for bit that of the filter without it.

Bias of the reported parameters (derived here, not in the paper)
----------------------------------------------------------------
U1-U6 treat the gains K(k) as given. They are not: P, and so K, is computed from the same
noisy samples as the state (the sample s enters A(k) in P's prediction, eq. 6), so the gain
and the error are correlated and the update's mean ``E[K(k) (y(k+1) - C x_pred)]`` is not
zero at second order in the noise. At 0 dB SNR (5 kHz, 50 Hz, the default Q) this biases the
frequency up by 0.38-0.43 of its reported sd (``sinewatch bench calibration --estimators
ges-kalman``; gains computed from the clean signal, or from an independent noise of the same
level, leave 0.13). To first order, ``P(k|k) = P_bar + sum_j dP_j v_j`` and
``e(k) = sum_j e_j v_j`` (U2); the derivative of the Riccati update at its optimal gain is
``(I - K C) dN (I - K C)^T``, so with N = A(k) P A(k)^T + Q::

    dP(k+1) = F(k) dP(k) F(k)^T + Dv(k) v(k+1),
    Dv(k) = (I - K C) (e12 P A(k)^T + A(k) P e21) (I - K C)^T    (P = P(k|k))       (B1)

Their cross moment per unit sigma^2, the 4 x 4 x 4 tensor ``M = sum_j dP_j (x) e_j``
(symmetric in its first two indices: 40 entries), follows from (U2) and (B1)::

    M(k+1) = (F(k) x F(k) x F(k)) M(k) + Dv(k) (x) h(k),        M(0) = 0              (B2)

The gain's deviation ``dK = (I - K C) A dP A^T C^T / S`` (S = C P(k+1|k) C^T + R) meets the
innovation's error ``-C A(k) e(k)``, and the gain's own dependence on the sample,
``d k1 / ds = (p02 + p12) / S``, meets its noise v(k+1); the mean error per unit sigma^2::

    b(k+1) = F(k) b(k) - (I - K C) A(k) m(k) / S + e1 (p02 + p12) / S,    b(0) = 0,
    m_a = sum over b, c in {0, 1} of M[a, b, c]                                   (B3)

and the parameters are reported at the state less its bias, sigma_hat^2 from (U5)::

    x_reported = x_hat - sigma_hat^2 b                                            (B4)

Left out: the curvature of the recovery (eq. 21: -sd_f^2 / (2 f), 0.02 Hz at 0 dB) and terms
of third order. (B2) costs ~550 flops a sample (the filter and U ~255), so
``bias_correction = false`` skips (B1)-(B4) and reports x_hat as it is.
"""

from __future__ import annotations

import math

import numpy as np

from sinewatch.estimators import detmath
from sinewatch.estimators.base import kernel, undefined_row

NOISE_MEMORY = 128  # N_sigma, samples: time constant of the noise-variance estimate (U5)
T_NEGLIGIBLE = 1e-100  # trace of T below which T (U3) is set to 0 and no longer propagated
LOG_CHI2_MEAN = -1.2703628454614782  # E[log z^2] for z ~ N(0, 1): psi(1/2) + log 2, (U5a)
ROBUST_CAP = 4.0  # (U5a): <u> at most four times the log-mean's estimate of sigma^2
TINY = 1e-300  # log(0) guard, (U5a)
# _noise_means skips exp when <u> is below the cap's lower bound times this: 1e-12 is ~4,000
# times the bound's worst relative rounding (a few 1e-16) plus exp's (< 1 ulp)
EXP_SCREEN_MARGIN = 1.0 - 1e-12
UNC_BASE = 35  # T (16), U (16), <u>, the weight w, <log u>
BIAS_SIZE = 44  # the bias recursion (B2)-(B3): M (40), b (4)
UNC_SIZE = UNC_BASE + BIAS_SIZE


@kernel(inline="always")
def _filter_step(
    s: float,
    x1: float, x2: float, x3: float, x4: float,
    p00: float, p01: float, p02: float, p03: float, p11: float,
    p12: float, p13: float, p22: float, p23: float, p33: float,
    q0: float, q1: float, q2: float, q3: float, R: float,
) -> tuple[
    float, float, float, float, float, float, float, float, float, float,
    float, float, float, float, float, float, float, float, float, float,
]:  # fmt: skip
    """One sample ``s = s(t_{k+1})`` of the Kalman filter on (6): the new ``(x1..x4, p00, p01,
    p02, p03, p11, p12, p13, p22, p23, p33)``, then the innovation ``e``, the gain
    ``k0..k3`` and ``1 / (C P(k+1|k) C^T + R)``. The one definition, called by the single-channel kernel and by the bank."""
    # prediction x(k+1|k) = A(k) x(k|k), eq. (6)
    xp1 = x1 + x2
    xp2 = x2 + s * x3 + x4
    # P(k+1|k) = A(k) P A(k)^T + Q, written out (A = I + e01 + s e12 + e13)
    m11 = p11 + s * p12 + p13
    m12 = p12 + s * p22 + p23
    m13 = p13 + s * p23 + p33
    n00 = p00 + 2.0 * p01 + p11 + q0
    n01 = p01 + p11 + s * (p02 + p12) + p03 + p13
    n02 = p02 + p12
    n03 = p03 + p13
    n11 = m11 + s * m12 + m13 + q1
    n12 = m12
    n13 = m13
    n22 = p22 + q2
    n23 = p23
    n33 = p33 + q3
    # update with y(k+1) = C x(k+1): scalar innovation and gain K = P C^T / (C P C^T + R)
    e = s - xp1
    inv_S = 1.0 / (n00 + R)
    k0 = n00 * inv_S
    k1 = n01 * inv_S
    k2 = n02 * inv_S
    k3 = n03 * inv_S
    x1 = xp1 + k0 * e
    x2 = xp2 + k1 * e
    x3 = x3 + k2 * e
    x4 = x4 + k3 * e
    # P(k+1|k+1) = P(k+1|k) - K S K^T (symmetric by construction)
    return (
        x1, x2, x3, x4,
        n00 - k0 * n00, n01 - k0 * n01, n02 - k0 * n02, n03 - k0 * n03,
        n11 - k1 * n01, n12 - k1 * n02, n13 - k1 * n03,
        n22 - k2 * n02, n23 - k2 * n03, n33 - k3 * n03,
        e, k0, k1, k2, k3, inv_S,
    )  # fmt: skip


@kernel(inline="always")
def _propagate_error(
    z00: float, z01: float, z02: float, z03: float,
    z10: float, z11: float, z12: float, z13: float,
    z20: float, z21: float, z22: float, z23: float,
    z30: float, z31: float, z32: float, z33: float,
    s: float, k0: float, k1: float, k2: float, k3: float,
    h0: float, h1: float, h2: float, h3: float, w: float,
) -> tuple[
    float, float, float, float, float, float, float, float,
    float, float, float, float, float, float, float, float,
]:  # fmt: skip
    """``Z <- (I - K C) A(k) Z A(k)^T (I - K C)^T + w h h^T``, eq. (U3)-(U4), on the 16
    entries of Z (row-major) held in registers; ``A(k) = I + e01 + s e12 + e13`` (eq. 6),
    ``C = e0``. Written out entry by entry, each in the order of the matrix form: M = A Z
    (row operations), M <- M A^T (column operations), then
    ``Z_ij = M_ij - K_i M_0j - M_i0 K_j + K_i K_j M_00 + w h_i h_j``."""
    # M = A Z (row operations), eq. (6)
    a00, a01, a02, a03 = z00 + z10, z01 + z11, z02 + z12, z03 + z13
    a10, a11, a12, a13 = z10 + s * z20 + z30, z11 + s * z21 + z31, z12 + s * z22 + z32, z13 + s * z23 + z33
    # M = (A Z) A^T (column operations): columns 0 and 1 change, 2 and 3 stay
    m00, m01 = a00 + a01, a01 + s * a02 + a03
    m10, m11 = a10 + a11, a11 + s * a12 + a13
    m20, m21 = z20 + z21, z21 + s * z22 + z23
    m30, m31 = z30 + z31, z31 + s * z32 + z33
    m02, m03, m12, m13 = a02, a03, a12, a13
    m22, m23, m32, m33 = z22, z23, z32, z33
    # (I - K C) M (I - K C)^T + w h h^T, eq. (U2)-(U4)
    return (
        m00 - k0 * m00 - m00 * k0 + k0 * k0 * m00 + w * h0 * h0,
        m01 - k0 * m01 - m00 * k1 + k0 * k1 * m00 + w * h0 * h1,
        m02 - k0 * m02 - m00 * k2 + k0 * k2 * m00 + w * h0 * h2,
        m03 - k0 * m03 - m00 * k3 + k0 * k3 * m00 + w * h0 * h3,
        m10 - k1 * m00 - m10 * k0 + k1 * k0 * m00 + w * h1 * h0,
        m11 - k1 * m01 - m10 * k1 + k1 * k1 * m00 + w * h1 * h1,
        m12 - k1 * m02 - m10 * k2 + k1 * k2 * m00 + w * h1 * h2,
        m13 - k1 * m03 - m10 * k3 + k1 * k3 * m00 + w * h1 * h3,
        m20 - k2 * m00 - m20 * k0 + k2 * k0 * m00 + w * h2 * h0,
        m21 - k2 * m01 - m20 * k1 + k2 * k1 * m00 + w * h2 * h1,
        m22 - k2 * m02 - m20 * k2 + k2 * k2 * m00 + w * h2 * h2,
        m23 - k2 * m03 - m20 * k3 + k2 * k3 * m00 + w * h2 * h3,
        m30 - k3 * m00 - m30 * k0 + k3 * k0 * m00 + w * h3 * h0,
        m31 - k3 * m01 - m30 * k1 + k3 * k1 * m00 + w * h3 * h1,
        m32 - k3 * m02 - m30 * k2 + k3 * k2 * m00 + w * h3 * h2,
        m33 - k3 * m03 - m30 * k3 + k3 * k3 * m00 + w * h3 * h3,
    )


@kernel(inline="always")
def _noise_means(
    u: float, w: float, m_u: float, m_l: float, lam: float, x_ref: float, e_ref: float
) -> tuple[float, float, float, float, float]:
    """One step of the exponentially weighted means of (U5) and the cap (U5a): the new
    ``(w, <u>, <log u>)``, then the new ``(x_ref, e_ref)``.

    ``e_ref = exp(x_ref)`` is the last exp this step took (start a block with 0, 0). Since
    ``exp(x) >= exp(x_ref) (1 + x - x_ref)``, a ``<u>`` below ``ROBUST_CAP w`` times that
    bound (less a margin far above the rounding of exp and of the bound) is below the cap
    (U5a) whatever exp's last bit, and ``min`` returns it: the exp is then skipped, with the
    same result. On a stationary signal the cap rarely binds and the exponent drifts slowly,
    so most samples take the log only."""
    w, m_u, m_l, x, screened = _noise_means_screened(u, detmath.log(max(u, TINY)), w, m_u, m_l, lam, x_ref, e_ref)
    if screened:
        return w, m_u, m_l, x_ref, e_ref
    m_u, e = _noise_means_cap(m_u, w, x)
    return w, m_u, m_l, x, e


@kernel(inline="always")
def _noise_means_screened(
    u: float, log_u: float, w: float, m_u: float, m_l: float, lam: float, x_ref: float, e_ref: float
) -> tuple[float, float, float, float, bool]:
    """The means' step (U5) without the cap: the new ``(w, <u>, <log u>)``, the cap's exponent
    ``x`` (U5a) and whether the bound of :func:`_noise_means` shows that the cap cannot bind (then
    ``<u>`` is final and exp is not taken). Branch-free (``&``, not ``and``), so that a bank can
    run it for 8 lanes as vectors and take :func:`_noise_means_cap` only for the lanes it fails."""
    w = lam * w + (1.0 - lam)  # (U5)
    m_u = lam * m_u + (1.0 - lam) * u
    m_l = lam * m_l + (1.0 - lam) * log_u
    x = m_l / w - LOG_CHI2_MEAN  # (U5a)'s exponent
    d1 = 1.0 + (x - x_ref)  # exp(x) >= e_ref d1
    return w, m_u, m_l, x, (d1 > 0.5) & (m_u <= ROBUST_CAP * w * e_ref * d1 * EXP_SCREEN_MARGIN)  # False on NaN


@kernel(inline="always")
def _noise_means_cap(m_u: float, w: float, x: float) -> tuple[float, float]:
    """The cap (U5a) on ``<u>`` with its exp taken: the new ``<u>`` and ``exp(x)``."""
    e = math.exp(x)
    return min(m_u, ROBUST_CAP * w * e), e  # (U5a)


@kernel(inline="always")
def _store4x4(
    Z: np.ndarray,
    z00: float, z01: float, z02: float, z03: float,
    z10: float, z11: float, z12: float, z13: float,
    z20: float, z21: float, z22: float, z23: float,
    z30: float, z31: float, z32: float, z33: float,
) -> None:  # fmt: skip
    """Write the 16 entries (row-major) into the 4 x 4 array ``Z``."""
    Z[0, 0], Z[0, 1], Z[0, 2], Z[0, 3] = z00, z01, z02, z03
    Z[1, 0], Z[1, 1], Z[1, 2], Z[1, 3] = z10, z11, z12, z13
    Z[2, 0], Z[2, 1], Z[2, 2], Z[2, 3] = z20, z21, z22, z23
    Z[3, 0], Z[3, 1], Z[3, 2], Z[3, 3] = z30, z31, z32, z33


@kernel(inline="always")
def _store_column(
    G: np.ndarray,
    o: int,
    st: int,
    c: int,
    y: tuple[float, ...],
    v01: float,
    v11: float,
    v12: float,
    v13: float,
    h: float,
) -> None:
    """Column ``c`` of M (B2), ``M[., ., c] = y + Dv h_c`` with ``y`` from :func:`_sandwich`; Dv
    is 0 but at 01, 11, 12 and 13."""
    G[o + c * st] = y[0]
    G[o + (4 + c) * st] = y[1] + v01 * h
    G[o + (8 + c) * st] = y[2]
    G[o + (12 + c) * st] = y[3]
    G[o + (16 + c) * st] = y[4] + v11 * h
    G[o + (20 + c) * st] = y[5] + v12 * h
    G[o + (24 + c) * st] = y[6] + v13 * h
    G[o + (28 + c) * st] = y[7]
    G[o + (32 + c) * st] = y[8]
    G[o + (36 + c) * st] = y[9]


@kernel(inline="always")
def _sandwich(
    z00: float, z01: float, z02: float, z03: float, z11: float, z12: float, z13: float, z22: float, z23: float,
    z33: float, s: float, k0: float, k1: float, k2: float, k3: float,
) -> tuple[float, float, float, float, float, float, float, float, float, float]:  # fmt: skip
    """``F Z F^T`` on the 10 distinct entries of a symmetric Z (order 00 01 02 03 11 12 13 22 23
    33), F = (I - K C) A(k): A Z A^T written out as in :func:`_filter_step`, then
    ``(I - K C) . (I - K C)^T``, (B2)."""
    m11 = z11 + s * z12 + z13
    m12 = z12 + s * z22 + z23
    m13 = z13 + s * z23 + z33
    n00 = z00 + 2.0 * z01 + z11
    n01 = z01 + z11 + s * (z02 + z12) + z03 + z13
    n02, n03 = z02 + z12, z03 + z13
    n11 = m11 + s * m12 + m13
    n12, n13, n22, n23, n33 = m12, m13, z22, z23, z33
    return (
        n00 - k0 * n00 - n00 * k0 + k0 * k0 * n00,
        n01 - k0 * n01 - n00 * k1 + k0 * k1 * n00,
        n02 - k0 * n02 - n00 * k2 + k0 * k2 * n00,
        n03 - k0 * n03 - n00 * k3 + k0 * k3 * n00,
        n11 - k1 * n01 - n01 * k1 + k1 * k1 * n00,
        n12 - k1 * n02 - n01 * k2 + k1 * k2 * n00,
        n13 - k1 * n03 - n01 * k3 + k1 * k3 * n00,
        n22 - k2 * n02 - n02 * k2 + k2 * k2 * n00,
        n23 - k2 * n03 - n02 * k3 + k2 * k3 * n00,
        n33 - k3 * n03 - n03 * k3 + k3 * k3 * n00,
    )


@kernel(inline="always")
def _bias_head(
    G: np.ndarray, o: int, st: int, s: float, k0: float, k1: float, k2: float, k3: float, inv_s: float,
    p02: float, p12: float, p22: float, p23: float,
) -> tuple[float, float, float, float]:  # fmt: skip
    """The first part of :func:`_propagate_bias`: b (B3) from M as it was, and the entries of Dv
    (B1) that are not 0, returned as (v01, v11, v12, v13)."""
    # m_a = sum over b, c in {0, 1} of M[a, b, c]: dK's factor A dP A^T C^T and C A e(k) (B3)
    m0 = G[o] + G[o + 1 * st] + G[o + 4 * st] + G[o + 5 * st]
    m1 = G[o + 4 * st] + G[o + 5 * st] + G[o + 16 * st] + G[o + 17 * st]
    m2 = G[o + 8 * st] + G[o + 9 * st] + G[o + 20 * st] + G[o + 21 * st]
    m3 = G[o + 12 * st] + G[o + 13 * st] + G[o + 24 * st] + G[o + 25 * st]
    # b <- (I - K C) (A b - A m / S) + e1 (p02 + p12) / S, (B3)
    b0, b1, b2, b3 = G[o + 40 * st], G[o + 41 * st], G[o + 42 * st], G[o + 43 * st]
    c0 = (b0 + b1) - (m0 + m1) * inv_s
    c1 = (b1 + s * b2 + b3) - (m1 + s * m2 + m3) * inv_s
    c2 = b2 - m2 * inv_s
    c3 = b3 - m3 * inv_s
    G[o + 40 * st] = c0 - k0 * c0
    G[o + 41 * st] = c1 - k1 * c0 + (p02 + p12) * inv_s
    G[o + 42 * st] = c2 - k2 * c0
    G[o + 43 * st] = c3 - k3 * c0
    # dN/ds, N = A P A^T + Q (eq. 6): the entries that hold s; Dv = (I - K C) dN (I - K C)^T (B1);
    # its entries 00, 02, 03, 22, 23, 33 are 0
    d01 = p02 + p12
    d11 = 2.0 * (p12 + s * p22 + p23)
    v01 = d01 - k0 * d01
    v11 = d11 - k1 * d01 - d01 * k1
    v12 = p22 - d01 * k2
    v13 = p23 - d01 * k3
    return v01, v11, v12, v13


@kernel(inline="always")
def _bias_pair(G: np.ndarray, i: int, st: int, s: float, k0: float, k1: float, k2: float, k3: float) -> None:
    """M's index c of one pair (a, b) at ``G[i + c st]``: A, then I - K C (B2)."""
    z0, z1, z2, z3 = G[i], G[i + st], G[i + 2 * st], G[i + 3 * st]
    w0, w1 = z0 + z1, z1 + s * z2 + z3
    G[i], G[i + st], G[i + 2 * st], G[i + 3 * st] = w0 - k0 * w0, w1 - k1 * w0, z2 - k2 * w0, z3 - k3 * w0


@kernel(inline="always")
def _bias_column(
    G: np.ndarray, o: int, st: int, c: int, s: float, k0: float, k1: float, k2: float, k3: float,
    v01: float, v11: float, v12: float, v13: float, h: float,
) -> None:  # fmt: skip
    """Column ``c`` of M: F . F^T on the pair's two indices, plus Dv h_c (B2)."""
    i = o + c * st
    y = _sandwich(
        G[i], G[i + 4 * st], G[i + 8 * st], G[i + 12 * st], G[i + 16 * st],
        G[i + 20 * st], G[i + 24 * st], G[i + 28 * st], G[i + 32 * st], G[i + 36 * st],
        s, k0, k1, k2, k3,
    )  # fmt: skip
    _store_column(G, o, st, c, y, v01, v11, v12, v13, h)


# compiled once and called (not inlined by numba at the IR level, to keep the kernel's compile
# time down); LLVM may still inline it. The bank runs the same three steps lane-major, each a
# loop over the lanes that the compiler vectorises (_ges_kalman_bank._bank_bias).
@kernel(refcount=False)
def _propagate_bias(
    G: np.ndarray, o: int, st: int, s: float, k0: float, k1: float, k2: float, k3: float, h1: float, inv_s: float,
    p00: float, p01: float, p02: float, p03: float, p11: float, p12: float, p13: float, p22: float, p23: float, p33: float,
) -> None:  # fmt: skip
    """One sample of the bias recursion (B1)-(B3) on ``G[o + i st]``, i = 0..43: M (B2), 40 entries
    ``M[a, b, c]`` at ``4 pair(a, b) + c`` (pairs a <= b in P's order 00 01 02 03 11 12 13 22 23
    33), then b (B3), 4 entries. ``p..`` is P(k|k) before the step, ``k..`` the gain, ``h1`` = k1 +
    x3_hat (U2), ``inv_s`` = 1 / (C P(k+1|k) C^T + R). Constant offsets times a stride: the
    single kernel runs it on its own array (stride 1)."""
    v01, v11, v12, v13 = _bias_head(G, o, st, s, k0, k1, k2, k3, inv_s, p02, p12, p22, p23)
    # M <- (F x F x F) M + Dv x h, F = (I - K C) A(k) on each index (B2), in place (m and b
    # above have read M): first the index c, pair by pair (A, then I - K C) ...
    for p in range(10):
        _bias_pair(G, o + 4 * p * st, st, s, k0, k1, k2, k3)
    # ... then the pair's two indices, column c by column, plus Dv h_c; h = (k0, h1, k2, k3)
    for c in range(4):
        h = k0 if c == 0 else (h1 if c == 1 else (k2 if c == 2 else k3))
        _bias_column(G, o, st, c, s, k0, k1, k2, k3, v01, v11, v12, v13, h)


@kernel(inline="always")
def _corrected(
    x1: float, x2: float, x3: float, x4: float, G: np.ndarray, o: int, st: int, s2: float, on: bool
) -> tuple[float, float, float, float]:  # fmt: skip
    """The state less its bias, x_hat - sigma_hat^2 b (B4), when ``on``; else x_hat as it is."""
    if not on:
        return x1, x2, x3, x4
    b = o + 40 * st
    return x1 - s2 * G[b], x2 - s2 * G[b + st], x3 - s2 * G[b + 2 * st], x4 - s2 * G[b + 3 * st]


@kernel(inline="always")
def _parameter_std(
    x1: float,
    x2: float,
    x3: float,
    x4: float,
    T: np.ndarray,
    U: np.ndarray,
    J: np.ndarray,
    s2: float,
    Ts: float,
    std: np.ndarray,
    row: int,
) -> None:
    """Row ``row`` of ``std``: sd of (f [Hz], A, theta, B) = sqrt(diag(J Pa J^T)) with
    ``Pa = T + s2 U`` (U1, U6); NaN outside (-4, 0) (eq. 20). J is the Jacobian of the
    recovery formulas (:mod:`sinewatch.estimators.ges_kalman`'s docstring) at x_hat, written into
    ``J`` (4 x 4, overwritten), which the caller owns: :func:`_estimate_row`, compiled without
    reference counting, allocates nothing."""
    if not (-4.0 < x3 < 0.0):
        for i in range(4):
            std[row, i] = np.nan
        return
    sh = math.sqrt(-0.25 * x3)  # sin(w Ts/2), eq. (4)
    ch = math.sqrt(1.0 + 0.25 * x3)  # cos(w Ts/2)
    dsh = -1.0 / (8.0 * sh)  # d sh / d x3
    dch = 1.0 / (8.0 * ch)  # d ch / d x3
    B = -x4 / x3  # Section III-E
    a_s = x1 - B  # A sin(theta_k)
    num = x2 / (2.0 * sh) + a_s * sh
    a_c = num / ch  # A cos(theta_k)
    amp2 = a_s * a_s + a_c * a_c
    amp = math.sqrt(amp2)
    # gradients with respect to (x1, x2, x3, x4)
    dB2, dB3 = x4 / (x3 * x3), -1.0 / x3
    das0, das2, das3 = 1.0, -dB2, -dB3
    dnum0 = das0 * sh
    dnum1 = 1.0 / (2.0 * sh)
    dnum2 = -x2 / (2.0 * sh * sh) * dsh + a_s * dsh + das2 * sh
    dnum3 = das3 * sh
    dac0 = dnum0 / ch
    dac1 = dnum1 / ch
    dac2 = dnum2 / ch - num / (ch * ch) * dch
    dac3 = dnum3 / ch
    for r in range(4):
        for i in range(4):
            J[r, i] = 0.0
    J[0, 2] = dsh / ch / (math.pi * Ts)  # f = asin(sh) / (pi Ts), eq. (21)
    das = (das0, 0.0, das2, das3)
    dac = (dac0, dac1, dac2, dac3)
    for i in range(4):
        J[1, i] = (a_s * das[i] + a_c * dac[i]) / amp  # A = hypot(a_s, a_c)
        J[2, i] = (a_c * das[i] - a_s * dac[i]) / amp2  # theta = atan2(a_s, a_c)
    J[3, 2] = dB2
    J[3, 3] = dB3
    for r in range(4):
        v = 0.0
        for i in range(4):
            for j in range(4):
                v += J[r, i] * (T[i, j] + s2 * U[i, j]) * J[r, j]
        std[row, r] = math.sqrt(max(v, 0.0))


@kernel(inline="always")
def _write_estimates(
    out: np.ndarray, j: int, x1: float, x2: float, x3: float, x4: float, p22: float, Ts: float, rel_std: float
) -> None:
    """Row ``j`` of ``out``: the parameters recovered from x_hat (eq. 21, Section III-E; amplitude and phase as :mod:`sinewatch.estimators.ges_kalman` derives them)."""
    if -4.0 < x3 < 0.0:  # (20)
        sh = math.sqrt(-0.25 * x3)  # sin(w Ts/2), from (4)
        ch = math.sqrt(1.0 + 0.25 * x3)  # cos(w Ts/2)
        B = -x4 / x3  # Section III-E
        a_sin = x1 - B  # A sin(theta_k)
        a_cos = (x2 / (2.0 * sh) + a_sin * sh) / ch  # A cos(theta_k), derived above
        out[j, 0] = math.asin(sh) / (math.pi * Ts)  # eq. (21), w/(2 pi)
        out[j, 1] = math.hypot(a_sin, a_cos)
        out[j, 2] = math.atan2(a_sin, a_cos)
        out[j, 3] = B
        out[j, 4] = 1.0 if math.sqrt(max(p22, 0.0)) < rel_std * -x3 else 0.0
    else:
        undefined_row(out, j)


@kernel(refcount=False)
def _estimate_row(
    out: np.ndarray, std: np.ndarray, row: int, x1: float, x2: float, x3: float, x4: float, G: np.ndarray,
    o: int, st: int, s2: float, corr: bool, T: np.ndarray, U: np.ndarray, J: np.ndarray, p22: float, Ts: float,
    rel_std: float,
) -> None:  # fmt: skip
    """Row ``row`` of ``out`` and ``std`` from x_hat, its bias in ``G`` (from ``o``, stride ``st``),
    sigma_hat^2 ``s2``, T and U (in ``T`` and ``U``) and ``J`` as scratch: x_hat less its bias (B4),
    the standard deviations (U1, U6) and the parameters (eq. 21). Compiled once and called from
    both of the single kernel's rows (every sample's, or the last) and the bank's, not inlined by
    numba: each inlined copy of these bodies was typed and lowered anew (four copies across the
    single kernel and the bank). Without reference counting, so a call costs no atomic operations
    and LLVM may still inline it."""
    c1, c2, c3, c4 = _corrected(x1, x2, x3, x4, G, o, st, s2, corr)  # (B4)
    _parameter_std(c1, c2, c3, c4, T, U, J, s2, Ts, std, row)
    _write_estimates(out, row, c1, c2, c3, c4, p22, Ts, rel_std)


@kernel
def ges_kalman_kernel(
    y: np.ndarray, state: np.ndarray, unc: np.ndarray, consts: np.ndarray, last_only: bool
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """Run the filter over block ``y`` from ``state`` and ``unc`` and return
    ``(out, sse, std, new_state, new_unc)``.

    ``state`` is the ``xP`` array, ``unc`` the ``unc`` array (layouts:
    :meth:`sinewatch.estimators.ges_kalman.GesKalman._initial_state`); ``consts`` packs q1..q4, R, Ts,
    convergence_rel_std and the noise memory N_sigma. ``out`` has one row per sample (or
    one row, the last sample, when ``last_only``) with columns frequency_hz, amplitude,
    phase_rad, offset, converged (0/1); ``std`` the same rows with the standard deviations
    of frequency_hz, amplitude, phase_rad, offset (U1-U6). ``sse`` is the sum of squared
    innovations. Pure: the inputs are not modified. The uncertainty recursion only reads
    the filter's quantities, so ``out``, ``sse`` and ``new_state`` do not depend on it.
    """
    x1, x2, x3, x4 = state[0], state[1], state[2], state[3]
    p00, p01, p02, p03 = state[4], state[5], state[6], state[7]
    p11, p12, p13 = state[9], state[10], state[11]
    p22, p23, p33 = state[14], state[15], state[19]
    q0, q1, q2, q3 = consts[0], consts[1], consts[2], consts[3]
    R, Ts, rel_std = consts[4], consts[5], consts[6]
    lam = 1.0 - 1.0 / consts[7]  # (U5)
    corr = consts[8] != 0.0  # the bias recursion (B1)-(B4)
    n = y.shape[0]
    out = np.empty((1 if last_only else n, 5))
    std = np.empty((1 if last_only else n, 4))
    sse = 0.0
    # T and U (U3)-(U4) in registers, row-major; 4 x 4 arrays only for _parameter_std
    t00, t01, t02, t03, t10, t11, t12, t13 = unc[0], unc[1], unc[2], unc[3], unc[4], unc[5], unc[6], unc[7]
    t20, t21, t22, t23, t30, t31, t32, t33 = unc[8], unc[9], unc[10], unc[11], unc[12], unc[13], unc[14], unc[15]
    u00, u01, u02, u03, u10, u11, u12, u13 = unc[16], unc[17], unc[18], unc[19], unc[20], unc[21], unc[22], unc[23]
    u20, u21, u22, u23, u30, u31, u32, u33 = unc[24], unc[25], unc[26], unc[27], unc[28], unc[29], unc[30], unc[31]
    m_u, w, m_l = unc[32], unc[33], unc[34]
    G = unc[UNC_BASE:].copy()  # M and b (B2)-(B3)
    x_ref, e_ref = 0.0, 0.0  # _noise_means: no exp taken yet
    T = np.empty((4, 4))
    U = np.empty((4, 4))
    J = np.empty((4, 4))
    # last_only: the u of (U5) per sample, for a second pass that keeps log and exp (calls,
    # which spill every register) out of the filter's loop
    u_seq = np.empty(n if last_only else 0)
    for k in range(n):
        s = y[k]  # s(t_{k+1}) enters A(k), eq. (6)
        x3_prior = x3
        r00, r01, r02, r03, r11, r12, r13, r22, r23, r33 = p00, p01, p02, p03, p11, p12, p13, p22, p23, p33
        x1, x2, x3, x4, p00, p01, p02, p03, p11, p12, p13, p22, p23, p33, e, k0, k1, k2, k3, inv_S = _filter_step(
            s, x1, x2, x3, x4, p00, p01, p02, p03, p11, p12, p13, p22, p23, p33, q0, q1, q2, q3, R
        )
        sse += e * e
        # actual error covariance (U1-U5): innovation statistics from the predicted U,
        # then T <- F T F^T, U <- F U F^T + h h^T with F = (I - K C) A(k), h = K + g_k
        u = e * e / (1.0 + u00 + 2.0 * u01 + u11)  # (U5)
        if last_only:  # the means (U5)-(U5a) in a second pass (below), out of this loop
            u_seq[k] = u
        else:
            w, m_u, m_l, x_ref, e_ref = _noise_means(u, w, m_u, m_l, lam, x_ref, e_ref)
        h1 = k1 + x3_prior  # h = K + g_k (U2); h0, h2, h3 = k0, k2, k3
        if corr:  # (B2)-(B3), from P(k|k) before the step
            _propagate_bias(G, 0, 1, s, k0, k1, k2, k3, h1, inv_S, r00, r01, r02, r03, r11, r12, r13, r22, r23, r33)
        if t00 + t11 + t22 + t33 > T_NEGLIGIBLE:  # T decays geometrically (U3):
            t00, t01, t02, t03, t10, t11, t12, t13, t20, t21, t22, t23, t30, t31, t32, t33 = _propagate_error(
                t00, t01, t02, t03, t10, t11, t12, t13, t20, t21, t22, t23, t30, t31, t32, t33,
                s, k0, k1, k2, k3, k0, h1, k2, k3, 0.0,
            )  # fmt: skip
        elif t00 != 0.0:  # once negligible, zero (subnormal floats are ~100x slower)
            t00, t01, t02, t03, t10, t11, t12, t13 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            t20, t21, t22, t23, t30, t31, t32, t33 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33 = _propagate_error(
            u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33,
            s, k0, k1, k2, k3, k0, h1, k2, k3, 1.0,
        )  # (U4)  # fmt: skip
        if not last_only:  # row k (last_only: the last row, after the loop)
            _store4x4(T, t00, t01, t02, t03, t10, t11, t12, t13, t20, t21, t22, t23, t30, t31, t32, t33)
            _store4x4(U, u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33)
            s2 = m_u / w if w > 0.0 else R
            _estimate_row(out, std, k, x1, x2, x3, x4, G, 0, 1, s2, corr, T, U, J, p22, Ts, rel_std)
    if last_only:  # (U5)-(U5a) over the block's u, in order: the same values as in the loop
        for k in range(n):
            w, m_u, m_l, x_ref, e_ref = _noise_means(u_seq[k], w, m_u, m_l, lam, x_ref, e_ref)
        _store4x4(T, t00, t01, t02, t03, t10, t11, t12, t13, t20, t21, t22, t23, t30, t31, t32, t33)
        _store4x4(U, u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33)
        s2 = m_u / w if w > 0.0 else R
        _estimate_row(out, std, 0, x1, x2, x3, x4, G, 0, 1, s2, corr, T, U, J, p22, Ts, rel_std)
    new_state = np.array(
        [x1, x2, x3, x4,
         p00, p01, p02, p03,
         p01, p11, p12, p13,
         p02, p12, p22, p23,
         p03, p13, p23, p33]
    )  # fmt: skip
    new_unc = np.empty(UNC_SIZE)
    _store4x4(
        new_unc[0:16].reshape(4, 4), t00, t01, t02, t03, t10, t11, t12, t13, t20, t21, t22, t23, t30, t31, t32, t33
    )
    _store4x4(
        new_unc[16:32].reshape(4, 4), u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33
    )
    new_unc[32] = m_u
    new_unc[33] = w
    new_unc[34] = m_l
    new_unc[UNC_BASE:] = G
    return out, sse, std, new_state, new_unc
