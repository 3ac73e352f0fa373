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
kernel costs ~10 ns per sample.

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
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field, field_validator

from sinewatch.estimators import register
from sinewatch.estimators.base import Estimator, EstimatorParams, Track, kernel, track_from_columns, undefined_row


class GesKalmanParams(EstimatorParams):
    q: float | list[float] = Field(
        1e-6, description="Process noise covariance: one value for Q = q I, or the 4 diagonal entries"
    )
    r: float = Field(1e-2, gt=0, description="Measurement noise variance R")
    x0: list[float] = Field([0.0, 0.0, 0.0, 0.0], description="Initial state x1..x4")
    p0: float = Field(1.0, gt=0, description="Initial covariance P0 = p0 I")
    convergence_rel_std: float = Field(0.1, gt=0, description="converged once std(x3) < convergence_rel_std * |x3|")

    @field_validator("q")
    @classmethod
    def _q_shape(cls, v: float | list[float]) -> float | list[float]:
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


@kernel
def ges_kalman_kernel(
    y: np.ndarray, state: np.ndarray, consts: np.ndarray, last_only: bool
) -> tuple[np.ndarray, float, np.ndarray]:
    """Run the filter over block ``y`` from ``state`` and return ``(out, sse, new_state)``.

    ``state`` is the ``xP`` array (layout: :meth:`GesKalman._initial_state`); ``consts``
    packs q1..q4, R, Ts and convergence_rel_std. ``out`` has one row per sample (or one row,
    the last sample, when ``last_only``) with columns frequency_hz, amplitude, phase_rad,
    offset, converged (0/1). ``sse`` is the sum of squared innovations. Pure: the
    inputs are not modified.
    """
    x1, x2, x3, x4 = state[0], state[1], state[2], state[3]
    p00, p01, p02, p03 = state[4], state[5], state[6], state[7]
    p11, p12, p13 = state[9], state[10], state[11]
    p22, p23, p33 = state[14], state[15], state[19]
    q0, q1, q2, q3 = consts[0], consts[1], consts[2], consts[3]
    R, Ts, rel_std = consts[4], consts[5], consts[6]
    n = y.shape[0]
    out = np.empty((1 if last_only else n, 5))
    sse = 0.0
    for k in range(n):
        s = y[k]  # s(t_{k+1}) enters A(k), eq. (6)
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
        sse += e * e
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
        p00 = n00 - k0 * n00
        p01 = n01 - k0 * n01
        p02 = n02 - k0 * n02
        p03 = n03 - k0 * n03
        p11 = n11 - k1 * n01
        p12 = n12 - k1 * n02
        p13 = n13 - k1 * n03
        p22 = n22 - k2 * n02
        p23 = n23 - k2 * n03
        p33 = n33 - k3 * n03
        if last_only and k != n - 1:
            continue
        j = 0 if last_only else k
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
    new_state = np.array(
        [x1, x2, x3, x4,
         p00, p01, p02, p03,
         p01, p11, p12, p13,
         p02, p12, p22, p23,
         p03, p13, p23, p33]
    )  # fmt: skip
    return out, sse, new_state


@register
class GesKalman(Estimator[GesKalmanParams], kernel=ges_kalman_kernel, name="ges-kalman"):
    """GES Kalman observer for one biased sinusoid"""

    paper = '"A globally exponentially stable (GES) discrete-time observer for the parameters of a biased sinusoid"'
    example_frequency_hz = 100.0  # the paper's Section IV

    def _setup(self) -> None:
        p = self.params
        q = p.q if isinstance(p.q, list) else [p.q] * 4
        self._constants = (np.array([*q, p.r, 1.0 / self.sample_rate_hz, p.convergence_rel_std]),)

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``xP`` (20,): the state estimate x1..x4, then the 16 entries of its covariance P
        (row-major)."""
        P0 = np.eye(4) * self.params.p0
        return {"xP": np.concatenate([np.asarray(self.params.x0, dtype=np.float64), P0.ravel()])}

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out, sse = outputs
        return track_from_columns(out, sse, block.shape[0])
