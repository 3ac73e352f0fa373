"""``kkl-biased``: the KKL observer of Praly et al. extended to a sinusoid with a constant offset.

Paper: L. Praly, L. Marconi, A. Isidori, "A new observer for an unknown harmonic
oscillator" (as :mod:`sinewatch.estimators.kkl`). The paper's
signal has no offset; this module is an **extension** built the same way (its Sections
III-IV), not something the paper shows. :mod:`sinewatch.estimators.kkl` holds the
unbiased observer and the design helpers used here.

Model: the oscillator (4) augmented with a constant state x4 (the offset)::

    x1' = -x2,  x2' = x3 x1,  x3' = 0,  x4' = 0,   y = x1 + x4

Filters as in (12), m >= 5 (one more unknown than in the paper, so one more filter)::

    xi_i' = -lambda_i xi_i + y

Their steady state (the analogue of (6), same derivation as Section IV)::

    T_i(x) = (lambda_i x1 + x2) / (lambda_i^2 + x3) + x4 / lambda_i

Inverse. With ``eta_i = lambda_i xi_i``, T reads
``eta_i (lambda_i^2 + x3) = lambda_i^2 (x1 + x4) + lambda_i x2 + x3 x4``, which the
bilinear term x3 x4 makes nonlinear; splitting ``eta = eta_bar 1 + eta_c`` (mean and
centred part) gives the linear system, analogue of (13)::

    L_c(eta_c) z = F^2 eta_c,   L_c = (lambda^2  lambda  1  -eta_c)   (m x 4)
    z = (x1 + x4 - eta_bar,  x2,  x3 (x4 - eta_bar),  x3)

from which ``x3 = z4``, ``x4 = eta_bar + z3 / z4``, ``x1 = z1 - z3 / z4``, ``x2 = z2``.
As in (8)-(9) it is solved in the regularised least-squares sense::

    gamma_b(eta) = (L_c^T L_c + mu_b I)^-1 L_c^T F^2 eta_c
    mu_b = max{ l_b |eta_c|^2 - 2 det(L_c^T L_c), 0 }
    l_b  = inf_{x in O_r, x1^2 + x2^2 != 0} det(L_c^T L_c) / |eta_c|^2  at eta = T(x)

``det(L_c^T L_c)`` (the Gram determinant, the analogue of |M xi|^2) and ``|eta_c|`` do not
depend on the offset x4 (it only adds a multiple of 1 to eta), so l_b > 0 and mu_b = 0
on T(O_r) for any offset. l_b is computed at construction like l of (10).

Everything else (frequency range in Hz and lambdas scaled with it, evaluation on the
unit vector eta_c/|eta_c| in time units of 1/omega_ref, exact first-order-hold
discretisation of the filters with the sinc^2 amplitude correction, the converged rule,
the residual and the extras) is as in :mod:`sinewatch.estimators.kkl`. The FOH keeps a
constant exactly (sinc(0) = 1), so the offset needs no correction. Differences:

* "zero" is judged on the centred part eta_c (no oscillation): below 1e-150, below
  1e-9 |eta_bar| (rounding of a constant input), or below ``silence_ratio`` of its
  recent peak. Then frequency, amplitude and phase are NaN and converged is False; the
  offset is still reported as eta_bar (exact for a constant input) once the filters
  have run for the settle time, NaN before.
* The relative prediction error compares with the running variance of y (not its mean
  square).
* Default lambda factors (1/3, 2/3, 1, 4/3, 5/3): the paper's (1, 2, 3, 4) plus one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import ClassVar

import numpy as np

from sinewatch.estimators import register
from sinewatch.estimators.base import kernel
from sinewatch.estimators.kkl import (
    PAPER_LAMBDA_FACTORS,
    FilterBankObserver,
    KklParams,
    ell_eq10,
    lambda_factors_field,
    max_fit_residual_field,
    max_prediction_error_field,
    silence_ratio_field,
)
from sinewatch.estimators.kkl_kernels import (
    ABS_FLOOR,
    consistent,
    half_step,
    jump_detector,
    next_sample,
    observer_constants,
    observer_head,
    packed_state,
    prediction_error,
    record_sample,
    undefined_sample,
    write_rows,
)

BIASED_LAMBDA_FACTORS = (*PAPER_LAMBDA_FACTORS, 5.0 / 3.0)
DC_FLOOR = 1e-9  # |eta_c| below 1e-9 |eta_bar| is rounding of a constant input, not an oscillation


def biased_image_columns(lam: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """x3 -> B(x3) with eta - x4 1 = B(x3) (x1, x2) (lambda in units of omega_ref)."""

    def cols(x3: np.ndarray) -> np.ndarray:
        d = lam[None, :] ** 2 + x3[:, None]
        return np.stack([lam[None, :] ** 2 / d, lam[None, :] / d], axis=-1)

    return cols


def biased_ell(lam: np.ndarray, x3_lo: float, x3_hi: float) -> tuple[float, float]:
    """l_b for filters ``lam`` and x3 in [x3_lo, x3_hi] (same time unit)."""
    m = lam.size
    basis = np.column_stack([lam**2, lam, np.ones(m)])
    centre = np.eye(m) - np.full((m, m), 1.0 / m)  # |eta_c|^2 = eta^T centre eta
    return ell_eq10(basis, biased_image_columns(lam), x3_lo, x3_hi, norm_weight=centre)


def gamma_biased_reference(xi: np.ndarray, lam: np.ndarray, ell_b: float) -> np.ndarray:
    """gamma_b literally (numpy, one xi, lambda and xi in one time unit): (x1, x2, x3, x4)."""
    eta = np.asarray(lam, dtype=np.float64) * np.asarray(xi, dtype=np.float64)
    eta_bar = float(eta.mean())
    eta_c = eta - eta_bar
    lc = np.column_stack([lam**2, lam, np.ones_like(lam), -eta_c])
    g = lc.T @ lc
    mu = max(ell_b * float(eta_c @ eta_c) - 2.0 * float(np.linalg.det(g)), 0.0)
    z = np.linalg.solve(g + mu * np.eye(4), lc.T @ (lam**2 * eta_c))
    x4 = eta_bar + z[2] / z[3]
    return np.array([z[0] - z[2] / z[3], z[1], z[3], x4])


class KklBiasedParams(KklParams):
    # The parameters of ``kkl`` (same names, defaults and checks) with one more filter:
    # m >= 5 and the default lambda factors BIASED_LAMBDA_FACTORS. The other fields are
    # redeclared only where they act on eta_c and the variance of y instead of xi and y.
    # (A comment, not a docstring: a docstring would become the JSON Schema's description.)

    min_filters: ClassVar[int] = 5

    lambda_factors: list[float] = lambda_factors_field(BIASED_LAMBDA_FACTORS, "m >= 5, distinct, > 0")
    silence_ratio: float = silence_ratio_field("the oscillation")
    max_fit_residual: float = max_fit_residual_field("|L_c z - F^2 eta_c| / |F^2 eta_c|")
    max_prediction_error: float = max_prediction_error_field("standard deviation")


@kernel
def kkl_biased_kernel(
    y: np.ndarray,
    state: np.ndarray,
    lam: np.ndarray,
    lam_phys: np.ndarray,
    fa: np.ndarray,
    fb0: np.ndarray,
    fb1: np.ndarray,
    kv: np.ndarray,
    kk: np.ndarray,
    consts: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Run the biased observer over ``y`` from ``state``; return ``(out, extras, sse, new_state)``.

    ``lam`` = lambda~ (units of omega_ref), ``lam_phys`` = lambda (rad/s); ``fa, fb0, fb1``
    the exact first-order-hold coefficients; ``kv`` (3 x 3, columns) and ``kk`` (3,) the
    eigenvectors and eigenvalues of C^T C, C = (lambda~^2 lambda~ 1), used to solve the
    4 x 4 system by its Schur complement for any mu. ``state`` is the ``xi_state`` array
    (layout: :meth:`KklBiased._initial_state`). ``consts`` packs Ts, omega_ref, l_b, silence_ratio, env_decay,
    n_settle, max_fit_residual, max_prediction_error, avg_gain, the omega Ts bounds of the
    converged range, and the gains of the jump detector's fast and slow means. Pure: the
    inputs are not modified.
    """
    Ts, w_ref, ell, silence_ratio, env_decay, n_settle, max_fit2, max_pred2, avg_gain, wts_lo, wts_hi, fast_gain, slow_gain = (
        observer_constants(consts)
    )  # fmt: skip
    m, n = lam.shape[0], y.shape[0]
    xi, y_prev, have_prev, y_pred, pred_valid, n_good, env, out, ext, rec = observer_head(state, m, n, last_only)
    e2_avg, y_avg, yv_avg, n_run = state[m + 6], state[m + 7], state[m + 8], state[m + 9]
    e2_fast, e2_slow = state[m + 10], state[m + 11]
    det_k0 = kk[0] * kk[1] * kk[2]  # det(C^T C)
    ik0, ik1, ik2 = 1.0 / kk[0], 1.0 / kk[1], 1.0 / kk[2]
    inv_m = 1.0 / m
    sse = 0.0
    defined, good, det, a_sin, a_cos, wts, rr, ff = undefined_sample()  # (n >= 1: set by the loop)
    offset = np.nan
    for k in range(n):
        yk = next_sample(y, k, xi, fa, fb0, fb1, have_prev, y_prev)  # (12)
        if have_prev != 0.0 and n_run < n_settle:  # the filters have run one more sample
            n_run += 1.0
        have_prev = 1.0
        y_prev = yk
        # one-step prediction error; running mean and variance of y
        e2, sse, e2_avg = prediction_error(yk, y_pred, pred_valid, sse, e2_avg, avg_gain)
        y_avg += avg_gain * (yk - y_avg)
        dy = yk - y_avg
        yv_avg += avg_gain * (dy * dy - yv_avg)
        jump, e2_fast, e2_slow = jump_detector(e2, e2_fast, e2_slow, fast_gain, slow_gain, yv_avg)
        # eta = lambda xi, its mean and centred part
        eta_bar = 0.0
        for i in range(m):
            eta_bar += lam_phys[i] * xi[i]
        eta_bar *= inv_m
        s2 = 0.0
        a1 = 0.0  # sum lambda~ eta_c
        a2 = 0.0  # sum lambda~^2 eta_c
        a3 = 0.0  # sum lambda~^3 eta_c
        a4 = 0.0  # sum lambda~^4 eta_c
        q2 = 0.0  # sum lambda~^2 eta_c^2
        for i in range(m):
            c = lam_phys[i] * xi[i] - eta_bar
            l2c = lam[i] * lam[i] * c
            s2 += c * c
            a1 += lam[i] * c
            a2 += l2c
            a3 += lam[i] * l2c
            a4 += lam[i] * lam[i] * l2c
            q2 += l2c * c
        s = math.sqrt(s2)
        env = max(s, env * env_decay)
        pred_valid = 0.0
        defined, good, det, a_sin, a_cos, wts, rr, ff = undefined_sample()
        offset = np.nan
        if n_run >= n_settle:
            offset = eta_bar  # exact for a constant input; replaced below when defined
            y_pred = eta_bar
            pred_valid = 1.0
        if s > ABS_FLOOR + DC_FLOOR * abs(eta_bar) and s >= silence_ratio * env:
            inv = 1.0 / s
            # unit eta_c: L_c^T L_c = [[C^T C, c], [c^T, 1]], c = -(a2, a1, 0) / s,
            # r = L_c^T F^2 eta_c = ((a4, a3, a2) / s, -q2 / s^2)
            c0 = -a2 * inv
            c1 = -a1 * inv
            r0 = a4 * inv
            r1 = a3 * inv
            r2 = a2 * inv
            r3 = -q2 * inv * inv
            # into the eigenbasis of C^T C (c has no third entry: sum eta_c = 0)
            ch0 = kv[0, 0] * c0 + kv[1, 0] * c1
            ch1 = kv[0, 1] * c0 + kv[1, 1] * c1
            ch2 = kv[0, 2] * c0 + kv[1, 2] * c1
            rh0 = kv[0, 0] * r0 + kv[1, 0] * r1 + kv[2, 0] * r2
            rh1 = kv[0, 1] * r0 + kv[1, 1] * r1 + kv[2, 1] * r2
            rh2 = kv[0, 2] * r0 + kv[1, 2] * r1 + kv[2, 2] * r2
            # Gram determinant det(L_c^T L_c) = det(C^T C) (1 - c^T (C^T C)^-1 c)
            det = det_k0 * (1.0 - ch0 * ch0 * ik0 - ch1 * ch1 * ik1 - ch2 * ch2 * ik2)
            mu = max(ell - 2.0 * det, 0.0)
            if mu == 0.0:
                i0, i1, i2 = ik0, ik1, ik2
            else:
                i0 = 1.0 / (kk[0] + mu)
                i1 = 1.0 / (kk[1] + mu)
                i2 = 1.0 / (kk[2] + mu)
            schur = 1.0 + mu - (ch0 * ch0 * i0 + ch1 * ch1 * i1 + ch2 * ch2 * i2)
            if schur > 1e-300:
                z3 = (r3 - (ch0 * rh0 * i0 + ch1 * rh1 * i1 + ch2 * rh2 * i2)) / schur
                w0 = (rh0 - ch0 * z3) * i0
                w1 = (rh1 - ch1 * z3) * i1
                w2 = (rh2 - ch2 * z3) * i2
                z0 = kv[0, 0] * w0 + kv[0, 1] * w1 + kv[0, 2] * w2
                z1 = kv[1, 0] * w0 + kv[1, 1] * w1 + kv[1, 2] * w2
                z2 = kv[2, 0] * w0 + kv[2, 1] * w1 + kv[2, 2] * w2
                # z = ((x1 + x4 - eta_bar) / s, (x2 / omega_ref) / s, x3~ (x4 - eta_bar) / s, x3~)
                if z3 > 0.0:
                    sq = math.sqrt(z3)
                    wts = w_ref * sq * Ts  # omega Ts
                    if wts < math.pi:
                        defined = True
                        dx4 = z2 / z3
                        offset = eta_bar + s * dx4  # x4
                        sh, chh, g = half_step(wts)
                        a_sin = s * (z0 - dx4) * g  # A sin(theta) = x1
                        a_cos = -s * z1 * g / sq  # A cos(theta) = -x2 / omega
                        y_pred = offset + a_sin * (1.0 - 2.0 * sh * sh) + a_cos * (2.0 * sh * chh)
                        pred_valid = 1.0
                        ff = 0.0
                        for i in range(m):
                            cn = (lam_phys[i] * xi[i] - eta_bar) * inv
                            t = lam[i] * lam[i] * cn
                            res = lam[i] * lam[i] * z0 + lam[i] * z1 + z2 - cn * z3 - t
                            rr += res * res
                            ff += t * t
                        good = n_run >= n_settle and consistent(
                            mu, rr, ff, max_fit2, e2_avg, max_pred2, yv_avg, jump, wts, wts_lo, wts_hi
                        )
        # the offset is reported even while the oscillation is undefined
        n_good = record_sample(rec, k, last_only, good, n_good, n_settle, defined, wts, a_sin, a_cos, offset, det,
                               rr, ff, e2_avg, yv_avg)  # fmt: skip
    write_rows(out, ext, rec, last_only, good, n_good, n_settle, defined, wts, Ts, a_sin, a_cos, offset, det, ell,
               rr, ff, e2_avg, yv_avg)  # fmt: skip
    tail = np.array(
        [y_prev, have_prev, y_pred, pred_valid, n_good, env, e2_avg, y_avg, yv_avg, n_run, e2_fast, e2_slow]
    )
    return out, ext, sse, packed_state(xi, tail)


@register
class KklBiased(FilterBankObserver[KklBiasedParams], kernel=kkl_biased_kernel, name="kkl-biased"):
    """KKL observer of one sinusoid with a constant offset: m >= 5 first-order filters and a static inverse map (extension of Praly, Marconi, Isidori)"""

    paper = 'L. Praly, L. Marconi, A. Isidori, "A new observer for an unknown harmonic oscillator" (extended)'
    ell_label = "l_b"
    # the bench's note under its table (``sinewatch bench kernels --estimators kkl-biased``)
    bench_note: ClassVar[str] = (
        "kkl-biased is below the streaming FFT (about 0.3-0.4x at 1024-sample blocks): the work of "
        "kkl (see its note) with m = 5 filters, their centred part and the 4 x 4 regularised "
        "solve by its Schur complement in the eigenbasis of C^T C, every sample: ~80 ns/sample "
        "for the kernel with the rows written after the loop."
    )
    # the default example signal is 0.5 + sin(2 pi 50 t + 0.3) + noise

    def _ell(self, x3_lo: float, x3_hi: float) -> tuple[float, float]:
        return biased_ell(self.lam_n, x3_lo, x3_hi)

    def _setup(self) -> None:
        super()._setup()
        basis = np.column_stack([self.lam_n**2, self.lam_n, np.ones_like(self.lam_n)])
        kk, kv = np.linalg.eigh(basis.T @ basis)
        self._kk = np.ascontiguousarray(kk)
        self._kv = np.ascontiguousarray(kv)
        self._constants = (
            self.lam_n, self.lambdas, self._fa, self._fb0, self._fb1, self._kv, self._kk, self._consts,
        )  # fmt: skip

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``xi_state`` (m + 12,): the filter states xi_1..xi_m, then y_prev, have_prev,
        y_pred, pred_valid, n_good, env, e2_avg, y_avg, yv_avg, n_run, e2_fast, e2_slow."""
        return {"xi_state": np.zeros(self.lam_n.size + 12)}
