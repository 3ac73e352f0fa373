"""``ges-kalman``: GES discrete-time Kalman observer for a biased sinusoid.

Paper: "A globally exponentially stable (GES) discrete-time observer for the parameters of
a biased sinusoid" (the authors and the year are not recorded here: the copy this was built
from does not print them).

Signal (eq. 1): ``y(k) = s(t_k) = A sin(w t_k + phi) + B``, sampled every ``Ts``.

State (Section III-A), with theta_k = w t_k + phi::

    x1(k) = s(t_k)                                   (measured)
    x2(k) = 2 A sin(w Ts/2) cos(theta_k + w Ts/2)
    x3(k) = -4 sin^2(w Ts/2)                          (4)
    x4(k) =  4 B sin^2(w Ts/2)                        (5)

Linear time-varying model (6), its transition matrix holding the measured next sample::

    x(k+1) = A(k) x(k),  y(k+1) = C x(k+1)
    A(k) = [[1, 1, 0,          0],
            [0, 1, s(t_{k+1}), 1],
            [0, 0, 1,          0],
            [0, 0, 0,          1]],   C = [1, 0, 0, 0]

The filter (Section III-C) is the standard Kalman filter on (6) with process noise
covariance ``Q = diag(q)`` and measurement noise variance ``R``; the paper's Section IV
uses Q = 1e-6 I, R = 1e-2 and a zero initial state. The prediction and the update are
written out on the ten distinct entries of the symmetric covariance ``P`` so that the
kernel stays cheap; with the standard-deviation recursion below (U and T in registers,
the noise means in a second pass) it runs at about 0.6x a streaming numpy FFT on the same
blocks (``sinewatch bench kernels --estimators ges-kalman --block 1024``; the bench's note
says why).

Recovery of the parameters from the state estimate x_hat:

* frequency, eq. (21): ``w_hat = 2/Ts * arcsin(sqrt(-x3_hat/4))`` in ]0, pi/Ts[,
  defined while ``-4 < x3_hat < 0`` (20);
* offset, Section III-E: ``B_hat = -x4_hat / x3_hat``;
* amplitude and phase (derived here; the paper leaves them open). With
  ``S = sin(w Ts/2) = sqrt(-x3/4)`` and ``Cw = cos(w Ts/2) = sqrt(1 + x3/4)``::

      A sin(theta_k)          = x1 - B
      A cos(theta_k + w Ts/2) = x2 / (2 S)
      => A cos(theta_k) = (x2/(2 S) + (x1 - B) S) / Cw          (cos(a+b) expansion)
      A_hat = hypot(A sin theta_k, A cos theta_k),  theta_hat_k = atan2(., .)

  ``Cw > 0`` because w Ts < pi (Nyquist, eq. 9-10).

While ``x3_hat`` lies outside (-4, 0) every output is NaN and ``converged`` is False.
``converged`` additionally requires the filter's own standard deviation of x3 to be below
``convergence_rel_std * |x3_hat|``. The residual is the innovation ``y(k+1) - x1_pred``.

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

The reported parameters p = (f, A, theta, B) are the functions of x_hat above (eq. 21,
Section III-E, the amplitude/phase recovery); their covariance follows by the delta method
with J = dp/dx at x_hat (written out in ``_parameter_std``)::

    sd(p_i) = sqrt( (J (T + sigma_hat^2 U) J^T)_ii )                             (U6)

The recursion only reads the filter's quantities (its state is the separate ``unc``
array), so the estimates are bit for bit those of the filter without it.

Calibration (sd of error / reported sd about its mean; one value per trial at the end of
2 s). With the paper's Q = 1e-6 I at 1 kHz (1000 seeded trials: ``pytest -m slow
tests/test_ges_kalman_uncertainty.py``): 0.97 to 1.04 for frequency, amplitude, phase and
offset at 25 and 50.5 Hz, SNR 10 to 40 dB. At the defaults (Q scaled to the sample rate,
:func:`default_q`; R = 1e-2) on 49.5-50.5 Hz tones of amplitude 0.5-2 at 5 kHz, 0 to 60 dB
(``sinewatch bench calibration --estimators ges-kalman --trials 300``): sd 0.96-1.10, |mean|
<= 0.2, but for the frequency's mean at 0 dB (+0.43).

Where it does not hold: U1-U6 are first order in the noise, and the noise on the sample in
A(k) biases x3_hat (errors in variables: a noisy regressor attenuates its coefficient, the
more the longer the filter's memory); so does a memory so short that x3_hat's own noise is
large (the filter is nonlinear in it). The paper's Q unscaled at 5 kHz is the second case
(mean error / sd +5.6 for frequency at 0 dB, +2.5 at 10 dB); R = sigma^2 at 10 dB SNR, 1 kHz,
the first (a -1.9 Hz bias at 50.5 Hz, -3 reported sd). The accuracy bench's tuning (Q scaled
at the scenario's nominal frequency, R = sigma^2 / 100 floored at 1e-3 A^2:
``sinewatch.apps.bench.params``) is calibrated 0.95-1.08 on its tone scenarios from 0 to 60 dB
(``sinewatch bench accuracy --estimators ges-kalman --scenarios snr --trials 30``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from pydantic import Field, field_validator

from sinewatch.estimators import register
from sinewatch.estimators.bank import register_bank
from sinewatch.estimators.base import (
    Estimator,
    EstimatorParams,
    Track,
    TrackStd,
    decode_array,
    encode_array,
    kernel,
    track_from_columns,
    undefined_row,
)

NOISE_MEMORY = 128  # N_sigma, samples: time constant of the noise-variance estimate (U5)
T_NEGLIGIBLE = 1e-100  # trace of T below which T (U3) is set to 0 and no longer propagated
LOG_CHI2_MEAN = -1.2703628454614782  # E[log z^2] for z ~ N(0, 1): psi(1/2) + log 2, (U5a)
ROBUST_CAP = 4.0  # (U5a): <u> at most four times the log-mean's estimate of sigma^2
TINY = 1e-300  # log(0) guard, (U5a)
# _noise_means skips exp when <u> is below the cap's lower bound times this: 1e-12 is ~4,000
# times the bound's worst relative rounding (a few 1e-16) plus exp's (< 1 ulp)
EXP_SCREEN_MARGIN = 1.0 - 1e-12
UNC_SIZE = 35  # T (16), U (16), <u>, the weight w, <log u>


PAPER_Q = 1e-6  # Section IV: Q = 1e-6 I at fs = 1 kHz, 100 Hz (w Ts = 0.2 pi)
PAPER_W_TS = 0.2 * math.pi
LEGACY_DEFAULTS: dict[str, Any] = {"q": PAPER_Q}  # the defaults of recordings made before default_q


def default_q(sample_rate_hz: float, reference_frequency_hz: float) -> list[float]:
    """The default process noise (not in the paper): its Q = 1e-6 I, tuned at w Ts = 0.2 pi,
    carried to another w Ts = 2 pi f_ref / fs. The states scale as x2 ~ A (w Ts) and x3, x4 ~
    (w Ts)^2 (eq. 4, 5 and Section III-A), so a random walk of the same size relative to each
    state is 1e-6 rho^2 for x1, x2 and 1e-6 rho^4 for x3, x4, rho = w Ts / (0.2 pi) = 10 f_ref /
    fs (x1, the measured sample, as x2). The paper's own Q where w Ts = 0.2 pi (500 Hz at 50 Hz). The paper's
    unscaled 1e-6 at 5 kHz lets x3 wander 25 % of its value a sample, so short a memory that
    the errors-in-variables bias and the filter's nonlinearity dominate (frequency RMSE 119 Hz
    at 50 Hz, 0 dB SNR; its error bars out of 0.9-1.1 up to 20 dB); scaled, every parameter
    is calibrated from 0 to 60 dB (``sinewatch bench calibration --estimators ges-kalman``)."""
    rho = (2.0 * math.pi * reference_frequency_hz / sample_rate_hz) / PAPER_W_TS
    return [PAPER_Q * rho**2, PAPER_Q * rho**2, PAPER_Q * rho**4, PAPER_Q * rho**4]


class GesKalmanParams(EstimatorParams):
    q: float | list[float] | None = Field(
        None,
        description="Process noise covariance: one value for Q = q I, or the 4 diagonal entries; null "
        "(default): the paper's Q = 1e-6 I at w Ts = 0.2 pi, scaled to this sample rate at "
        "reference_frequency_hz (1e-6 rho^2 for x1, x2, 1e-6 rho^4 for x3, x4, rho = 10 f_ref / fs)",
    )
    r: float = Field(1e-2, gt=0, description="Measurement noise variance R")
    reference_frequency_hz: float = Field(
        50.0,
        gt=0,
        description="The frequency the default Q is scaled for (mains: 50; 60 gives a 1.44x larger Q "
        "for x1, x2 and 2.07x for x3, x4). Unused when q is given",
    )
    x0: list[float] = Field([0.0, 0.0, 0.0, 0.0], description="Initial state x1..x4")
    p0: float = Field(1.0, gt=0, description="Initial covariance P0 = p0 I")
    convergence_rel_std: float = Field(0.1, gt=0, description="converged once std(x3) < convergence_rel_std * |x3|")

    @field_validator("q")
    @classmethod
    def _q_shape(cls, v: float | list[float] | None) -> float | list[float] | None:
        if v is None:
            return v
        values = [v] if isinstance(v, (int, float)) else v
        if isinstance(v, list) and len(v) != 4:
            raise ValueError(f"expected 1 or 4 values, got {len(v)}")
        if any(not (x >= 0 and math.isfinite(x)) for x in values):
            raise ValueError(f"expected finite values >= 0, got {v}")
        return v

    @field_validator("x0")
    @classmethod
    def _x0_shape(cls, v: list[float]) -> list[float]:
        if len(v) != 4 or not all(math.isfinite(x) for x in v):
            raise ValueError(f"expected 4 finite values, got {v}")
        return v


@kernel(inline="always")
def _filter_step(
    s: float,
    x1: float, x2: float, x3: float, x4: float,
    p00: float, p01: float, p02: float, p03: float, p11: float,
    p12: float, p13: float, p22: float, p23: float, p33: float,
    q0: float, q1: float, q2: float, q3: float, R: float,
) -> tuple[
    float, float, float, float, float, float, float, float, float, float,
    float, float, float, float, float, float, float, float, float,
]:  # fmt: skip
    """One sample ``s = s(t_{k+1})`` of the Kalman filter on (6): the new ``(x1..x4, p00, p01,
    p02, p03, p11, p12, p13, p22, p23, p33)``, then the innovation ``e`` and the gain
    ``k0..k3``. The one definition, called by the single-channel kernel and by the bank."""
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
        e, k0, k1, k2, k3,
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
    return _noise_means_of_log(u, math.log(max(u, TINY)), w, m_u, m_l, lam, x_ref, e_ref)


@kernel(inline="always")
def _noise_means_of_log(
    u: float, log_u: float, w: float, m_u: float, m_l: float, lam: float, x_ref: float, e_ref: float
) -> tuple[float, float, float, float, float]:
    """:func:`_noise_means` with ``log_u = log(max(u, TINY))`` given: a caller may take the
    logs of a block's u in a loop of their own, where the calls overlap."""
    w = lam * w + (1.0 - lam)
    m_u = lam * m_u + (1.0 - lam) * u
    m_l = lam * m_l + (1.0 - lam) * log_u
    x = m_l / w - LOG_CHI2_MEAN
    d1 = 1.0 + (x - x_ref)
    if d1 > 0.5 and m_u <= ROBUST_CAP * w * e_ref * d1 * EXP_SCREEN_MARGIN:  # False on NaN
        return w, m_u, m_l, x_ref, e_ref
    e = math.exp(x)
    m_u = min(m_u, ROBUST_CAP * w * e)  # (U5a)
    return w, m_u, m_l, x, e


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
def _parameter_std(
    x1: float,
    x2: float,
    x3: float,
    x4: float,
    T: np.ndarray,
    U: np.ndarray,
    s2: float,
    Ts: float,
    std: np.ndarray,
    row: int,
) -> None:
    """Row ``row`` of ``std``: sd of (f [Hz], A, theta, B) = sqrt(diag(J Pa J^T)) with
    ``Pa = T + s2 U`` (U1, U6); NaN outside (-4, 0) (eq. 20). J is the Jacobian of the
    recovery formulas of the module docstring at x_hat."""
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
    J = np.zeros((4, 4))
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
    """Row ``j`` of ``out``: the parameters recovered from x_hat (module docstring)."""
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


@kernel
def ges_kalman_kernel(
    y: np.ndarray, state: np.ndarray, unc: np.ndarray, consts: np.ndarray, last_only: bool
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """Run the filter over block ``y`` from ``state`` and ``unc`` and return
    ``(out, sse, std, new_state, new_unc)``.

    ``state`` is the ``xP`` array, ``unc`` the ``unc`` array (layouts:
    :meth:`GesKalman._initial_state`); ``consts`` packs q1..q4, R, Ts,
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
    x_ref, e_ref = 0.0, 0.0  # _noise_means: no exp taken yet
    T = np.empty((4, 4))
    U = np.empty((4, 4))
    # last_only: the u of (U5) per sample, for a second pass that keeps log and exp (calls,
    # which spill every register) out of the filter's loop
    u_seq = np.empty(n if last_only else 0)
    for k in range(n):
        s = y[k]  # s(t_{k+1}) enters A(k), eq. (6)
        x3_prior = x3
        x1, x2, x3, x4, p00, p01, p02, p03, p11, p12, p13, p22, p23, p33, e, k0, k1, k2, k3 = _filter_step(
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
            _parameter_std(x1, x2, x3, x4, T, U, m_u / w if w > 0.0 else R, Ts, std, k)
            _write_estimates(out, k, x1, x2, x3, x4, p22, Ts, rel_std)
    if last_only:  # (U5)-(U5a) over the block's u, in order: the same values as in the loop
        for k in range(n):
            w, m_u, m_l, x_ref, e_ref = _noise_means(u_seq[k], w, m_u, m_l, lam, x_ref, e_ref)
        _store4x4(T, t00, t01, t02, t03, t10, t11, t12, t13, t20, t21, t22, t23, t30, t31, t32, t33)
        _store4x4(U, u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33)
        _parameter_std(x1, x2, x3, x4, T, U, m_u / w if w > 0.0 else R, Ts, std, 0)
        _write_estimates(out, 0, x1, x2, x3, x4, p22, Ts, rel_std)
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
    return out, sse, std, new_state, new_unc


@register
class GesKalman(Estimator[GesKalmanParams], kernel=ges_kalman_kernel, name="ges-kalman"):
    """GES Kalman observer for one biased sinusoid"""

    paper = '"A globally exponentially stable (GES) discrete-time observer for the parameters of a biased sinusoid"'
    example_frequency_hz = 100.0  # the paper's Section IV
    example_params: ClassVar[dict[str, Any]] = {"q": PAPER_Q}  # and its Q, at its own w Ts = 0.2 pi
    # defaults of recordings made before ESTIMATOR_DEFAULTS_VERSION 2 (replay sets them)
    defaults_before: ClassVar[dict[str, Any]] = LEGACY_DEFAULTS
    # Printed by ``sinewatch bench kernels`` under its table. Its ratio and ns/sample: ``sinewatch bench kernels --block 1024 --estimators ges-kalman``
    # (the kernel alone: that ns/sample less the per-block call, ~5-7 us / 1024).
    bench_note: ClassVar[str] = (
        "ges-kalman is below the streaming FFT (about 0.6-0.9x at 1024-sample blocks): besides the "
        "filter on (6) (~50 flops a sample), every sample propagates the actual error's covariance "
        "U (U4), 16 entries at ~9 flops each after M = A U A^T, and updates the noise means "
        "(U5)-(U5a), one log a sample (the exp of the cap only where a bound on it does not already "
        "show that the cap cannot bind). With U and T in registers, the means in a second pass and "
        "the last row written after the loop, each operation in the order that keeps the outputs "
        "bit for bit, the kernel is one dependent chain a sample (a division for the gain, another "
        "for u); the FFT shares its work across a frame instead."
    )
    # Printed by ``sinewatch bench kernels --bank N`` when the bank stays below twice the FFT.
    bank_note: ClassVar[str] = (
        "the bank advances 8 channels as one vector (lane-major state; the filter, T and U in "
        "256-bit AVX registers, LLVM's preferred width here) at ~1.7-2x one channel, and still "
        "takes, per sample of every channel, one log from the C library for the noise means (U5), "
        "scalar per lane (~6.5 ns a call by throughput; a vectorised log would round differently): "
        "about a third of the bank's time (perf). The rest is the filter and U (~255 flops a "
        "sample, two divisions on the chain from one sample to the next, ~45 %) and the means' "
        "recursion lane by lane (~20 %). Twice the 4096-sample FFT is ~16 ns a sample: it would "
        "take a log vectorised with the C library's exact rounding"
    )

    def _setup(self) -> None:
        p = self.params
        q = default_q(self.sample_rate_hz, p.reference_frequency_hz) if p.q is None else p.q
        q = q if isinstance(q, list) else [q] * 4
        self._constants = (np.array([*q, p.r, 1.0 / self.sample_rate_hz, p.convergence_rel_std, float(NOISE_MEMORY)]),)

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``xP`` (20,): the state estimate x1..x4, then the 16 entries of its covariance P
        (row-major). ``unc`` (35,): the actual error covariance's parts T (16, row-major,
        from p0 I) and U (16, from 0), then the exponentially weighted sums <u>, w and
        <log u> (from 0), eq. (U1)-(U5a)."""
        P0 = np.eye(4) * self.params.p0
        return {
            "xP": np.concatenate([np.asarray(self.params.x0, dtype=np.float64), P0.ravel()]),
            "unc": np.concatenate([P0.ravel(), np.zeros(16), np.zeros(3)]),
        }

    def set_state(self, snapshot: Mapping[str, Any]) -> None:
        """As :meth:`Estimator.set_state`; snapshots of earlier builds are accepted: one
        without ``unc`` (only ``xP``) starts ``unc`` afresh (the estimates themselves do not
        depend on it; the reported sd settles within a few N_sigma samples), one whose
        ``unc`` ends in the former (<e^2>, <1 + C U C^T>) pair continues from their ratio."""
        state = snapshot.get("state")
        if isinstance(state, Mapping) and "xP" in state and "unc" not in state:
            fresh = self._initial_state()["unc"]
            snapshot = {**snapshot, "state": {**state, "unc": encode_array(fresh)}}
        elif isinstance(state, Mapping) and "unc" in state:
            unc = decode_array(state["unc"])
            if unc.shape == (UNC_SIZE - 1,):  # (T, U, <e^2>, <1 + C U C^T>)
                s2 = unc[32] / unc[33] if unc[33] > 0 else self.params.r
                tail = [s2, 1.0, math.log(max(s2, TINY)) + LOG_CHI2_MEAN]  # <u>, w = 1, <log u>
                snapshot = {**snapshot, "state": {**state, "unc": encode_array(np.concatenate([unc[:32], tail]))}}
        super().set_state(snapshot)

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out, sse, std = outputs
        track = track_from_columns(out, sse, block.shape[0])
        track.std = TrackStd(frequency_hz=std[:, 0:1], amplitude=std[:, 1:2], phase_rad=std[:, 2:3], offset=std[:, 3])
        return track


# ---- bank: the channels of a frame together (sinewatch.estimators.bank) -------------------
LANES = 8  # channels advanced together: 8 doubles, one AVX-512 register
# rows of the bank's lane-major work array: one row of LANES doubles per per-sample quantity
# x1..x4; the 10 entries of P; T (16); U (16); sse; the sample in; u of (U5) out
_RX, _RP, _RT, _RU, _RSSE, _RS, _RUO = 0, 4, 14, 30, 46, 47, 49  # _RS: two rows, see the bank kernel
_ROWS = 50
_P_IN_XP = (4, 5, 6, 7, 9, 10, 11, 14, 15, 19)  # p00 p01 p02 p03 p11 p12 p13 p22 p23 p33 in ``xP``
_P_OF_ENTRY = (0, 1, 2, 3, 1, 4, 5, 6, 2, 5, 7, 8, 3, 6, 8, 9)  # P[i, j] (row-major) -> its distinct entry


@kernel(inline="always")
def _bank_sample(
    S: np.ndarray, lane: int, rs: int, with_t: bool, q0: float, q1: float, q2: float, q3: float, R: float
) -> None:
    """One sample (row ``rs``) of lane ``lane`` of the work array ``S`` (rows ``_R*``, each
    ``LANES`` wide): the filter (:func:`_filter_step`), T (U3) and U (U4) advanced exactly as
    :func:`ges_kalman_kernel` does (T's branches as selects: the propagation is computed and
    kept or not), the sse summed, u of (U5) into row ``_RUO``. Straight-line arithmetic that
    reads and writes one array at constant offsets only, so the compiler can prove the lanes
    independent and run them as one vector (a second array would need a run-time overlap
    check, which LLVM does not add to a loop of 8 iterations)."""
    L = LANES
    s = S[rs * L + lane]
    x1, x2, x3, x4 = S[(_RX + 0) * L + lane], S[(_RX + 1) * L + lane], S[(_RX + 2) * L + lane], S[(_RX + 3) * L + lane]
    b = _RP * L + lane
    p00, p01, p02, p03, p11 = S[b], S[b + L], S[b + 2 * L], S[b + 3 * L], S[b + 4 * L]
    p12, p13, p22, p23, p33 = S[b + 5 * L], S[b + 6 * L], S[b + 7 * L], S[b + 8 * L], S[b + 9 * L]
    x3_prior = x3
    x1, x2, x3, x4, p00, p01, p02, p03, p11, p12, p13, p22, p23, p33, e, k0, k1, k2, k3 = _filter_step(
        s, x1, x2, x3, x4, p00, p01, p02, p03, p11, p12, p13, p22, p23, p33, q0, q1, q2, q3, R
    )
    S[(_RX + 0) * L + lane], S[(_RX + 1) * L + lane], S[(_RX + 2) * L + lane], S[(_RX + 3) * L + lane] = x1, x2, x3, x4
    S[b], S[b + L], S[b + 2 * L], S[b + 3 * L], S[b + 4 * L] = p00, p01, p02, p03, p11
    S[b + 5 * L], S[b + 6 * L], S[b + 7 * L], S[b + 8 * L], S[b + 9 * L] = p12, p13, p22, p23, p33
    S[_RSSE * L + lane] += e * e
    h1 = k1 + x3_prior  # h = K + g_k (U2)
    if with_t:  # else no lane's T is propagated: the caller applies (U3)'s zeroing
        t = _RT * L + lane
        t00, t01, t02, t03 = S[t], S[t + L], S[t + 2 * L], S[t + 3 * L]
        t10, t11, t12, t13 = S[t + 4 * L], S[t + 5 * L], S[t + 6 * L], S[t + 7 * L]
        t20, t21, t22, t23 = S[t + 8 * L], S[t + 9 * L], S[t + 10 * L], S[t + 11 * L]
        t30, t31, t32, t33 = S[t + 12 * L], S[t + 13 * L], S[t + 14 * L], S[t + 15 * L]
        n00, n01, n02, n03, n10, n11, n12, n13, n20, n21, n22, n23, n30, n31, n32, n33 = _propagate_error(
            t00, t01, t02, t03, t10, t11, t12, t13, t20, t21, t22, t23, t30, t31, t32, t33,
            s, k0, k1, k2, k3, k0, h1, k2, k3, 0.0,
        )  # fmt: skip
        keep = t00 + t11 + t22 + t33 > T_NEGLIGIBLE  # (U3) as in ges_kalman_kernel
        zero = (not keep) and t00 != 0.0
        # T <- propagated if keep, 0 if zero, else as it was (the single kernel's if / elif)
        t00 = n00 if keep else (0.0 if zero else t00)
        t01 = n01 if keep else (0.0 if zero else t01)
        t02 = n02 if keep else (0.0 if zero else t02)
        t03 = n03 if keep else (0.0 if zero else t03)
        t10 = n10 if keep else (0.0 if zero else t10)
        t11 = n11 if keep else (0.0 if zero else t11)
        t12 = n12 if keep else (0.0 if zero else t12)
        t13 = n13 if keep else (0.0 if zero else t13)
        t20 = n20 if keep else (0.0 if zero else t20)
        t21 = n21 if keep else (0.0 if zero else t21)
        t22 = n22 if keep else (0.0 if zero else t22)
        t23 = n23 if keep else (0.0 if zero else t23)
        t30 = n30 if keep else (0.0 if zero else t30)
        t31 = n31 if keep else (0.0 if zero else t31)
        t32 = n32 if keep else (0.0 if zero else t32)
        t33 = n33 if keep else (0.0 if zero else t33)
        S[t], S[t + L], S[t + 2 * L], S[t + 3 * L] = t00, t01, t02, t03
        S[t + 4 * L], S[t + 5 * L], S[t + 6 * L], S[t + 7 * L] = t10, t11, t12, t13
        S[t + 8 * L], S[t + 9 * L], S[t + 10 * L], S[t + 11 * L] = t20, t21, t22, t23
        S[t + 12 * L], S[t + 13 * L], S[t + 14 * L], S[t + 15 * L] = t30, t31, t32, t33
    v = _RU * L + lane
    u00, u01, u02, u03 = S[v], S[v + L], S[v + 2 * L], S[v + 3 * L]
    u10, u11, u12, u13 = S[v + 4 * L], S[v + 5 * L], S[v + 6 * L], S[v + 7 * L]
    u20, u21, u22, u23 = S[v + 8 * L], S[v + 9 * L], S[v + 10 * L], S[v + 11 * L]
    u30, u31, u32, u33 = S[v + 12 * L], S[v + 13 * L], S[v + 14 * L], S[v + 15 * L]
    u = e * e / (1.0 + u00 + 2.0 * u01 + u11)  # (U5), from the predicted U
    u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33 = _propagate_error(
        u00, u01, u02, u03, u10, u11, u12, u13, u20, u21, u22, u23, u30, u31, u32, u33,
        s, k0, k1, k2, k3, k0, h1, k2, k3, 1.0,
    )  # (U4)  # fmt: skip
    S[v], S[v + L], S[v + 2 * L], S[v + 3 * L] = u00, u01, u02, u03
    S[v + 4 * L], S[v + 5 * L], S[v + 6 * L], S[v + 7 * L] = u10, u11, u12, u13
    S[v + 8 * L], S[v + 9 * L], S[v + 10 * L], S[v + 11 * L] = u20, u21, u22, u23
    S[v + 12 * L], S[v + 13 * L], S[v + 14 * L], S[v + 15 * L] = u30, u31, u32, u33
    S[_RUO * L + lane] = u


@kernel(inline="always")
def _bank_t_live(S: np.ndarray) -> bool:
    """Whether some lane of ``S`` propagates its T at the next sample (U3), as
    :func:`ges_kalman_kernel` decides it. Once no lane does, none will again (T then stays
    zero or as it was)."""
    L = LANES
    live = False
    for lane in range(L):
        t = _RT * L + lane
        live |= S[t] + S[t + 5 * L] + S[t + 10 * L] + S[t + 15 * L] > T_NEGLIGIBLE
    return live


@kernel(inline="always")
def _bank_t_zero(S: np.ndarray) -> None:
    """The zeroing of T (U3) in lanes where no lane propagates it: 0 where ``T[0, 0] != 0``."""
    L = LANES
    for lane in range(L):
        if S[_RT * L + lane] != 0.0:
            for i in range(16):
                S[(_RT + i) * L + lane] = 0.0


@kernel(inline="always")
def _bank_row(
    S: np.ndarray, lane: int, s2: float, Ts: float, rel_std: float,
    out: np.ndarray, std: np.ndarray, row: int, T: np.ndarray, U: np.ndarray,
) -> None:  # fmt: skip
    """Row ``row`` of ``out`` and ``std`` (one channel's) from lane ``lane`` of ``S``, as
    :func:`ges_kalman_kernel` writes it."""
    L = LANES
    for i in range(16):
        T[i // 4, i % 4] = S[(_RT + i) * L + lane]
        U[i // 4, i % 4] = S[(_RU + i) * L + lane]
    x1, x2, x3, x4 = S[(_RX + 0) * L + lane], S[(_RX + 1) * L + lane], S[(_RX + 2) * L + lane], S[(_RX + 3) * L + lane]
    _parameter_std(x1, x2, x3, x4, T, U, s2, Ts, std, row)
    _write_estimates(out, row, x1, x2, x3, x4, S[(_RP + 7) * L + lane], Ts, rel_std)


@kernel(inline="always")
def _bank_means_pair(
    us: np.ndarray, logs: np.ndarray, means: np.ndarray, refs: np.ndarray, lam: float, n: int, a: int
) -> None:
    """:func:`_noise_means_of_log` over the block's u of lanes ``a`` and ``a + 1``, each in
    order; the two chains side by side, so that each waits less on its own latency."""
    b = a + 1
    m_ua, w_a, m_la, x_ra, e_ra = means[0, a], means[1, a], means[2, a], refs[0, a], refs[1, a]
    m_ub, w_b, m_lb, x_rb, e_rb = means[0, b], means[1, b], means[2, b], refs[0, b], refs[1, b]
    for k in range(n):
        i = k * LANES + a
        w_a, m_ua, m_la, x_ra, e_ra = _noise_means_of_log(us[i], logs[i], w_a, m_ua, m_la, lam, x_ra, e_ra)
        w_b, m_ub, m_lb, x_rb, e_rb = _noise_means_of_log(us[i + 1], logs[i + 1], w_b, m_ub, m_lb, lam, x_rb, e_rb)
    means[0, a], means[1, a], means[2, a], refs[0, a], refs[1, a] = m_ua, w_a, m_la, x_ra, e_ra
    means[0, b], means[1, b], means[2, b], refs[0, b], refs[1, b] = m_ub, w_b, m_lb, x_rb, e_rb


@kernel(inline="always")
def _bank_means(us: np.ndarray, logs: np.ndarray, means: np.ndarray, refs: np.ndarray, lam: float, n: int) -> None:
    """The noise means (U5)-(U5a) of the block's u, every lane (lanes past the last channel
    run on their zeros harmlessly), two lanes at a time. Not all lanes in one loop: the
    compiler would vectorise it and, taking exp for a pure function, call exp for every lane
    on every sample, which undoes :func:`_noise_means`' skipping of it."""
    for a in range(0, LANES, 2):
        _bank_means_pair(us, logs, means, refs, lam, n, a)


@kernel
def ges_kalman_bank_kernel(
    y: np.ndarray, xP: np.ndarray, unc: np.ndarray, consts: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`ges_kalman_kernel` for C channels at once: ``y`` (N, C), ``xP`` (20, C), ``unc``
    (35, C), one channel per column; returns ``out`` (C, rows, 5), ``sse`` (C,), ``std``
    (C, rows, 4) and the new ``xP`` and ``unc``. Channels go ``LANES`` at a time through a
    lane-major work array (copied in and out once per block): the filter, T and U of the
    ``LANES`` channels advance as one vector (:func:`_bank_sample`, a loop of literal trip
    count over one array), then each channel's noise means (U5)-(U5a) take their log and
    exp lane by lane, the C library's scalar calls that the single kernel makes."""
    n, nc = y.shape
    rows = 1 if last_only else n
    out = np.empty((nc, rows, 5))
    std = np.empty((nc, rows, 4))
    sse = np.empty(nc)
    new_xP = np.empty((20, nc))
    new_unc = np.empty((UNC_SIZE, nc))
    q0, q1, q2, q3 = consts[0], consts[1], consts[2], consts[3]
    R, Ts, rel_std = consts[4], consts[5], consts[6]
    lam = 1.0 - 1.0 / consts[7]  # (U5)
    L = LANES
    S = np.empty(_ROWS * L)
    ys = np.empty(n * L)
    us = np.empty(n * L)
    logs = np.empty(n * L if last_only else 0)
    T = np.empty((4, 4))
    U = np.empty((4, 4))
    for g in range(0, nc, L):
        width = min(L, nc - g)
        S[:] = 0.0  # lanes past the last channel run on zeros, their results dropped
        if width < L:
            ys[:] = 0.0
        for c in range(width):
            for i in range(4):
                S[(_RX + i) * L + c] = xP[i, g + c]
            for i in range(10):
                S[(_RP + i) * L + c] = xP[_P_IN_XP[i], g + c]
            for i in range(32):
                S[(_RT + i) * L + c] = unc[i, g + c]
        for k in range(n):  # row by row: y (N, C) is read in its own order
            for c in range(width):
                ys[k * L + c] = y[k, g + c]
        means = np.zeros((3, L))  # <u>, w, <log u>
        refs = np.zeros((2, L))  # _noise_means' x_ref, e_ref
        for c in range(width):
            means[0, c], means[1, c], means[2, c] = unc[32, g + c], unc[33, g + c], unc[34, g + c]
        for lane in range(L):  # sample 0's row
            S[_RS * L + lane] = ys[lane]
        t_live = True
        for k in range(n):
            # sample k + 1 into the row sample k does not read: written one step before it is
            # read as a vector (read at once, 8 scalar stores would stall its load ~15 cycles)
            nxt = min(k + 1, n - 1) * L
            rs_next = (_RS + 1 - k % 2) * L
            for lane in range(L):
                S[rs_next + lane] = ys[nxt + lane]
            if t_live:  # some lane's T is still propagated (U3): half the arithmetic
                t_live = _bank_t_live(S)
            if not t_live:  # none: the single kernel's zeroing of T, where it applies
                _bank_t_zero(S)
            # rows and the T switch as constants, so the compiler sees the lanes independent
            if k % 2 == 0 and t_live:
                for lane in range(L):  # literal trip count: one vector
                    _bank_sample(S, lane, _RS, True, q0, q1, q2, q3, R)
            elif t_live:
                for lane in range(L):
                    _bank_sample(S, lane, _RS + 1, True, q0, q1, q2, q3, R)
            elif k % 2 == 0:
                for lane in range(L):
                    _bank_sample(S, lane, _RS, False, q0, q1, q2, q3, R)
            else:
                for lane in range(L):
                    _bank_sample(S, lane, _RS + 1, False, q0, q1, q2, q3, R)
            for lane in range(L):
                us[k * L + lane] = S[_RUO * L + lane]
            if not last_only:
                for c in range(width):  # the means and row k, lane by lane (log, exp: scalar)
                    w, m_u, m_l, refs[0, c], refs[1, c] = _noise_means(
                        us[k * L + c], means[1, c], means[0, c], means[2, c], lam, refs[0, c], refs[1, c]
                    )
                    means[0, c], means[1, c], means[2, c] = m_u, w, m_l
                    _bank_row(S, c, m_u / w if w > 0.0 else R, Ts, rel_std, out[g + c], std[g + c], k, T, U)
        if last_only:  # (U5)-(U5a) over the block's u, in order, then the last row
            for i in range(n * L):  # the logs first: independent calls, which overlap
                logs[i] = math.log(max(us[i], TINY))
            _bank_means(us, logs, means, refs, lam, n)
            for c in range(width):
                m_u, w = means[0, c], means[1, c]
                _bank_row(S, c, m_u / w if w > 0.0 else R, Ts, rel_std, out[g + c], std[g + c], 0, T, U)
        for c in range(width):
            ch = g + c
            sse[ch] = S[_RSSE * L + c]
            for i in range(4):
                new_xP[i, ch] = S[(_RX + i) * L + c]
            for i in range(16):  # P's 16 entries (row-major) from its 10 distinct ones
                new_xP[4 + i, ch] = S[(_RP + _P_OF_ENTRY[i]) * L + c]
            for i in range(32):
                new_unc[i, ch] = S[(_RT + i) * L + c]
            new_unc[32, ch], new_unc[33, ch], new_unc[34, ch] = means[0, c], means[1, c], means[2, c]
    return out, sse, std, new_xP, new_unc


register_bank(GesKalman, ges_kalman_bank_kernel, n_outputs=3)
