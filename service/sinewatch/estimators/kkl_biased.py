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

from collections.abc import Callable
from typing import ClassVar

import numpy as np

from sinewatch.estimators import register
from sinewatch.estimators.bank import register_bank
from sinewatch.estimators.kkl import (
    PAPER_LAMBDA_FACTORS,
    FilterBankObserver,
    KklParams,
    ell_eq10,
    lambda_factors_field,
    max_fit_residual_field,
    max_prediction_error_field,
    observer_bank_tracks,
    silence_ratio_field,
)
from sinewatch.estimators.kkl_biased_kernels import DC_FLOOR, kkl_biased_bank_kernel, kkl_biased_kernel

__all__ = ["DC_FLOOR", "KklBiased", "KklBiasedParams", "biased_ell", "gamma_biased_reference", "kkl_biased_kernel"]

BIASED_LAMBDA_FACTORS = (*PAPER_LAMBDA_FACTORS, 5.0 / 3.0)


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
    # Printed by ``sinewatch bench kernels --bank N`` when the bank stays below twice the FFT.
    bank_note: ClassVar[str] = (
        "the bank is kkl's (lane-major state, the m = 5 filters unrolled, two loops over 8 lanes that "
        "LLVM vectorises 8 doubles wide: vdivpd, vsqrtpd and vmulpd on zmm in its assembly, the sine "
        "of the first-order hold's correction by sinewatch.estimators.detmath.sin, no library call) "
        "at ~3.5-4.7x one channel, and is bound by the arithmetic: per sample and channel the work of "
        "kkl's bank with one more filter, the centred sums and the 4 x 4 solve by its Schur "
        "complement: seven divisions (the three of the regularised eigenvalues are taken for every "
        "lane: a vector computes both sides of the select on mu = 0) and two square roots, "
        "long-latency and not fully pipelined, plus the sine's ~40 flops. 512-bit lanes against "
        "256-bit ones, measured in turn under load 13-23: 1.29x and 1.20x the streaming FFT. Without "
        "AVX-512 (2-core AMD EPYC VM (AVX2)), read in the bank's assembly: its sample loop is 810 "
        "instructions, 527 of them packed double arithmetic, 8 vdivpd and 3 vsqrtpd, 155 loads and "
        "stores on the stack (more live values than AVX2's 16 registers) and no masked move (863 "
        "instructions, 167 on the stack and 26 vmaskmovpd before): the lanes' flags are LLVM selects "
        "and & (a Python conditional or `and` is a branch in numba's IR, and the vectoriser predicated "
        "the stores behind those branches: pairs of masked stores of complementary masks) and a row "
        "kept where a lane's flag is off goes through freeze (sinewatch.estimators.lanes.select and "
        "frozen; vmaskmovpd is microcode on AMD's cores): the kernel 35.5-36.4 -> 28.9-30.5 ns a "
        "channel-sample, update_bank 1.21-1.27x -> 1.52-1.65x the streaming FFT (`sinewatch bench "
        "kernels --block 1024 --bank 8`, paired "
        "rounds, load 4-16). What is left is that arithmetic, ~90 % of update_bank"
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


register_bank(KklBiased, kkl_biased_bank_kernel, n_outputs=3, tracks=observer_bank_tracks)
