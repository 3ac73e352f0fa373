"""``kkl``: nonlinear Luenberger (Kazantzis-Kravaris-Luenberger) observer of a sinusoid.

Paper: L. Praly, L. Marconi, A. Isidori, "A new observer for an unknown harmonic oscillator"
(the year is not recorded here: the copy this was built from does not print it; its most
recent reference is from 2005).

Model (4): the signal is the output of the uncertain oscillator::

    x1' = -x2,   x2' = x3 x1,   x3' = 0,   y = x1                               (4)

so that ``y = A sin(theta)``, ``theta' = omega``, with ``x1 = A sin(theta)``,
``x2 = -A omega cos(theta)``, ``x3 = omega^2``.

Observer (2) with ``F = -diag(lambda_1..lambda_m)``, ``G = (1, .., 1)``: m first-order
filters driven by the measured signal (12)::

    xi_i' = -lambda_i xi_i + y,    i = 1..m,  m >= 4, lambda_i > 0 distinct      (12)

whose state converges to ``T(x)`` with (5)-(6)::

    T_i(x) = (lambda_i x1 + x2) / (lambda_i^2 + x3)                              (6)

and the static left inverse (8)-(9) of T::

    gamma(xi) = Phi(xi)^-1 L(xi)^T F^2 xi                                        (8)
    Phi(xi)   = L(xi)^T L(xi) + mu(xi) I,   L(xi) = (lambda  1  -xi)  (m x 3)
    mu(xi)    = max{ l |xi|^2 - 2 |M xi|^2, 0 }                                 (9)
    l         = inf_{x in O_r, |T(x)| = 1} |M T(x)|^2                            (10)
    O_r       = {x : x1^2 + x2^2 != 0, x3 in [x3_min, x3_max]}                   (11)

i.e. the regularised least-squares solution (15) of ``L(xi) x = F^2 xi`` (13).

What was rebuilt or checked here (the extraction is clean for this paper, but):

* M (printed for m = 4 only) is skew-symmetric and ``|M xi|^2 = det(L(xi)^T L(xi))``
  (checked numerically to 1e-14; it is the Gram determinant of (lambda, 1, xi)). That is
  how the kernel evaluates it, and how it generalises to m > 4:
  ``|M xi|^2 := det(L^T L) = det(C^T C) * |P_perp xi|^2`` with ``C = (lambda 1)`` and
  ``P_perp`` the projector off span(C).
* (10) is printed with ``x in O``; it is O_r of (11). T is linear in (x1, x2) for fixed x3
  (``T = B(x3) (x1, x2)``), so ``l`` is the infimum over x3 in [x3_min, x3_max] of the
  smallest generalised eigenvalue of ``(B^T M^T M B, B^T B)``; it is computed at
  construction on a 2049-point grid of x3 refined by ``scipy.optimize.minimize_scalar``.
* **The printed l = 5 is wrong for mu as printed.** For the paper's lambda = (1, 2, 3, 4)
  and a 3 rad/s signal, (10) gives l = 1.46e-3 at x3 = 9 alone and 4.46e-5 over
  1-9 rad/s (the infimum is at the top of the range), while ``|M T(x)|^2 / |T(x)|^2``
  runs from 1.46e-3 to 1.4 along the 3 rad/s trajectory. With l = 5, mu > 0 on almost
  all of T(O_r) and gamma collapses (x3 comes out in [-0.14, 0.03] instead of 9: no
  frequency, or ~0.2 rad/s; ``tests/test_kkl.py`` shows it with :func:`gamma_reference`).
  With l from (10), mu = 0 on T(O_r) (the factor 2 in (9) is a margin) and gamma is the
  exact inverse, as Section IV proves. Section V is then reproduced to within 1-2 % on
  the standard deviations (docs/estimators/kkl.md).
* Amplitude, frequency and phase from x = gamma(xi): ``omega = sqrt(x3)``,
  ``A = sqrt(x1^2 + x2^2 / x3)`` (Section III). The printed phase
  ``Phi = arctan(sqrt(x30) x10 / x20)`` loses the quadrant and has the wrong sign for
  y = A sin(omega t + Phi) with x1' = -x2; here, from ``x1 = A sin(theta)`` and
  ``x2 = -A omega cos(theta)``: ``theta = atan2(x1 sqrt(x3), -x2)``, the instantaneous
  phase at each sample.

Design choices (not in the paper):

* The user gives a frequency range [f_min, f_max] in Hz; x3 ranges over
  [(2 pi f_min)^2, (2 pi f_max)^2] and ``lambda_i = lambda_factor_i * omega_ref`` with
  ``omega_ref = 2 pi sqrt(f_min f_max)``. The default factors (1/3, 2/3, 1, 4/3) are the
  paper's lambda = (1, 2, 3, 4) rad/s for its 3 rad/s signal. gamma is evaluated in time
  units of 1/omega_ref (``lambda~ = lambda/omega_ref``, ``x3~ = x3/omega_ref^2``, and l
  in those units), so the same design serves 3 rad/s and 50 Hz.
* gamma is evaluated on ``xi / |xi|`` and the amplitude rescaled by |xi|. Where mu = 0
  (on and near T(O_r)) this is exactly (8), because (13) is homogeneous: T(a x1, a x2, x3)
  = a T(x). Off it, the regularisation no longer depends on the signal's units, and the
  3 x 3 system stays well conditioned for any amplitude.
* Sampled input: each filter (12) is discretised exactly for an input that is linear
  between samples (first-order hold, "connect the dots")::

      xi_i(k+1) = a_i xi_i(k) + b0_i y(k) + b1_i y(k+1),   a_i = exp(-lambda_i Ts)
      b1_i = (lambda_i Ts - 1 + a_i) / (lambda_i^2 Ts),  b0_i = (1 - a_i)/lambda_i - b1_i

  The interpolated signal carries the tone at frequency w scaled by
  ``sinc^2(w Ts/2)`` (the triangle kernel's spectrum) with zero phase, and images that
  the filters reduce to O((w Ts)^3). A common scale on xi leaves x3 and theta unchanged,
  so only the amplitude is corrected: ``A = A_gamma / sinc^2(w_hat Ts / 2)``.
  A frequency estimate at or above Nyquist is treated as undefined.

Outputs and flags, per sample:

* Undefined (every output NaN, converged False): |xi| below ``1e-150`` or below
  ``silence_ratio`` times its recent peak (a peak envelope decaying at lambda_min/10,
  so a signal that stops is flagged at most ~8 filter time constants later; in practice
  x3 <= 0 comes first), x3 <= 0, or omega at/above Nyquist. The state stays finite (xi
  entries below 1e-250 are flushed to 0, so a long silence costs no denormal arithmetic).
* converged: the last ``settle_time_constants / lambda_min`` seconds (n_settle samples)
  were all "good", and so is this one. Good = defined, mu(xi) = 0 (xi lies where gamma
  is the exact inverse), the relative least-squares residual ``|L x - F^2 xi| / |F^2 xi|``
  (zero on T(O)) at most ``max_fit_residual``, the running RMS of the one-step prediction
  error (time constant 1/lambda_min) at most ``max_prediction_error`` times the running
  RMS of y, no jump of the prediction error (its mean square over 1/omega_ref above 9
  times its level over 10/lambda_min plus (2 % of the RMS of y)^2), and the frequency
  inside [f_min / 1.25, 1.25 f_max] (the paper's guarantee covers O_r only; the inverse
  stays exact beyond while mu = 0, e.g. 80 Hz on a 45-65 Hz design, but a DC input reads
  as omega -> 0 and must not pass). So converged falls on any anomaly and comes back only
  after a full settle time. It is a consistency check, not a guarantee: gamma is static
  and follows its input, so the one-step prediction error stays small while the estimate
  slides (a 50 Hz input cut to zero at 5 kHz: the estimate is at 35 Hz 3 ms later with a
  relative prediction error of only 0.2); the jump detector is what catches that (the
  flag falls within 2 samples there), and the absolute bounds catch slow drifts.
* offset: 0 (the model has none) whenever the estimate is defined. The biased variant
  ``kkl-biased`` (:mod:`sinewatch.estimators.kkl_biased`) estimates it.
* residual: ``y(k+1) - A sin(theta_k + w Ts)`` (one-step prediction from the previous
  sample's estimate; the prediction is 0 while it is undefined).
* extras: ``manifold_margin`` = ``2 |M xi|^2 / (l |xi|^2)`` (>= 1 iff mu = 0, >= 2 on
  T(O_r)), ``fit_residual`` (the relative residual above) and ``prediction_error`` (the
  running relative RMS above).
* Cost (through ``update``, one core, 1024-sample blocks): ~60 ns/sample with
  ``last_only``, ~80 ns/sample for the full per-sample track (ges-kalman: 16 / 58 in the
  same run).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, TypeVar

import numpy as np
from pydantic import Field, field_validator, model_validator

from sinewatch.estimators import register
from sinewatch.estimators.bank import column_tracks, register_bank
from sinewatch.estimators.base import Estimator, EstimatorParams, Track, track_from_columns
from sinewatch.estimators.kkl_kernels import kkl_bank_kernel, kkl_kernel
from sinewatch.schemas.errors import ParameterError

#: The paper's lambda = (1, 2, 3, 4) rad/s for its 3 rad/s signal (Section V), as multiples
#: of the reference angular frequency.
PAPER_LAMBDA_FACTORS = (1.0 / 3.0, 2.0 / 3.0, 1.0, 4.0 / 3.0)

ENV_SLOWDOWN = 10.0  # the peak envelope decays at lambda_min / ENV_SLOWDOWN
CONVERGED_RANGE_FACTOR = 1.25  # converged needs f in [f_min / 1.25, 1.25 f_max]


# ---- design helpers (Python, run once at construction) ------------------------------------


def validate_lambda_factors(v: list[float], m_min: int) -> list[float]:
    """m >= m_min finite positive, mutually distinct factors (relative gap > 1e-6)."""
    if len(v) < m_min:
        raise ValueError(f"expected at least {m_min} filters (m >= {m_min}), got {len(v)}")
    if not all(math.isfinite(x) and x > 0 for x in v):
        raise ValueError(f"expected finite values > 0, got {v}")
    s = sorted(v)
    gaps = [b - a for a, b in itertools.pairwise(s)]
    if min(gaps) <= 1e-6 * s[-1]:
        raise ValueError(f"expected mutually distinct values (relative gap > 1e-6), got {v}")
    return v


def foh_coefficients(lam: np.ndarray, ts: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact discretisation of xi' = -lam xi + u for u linear between samples.

    Returns (a, b0, b1) with xi(k+1) = a xi(k) + b0 u(k) + b1 u(k+1). For small lam Ts the
    closed forms cancel, so a series is used there."""
    x = lam * ts
    a = np.exp(-x)
    g0 = -np.expm1(-x) / lam  # integral of exp(-lam (Ts - tau)) over [0, Ts]
    # b1 = Ts * (x - 1 + e^-x) / x^2 ; series (1/2 - x/6 + x^2/24 - x^3/120 + x^4/720) below 1e-2
    small = x < 1e-2
    xs = np.where(small, 1.0, x)
    closed = (x + np.expm1(-x)) / (xs * xs)
    series = 0.5 - x / 6.0 + x**2 / 24.0 - x**3 / 120.0 + x**4 / 720.0
    b1 = ts * np.where(small, series, closed)
    b0 = g0 - b1
    return a, b0, b1


def gram_weight(columns: np.ndarray) -> np.ndarray:
    """Q with ``v^T Q v = det([C v]^T [C v])`` for C = columns (m x p): det(C^T C) P_perp."""
    c = np.asarray(columns, dtype=np.float64)
    g = c.T @ c
    p_perp = np.eye(c.shape[0]) - c @ np.linalg.solve(g, c.T)
    q: np.ndarray = np.linalg.det(g) * p_perp
    return q


def min_generalised_ratio(b: np.ndarray, q: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Batched ``min_v (v^T B^T Q B v) / (v^T B^T N B v)`` for B of shape (..., m, 2)."""
    a = np.swapaxes(b, -1, -2) @ q @ b
    c = np.swapaxes(b, -1, -2) @ n @ b
    # det(A - t C) = 0: (c00 c11 - c01^2) t^2 - (a00 c11 + a11 c00 - 2 a01 c01) t + det A = 0
    qa = c[..., 0, 0] * c[..., 1, 1] - c[..., 0, 1] ** 2
    qb = a[..., 0, 0] * c[..., 1, 1] + a[..., 1, 1] * c[..., 0, 0] - 2.0 * a[..., 0, 1] * c[..., 0, 1]
    qc = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] ** 2
    disc = np.sqrt(np.maximum(qb * qb - 4.0 * qa * qc, 0.0))
    # smaller root, in the form that does not cancel: 2 qc / (qb + disc)
    ratio: np.ndarray = 2.0 * qc / (qb + disc)
    return ratio


def ell_eq10(
    basis: np.ndarray,
    image_columns: Callable[[np.ndarray], np.ndarray],
    x3_lo: float,
    x3_hi: float,
    norm_weight: np.ndarray | None = None,
    n_grid: int = 2049,
) -> tuple[float, float]:
    """The constant l of (10): ``inf over x3 in [x3_lo, x3_hi] and (x1, x2) of
    det([basis, v]^T [basis, v]) / |v|_N^2`` with ``v = image_columns(x3) @ (x1, x2)``.

    Returns (l, the x3 where the infimum is reached). A 2049-point log grid, then
    ``scipy.optimize.minimize_scalar`` (bounded) on the cells around the grid minimum."""
    m = basis.shape[0]
    q = gram_weight(basis)
    nw = np.eye(m) if norm_weight is None else norm_weight

    def ratio(x3s: np.ndarray) -> np.ndarray:
        return min_generalised_ratio(image_columns(np.asarray(x3s, dtype=np.float64)), q, nw)

    grid = np.geomspace(x3_lo, x3_hi, n_grid)
    vals = ratio(grid)
    i = int(np.argmin(vals))
    best, best_x3 = float(vals[i]), float(grid[i])
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, n_grid - 1)]
    if hi > lo:
        from scipy.optimize import minimize_scalar  # imported here: 0.3 s, construction only

        res = minimize_scalar(
            lambda u: float(ratio(np.array([math.exp(u)]))[0]),
            bounds=(math.log(lo), math.log(hi)),
            method="bounded",
            options={"xatol": 1e-10},
        )
        if res.success and float(res.fun) < best:
            best, best_x3 = float(res.fun), math.exp(float(res.x))
    return best, best_x3


def kkl_image_columns(lam: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """x3 -> B(x3) (..., m, 2) with T(x) = B(x3) (x1, x2), eq. (6)."""

    def cols(x3: np.ndarray) -> np.ndarray:
        d = lam[None, :] ** 2 + x3[:, None]
        return np.stack([lam[None, :] / d, 1.0 / d], axis=-1)

    return cols


def kkl_ell(lam: np.ndarray, x3_lo: float, x3_hi: float) -> tuple[float, float]:
    """l of (10) for filters ``lam`` and x3 in [x3_lo, x3_hi] (same time unit)."""
    basis = np.column_stack([lam, np.ones_like(lam)])
    return ell_eq10(basis, kkl_image_columns(lam), x3_lo, x3_hi)


def paper_m_matrix(lam: np.ndarray) -> np.ndarray:
    """M of (9) exactly as printed (m = 4)."""
    l1, l2, l3, l4 = (float(v) for v in lam)
    return np.array(
        [
            [0.0, l3 - l4, l4 - l2, l2 - l3],
            [l4 - l3, 0.0, l1 - l4, l3 - l1],
            [l2 - l4, l4 - l1, 0.0, l1 - l2],
            [l3 - l2, l1 - l3, l2 - l1, 0.0],
        ]
    )


def gamma_reference(xi: np.ndarray, lam: np.ndarray, ell: float) -> np.ndarray:
    """gamma(xi) of (8)-(9) literally (numpy, one xi, any units): the 3-vector x_hat.

    For m = 4 it uses the printed M; for m > 4 ``|M xi|^2 = det(L^T L)``. Reference for
    tests and docs; the kernel evaluates the same map on xi/|xi| (see module docstring)."""
    xi = np.asarray(xi, dtype=np.float64)
    lam = np.asarray(lam, dtype=np.float64)
    if not np.any(xi):
        return np.zeros(3)  # gamma_0
    L = np.column_stack([lam, np.ones_like(lam), -xi])
    if lam.size == 4:
        m_xi2 = float(np.sum((paper_m_matrix(lam) @ xi) ** 2))
    else:
        m_xi2 = float(np.linalg.det(L.T @ L))
    mu = max(ell * float(xi @ xi) - 2.0 * m_xi2, 0.0)  # (9)
    phi = L.T @ L + mu * np.eye(3)  # Phi(xi)
    return np.linalg.solve(phi, L.T @ (lam**2 * xi))  # (8): Phi^-1 L^T F^2 xi


def parameters_from_x(x: np.ndarray) -> tuple[float, float, float]:
    """(amplitude, omega, theta) from x = (x1, x2, x3) of (4): A sin(theta) = x1,
    A omega cos(theta) = -x2. NaNs while x3 <= 0."""
    x1, x2, x3 = (float(v) for v in x)
    if not x3 > 0.0:
        return math.nan, math.nan, math.nan
    w = math.sqrt(x3)
    return math.sqrt(x1 * x1 + x2 * x2 / x3), w, math.atan2(x1 * w, -x2)


# ---- parameters ---------------------------------------------------------------------------


def lambda_factors_field(default: tuple[float, ...], description: str) -> Any:
    """The ``lambda_factors`` field: ``default`` and what the description adds after the
    definition of the factors."""
    return Field(
        list(default),
        description=f"Filter poles lambda_i as multiples of omega_ref = 2 pi sqrt(f_min f_max); {description}",
    )


def silence_ratio_field(what: str) -> Any:
    """The ``silence_ratio`` field; ``what`` is the quantity that counts as zero."""
    return Field(1e-3, gt=0, lt=1, description=f"{what} counts as zero below this fraction of its recent peak")


def max_fit_residual_field(residual: str) -> Any:
    """The ``max_fit_residual`` field; ``residual`` is the relative residual of the inverse map."""
    return Field(0.05, gt=0, description=f"converged only while {residual} is at most this")


def max_prediction_error_field(level: str) -> Any:
    """The ``max_prediction_error`` field; ``level`` is the running level of y it compares with."""
    return Field(
        0.3,
        gt=0,
        description="converged only while the running RMS of the one-step prediction error "
        f"is at most this fraction of the running {level} of y",
    )


class KklParams(EstimatorParams):
    #: the least number of filters m (``kkl-biased`` overrides it: one more unknown)
    min_filters: ClassVar[int] = 4

    f_min_hz: float = Field(45.0, gt=0, description="Lower end of the frequency range (Hz), eq. (11)")
    f_max_hz: float = Field(65.0, gt=0, description="Upper end of the frequency range (Hz), eq. (11)")
    lambda_factors: list[float] = lambda_factors_field(
        PAPER_LAMBDA_FACTORS, "m >= 4, distinct, > 0. Default: the paper's (1, 2, 3, 4) rad/s for 3 rad/s"
    )
    settle_time_constants: float = Field(
        6.0, gt=0, description="converged only after this many 1/lambda_min of consecutive good samples"
    )
    silence_ratio: float = silence_ratio_field("xi")
    max_fit_residual: float = max_fit_residual_field("|L x - F^2 xi| / |F^2 xi|")
    max_prediction_error: float = max_prediction_error_field("RMS")

    @field_validator("f_min_hz", "f_max_hz", "settle_time_constants", "max_fit_residual", "max_prediction_error")
    @classmethod
    def _finite(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError(f"expected a finite value, got {v}")
        return v

    @field_validator("lambda_factors")
    @classmethod
    def _factors(cls, v: list[float]) -> list[float]:
        return validate_lambda_factors(v, cls.min_filters)

    @model_validator(mode="after")
    def _range(self) -> KklParams:
        if not self.f_min_hz < self.f_max_hz:
            raise ValueError(f"expected f_min_hz < f_max_hz, got f_min_hz={self.f_min_hz}, f_max_hz={self.f_max_hz}")
        return self


_KP = TypeVar("_KP", bound=KklParams)


def check_nyquist(name: str, f_max_hz: float, sample_rate_hz: float) -> None:
    nyq = 0.5 * sample_rate_hz
    if not f_max_hz < nyq:
        raise ParameterError(
            f"{name}: f_max_hz: expected < Nyquist = {nyq:g} Hz (sample rate {sample_rate_hz:g} Hz), got {f_max_hz:g}"
        )


# ---- design shared with kkl-biased (Python, run once at construction) ---------------------


def reference_scaling(p: KklParams) -> tuple[float, np.ndarray, np.ndarray, float, float]:
    """``(omega_ref, lambda~, lambda, x3~_lo, x3~_hi)``: omega_ref = 2 pi sqrt(f_min f_max),
    the filter poles in units of omega_ref and in rad/s, and the x3 range of (11) in units
    of omega_ref^2 (module docstring, design choices)."""
    f_ref = math.sqrt(p.f_min_hz * p.f_max_hz)
    omega_ref = 2.0 * math.pi * f_ref
    lam_n = np.asarray(p.lambda_factors, dtype=np.float64)
    return omega_ref, lam_n, lam_n * omega_ref, (p.f_min_hz / f_ref) ** 2, (p.f_max_hz / f_ref) ** 2


def observer_consts(p: KklParams, ts: float, omega_ref: float, ell: float, lam_min: float) -> np.ndarray:
    """The ``consts`` array of :func:`kkl_kernel` (and of the ``kkl-biased`` kernel, which
    packs the same 13 constants): Ts, omega_ref, l, silence_ratio, env_decay, n_settle,
    max_fit_residual, max_prediction_error, avg_gain, the omega Ts bounds of the converged
    range and the jump detector's gains. ``lam_min`` in rad/s."""
    n_settle = math.ceil(p.settle_time_constants / (lam_min * ts))
    return np.array(
        [
            ts,
            omega_ref,
            ell,
            p.silence_ratio,
            math.exp(-lam_min * ts / ENV_SLOWDOWN),  # env_decay
            float(n_settle),
            p.max_fit_residual,
            p.max_prediction_error,
            -math.expm1(-lam_min * ts),  # avg_gain: running means over ~1/lambda_min
            2.0 * math.pi * p.f_min_hz * ts / CONVERGED_RANGE_FACTOR,
            2.0 * math.pi * p.f_max_hz * ts * CONVERGED_RANGE_FACTOR,
            -math.expm1(-omega_ref * ts),  # fast mean: time constant 1/omega_ref
            -math.expm1(-lam_min * ts / ENV_SLOWDOWN),  # slow mean: 10/lambda_min
        ]
    )


#: the kernels' ``extras`` columns, in order (module docstring, "extras")
EXTRA_NAMES = ("manifold_margin", "fit_residual", "prediction_error")


def observer_track(outputs: tuple[Any, ...], block: np.ndarray) -> Track:
    """The Track of a kernel's outputs ``(out, extras, sse)`` over ``block``."""
    out, ext, sse = outputs
    e = ext.T  # e[i] is the column ext[:, i], one index operation
    return track_from_columns(
        out, sse, block.shape[0], {EXTRA_NAMES[0]: e[0], EXTRA_NAMES[1]: e[1], EXTRA_NAMES[2]: e[2]}
    )


def observer_bank_tracks(_first: Any, outputs: tuple[Any, ...], block: np.ndarray) -> Sequence[Track]:
    """:func:`observer_track` of every channel of a bank (outputs channel first, ``block`` (N, C))."""
    out, ext, sse = outputs
    extras = {EXTRA_NAMES[0]: ext[:, :, 0], EXTRA_NAMES[1]: ext[:, :, 1], EXTRA_NAMES[2]: ext[:, :, 2]}
    return column_tracks(out, sse, block.shape[0], extras)


# ---- estimator ----------------------------------------------------------------------------


class FilterBankObserver(Estimator[_KP]):
    """What ``kkl`` and ``kkl-biased`` share: the design from the frequency range (module
    docstring, design choices), the Nyquist check, the example and the Track. A subclass
    gives the constant l of its inverse map (:meth:`_ell`) and the kernel."""

    #: what the constant l is called in the error for a degenerate design
    ell_label: ClassVar[str] = "l of (10)"
    example_sample_rate_hz = 5000.0
    example_params: ClassVar[dict[str, Any]] = {"f_min_hz": 45.0, "f_max_hz": 65.0}

    def _ell(self, x3_lo: float, x3_hi: float) -> tuple[float, float]:
        """(l, the x3 where its infimum is reached) for filters ``self.lam_n`` and x3 in
        [x3_lo, x3_hi], in units of omega_ref."""
        raise NotImplementedError

    def _check_params(self) -> None:
        check_nyquist(self.name, self.params.f_max_hz, self.sample_rate_hz)

    def _setup(self) -> None:
        ts = 1.0 / self.sample_rate_hz
        # lambda~ (units of omega_ref), lambda (rad/s), x3~ range of (11)
        self.omega_ref, self.lam_n, self.lambdas, x3_lo, x3_hi = reference_scaling(self.params)
        self.ell, self.ell_x3 = self._ell(x3_lo, x3_hi)  # (10), units of omega_ref^2
        if not (self.ell > 0.0 and math.isfinite(self.ell)):
            raise ParameterError(f"{self.name}: {self.ell_label}: expected > 0, got {self.ell} (degenerate design)")
        self._fa, self._fb0, self._fb1 = foh_coefficients(self.lambdas, ts)
        self._consts = observer_consts(self.params, ts, self.omega_ref, self.ell, float(self.lambdas.min()))

    @property
    def memory_samples(self) -> int:
        """``settle_time_constants / lambda_min`` seconds (n_settle samples): the run of good
        samples converged needs, the filters' slowest memory."""
        return int(self._consts[5])

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        return observer_track(outputs, block)


@register
class Kkl(FilterBankObserver[KklParams], kernel=kkl_kernel, name="kkl"):
    """KKL / nonlinear Luenberger observer of one sinusoid without offset: m >= 4 first-order filters and the static inverse map gamma (Praly, Marconi, Isidori)"""

    paper = 'L. Praly, L. Marconi, A. Isidori, "A new observer for an unknown harmonic oscillator"'
    # Printed by ``sinewatch bench kernels`` under its table. Its ratio and ns/sample: ``sinewatch bench kernels --block 1024 --estimators kkl``
    # (the kernel alone: that ns/sample less the per-block call, ~5-7 us / 1024).
    bench_note: ClassVar[str] = (
        "kkl is below the streaming FFT (about 0.5x at 1024-sample blocks): every sample runs "
        "the m = 4 filters (12) and then the static inverse map (8)-(9) afresh: six weighted sums "
        "over the filters, the Gram determinant, a regularised 3 x 3 solve by its adjugate, "
        "three square roots, four divisions, a sine (the first-order hold's correction and the "
        "prediction) and the fit residual over the filters, about 200 flops in a dependency "
        "chain of ~250 cycles; with the rows written after the loop the kernel takes ~60 ns/sample."
    )
    # Printed by ``sinewatch bench kernels --bank N`` when the bank stays below twice the FFT.
    bank_note: ClassVar[str] = (
        "the bank advances 8 channels as one 512-bit vector (lane-major state, the m filters "
        "unrolled; the filters, the inverse map (8)-(9), the sine of the first-order hold's "
        "correction by sinewatch.estimators.detmath.sin, plain arithmetic that the single kernel uses "
        "too, the read-out and the fit residual in loops over the lanes that LLVM vectorises 8 "
        "doubles wide: zmm in its assembly, no library call) at ~4-4.6x one channel, and is bound by "
        "that arithmetic itself: per sample and channel ~200 flops and the sine's ~40, three square "
        "roots and four divisions (vsqrtpd and vdivpd, long-latency and not fully pipelined). 512-bit "
        "lanes against 256-bit ones, measured in turn under load 13-23: 1.48x and 1.35x the streaming "
        "FFT. On a 2-core AMD EPYC VM (AVX2), with the lanes' flags as selects and no masked store left "
        "in its sample loop, the kernel alone runs at 2.0-2.1x the streaming FFT (22.0-22.5 ns a "
        "channel-sample) and update_bank at 1.80-1.96x (24.2-25.3 ns: `sinewatch bench kernels --block "
        "1024 --bank 8`, paired rounds, load 4-16): at the bar's edge, the Python around the call 2-3 "
        "ns. Twice the FFT in every run would need fewer divisions and square roots a sample, not "
        "wider vectors"
    )

    @classmethod
    def example_signal(cls, n: int, seed: int = 0) -> np.ndarray:
        """The paper's model has no offset: a 50 Hz sine of amplitude 1 plus 1 % noise."""
        rng = np.random.default_rng(seed)
        t = np.arange(n) / cls.example_sample_rate_hz
        return np.sin(2 * np.pi * cls.example_frequency_hz * t + 0.3) + 0.01 * rng.standard_normal(n)

    def _ell(self, x3_lo: float, x3_hi: float) -> tuple[float, float]:
        return kkl_ell(self.lam_n, x3_lo, x3_hi)

    def _setup(self) -> None:
        super()._setup()
        self._constants = (self.lam_n, self._fa, self._fb0, self._fb1, self._consts)

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``xi_state`` (m + 10,): the filter states xi_1..xi_m of (12), then y_prev,
        have_prev, y_pred, pred_valid, n_good, env, e2_avg, y2_avg, e2_fast, e2_slow."""
        return {"xi_state": np.zeros(self.lam_n.size + 10)}


register_bank(Kkl, kkl_bank_kernel, n_outputs=3, tracks=observer_bank_tracks)
