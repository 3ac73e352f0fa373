"""``adaptive-multisine``: adaptive observer for n biased sinusoids with excitation switching.

Paper: B. Chen, G. Pin, W. M. Ng, S. Y. Hui, T. Parisini, "An adaptive observer-based
robust estimator of multi-sinusoidal signals", IEEE Trans. Automatic Control 63(6),
1618-1631, 2018. Algorithm 1 is the reference.

Signal (1)-(2): ``y(t) = A0 + sum_i A_i sin(phi_i(t)) + d(t)``, ``phi_i' = omega_i``.

Biased multi-oscillator (3)-(7), ``x in R^(2n+1)`` (``R^(2n)`` with ``bias=False``)::

    x' = F_x x + G_x(x) theta*,       y = C_x x
    F_x = blockdiag(J_1, ..., J_n, 0),  J_i = [[0, 1], [a_i, 0]],  C_x = [1 0 1 0 ... 1 0 | 1]
    G_x_i(x) = -x_{2i-1} e_{2i}                                                      (6)-(7)
    theta*_i = a_i + Omega_i,  Omega_i = omega_i^2                                   (4)

so that ``x_{2i-1} = A_i sin(phi_i)``, ``x_{2i} = A_i omega_i cos(phi_i)`` and
``x_{2n+1} = A0``. *Rebuilt:* the extraction prints ``G_x_i = +x_{2i-1} e_{2i}``; with (4)
and the -1 entry of F_i that gives ``x_{2i}' = (2 a_i + Omega_i) x_{2i-1}``, not an
oscillator, so the sign is ``-`` (the tests check that (3) with it generates the sinusoids).

Output filter (12): ``yf' = F_f yf + B_f y`` with ``n_f = n - 1`` states (``F_f`` diagonal,
``B_f`` a vector). Augmented state (15): ``z = [x; yf]``, ``F_z = [[F_x, 0], [B_f C_x, F_f]]``,
``C_z = blockdiag(C_x, I_{n-1})``, output ``eta = [y; yf]``, ``G_z = [G_x; 0]``.
Estimator, with ``L = [[L_x, 0], [0, 0]]``, ``L_x`` by pole placement of ``F_x - L_x C_x``
(Algorithm 1's initialisation) and ``A_L = F_z - L C_z``::

    zh'  = A_L zh + L eta + G_z(zh) thetah + Xi thetah'                              (16)
    xi_i' = A_L xi_i + G_z_i(zh),   Xi = [xi_1 ... xi_n]                        (17)-(18)
    thetah' = P[thetah'_unc]  (projection on |thetah| <= theta_bar)            (19)-(21)
    thetah'_unc = -mu V Psi V^T Xi^T C_z^T (C_z zh - eta)                            (22)
    Ah_i' = -mu_A omegah_i (omegah_i Ah_i - A_i,inst)                                (11)
    omegah_i = sqrt(thetah_i - a_i) (8),  phih_i = angle(x_{2i} + j omegah_i x_{2i-1}) (10)

Excitation (23)-(25): ``M = Xi^T Xi + rho^2 I``, ``Phi_Xi = Xi^T C_z^T C_z Xi``; ``lambda_i``
are the eigenvalues of ``Phi_Psi = M^-1 Phi_Xi`` (in [0, 1)), sorted decreasing; ``psi_i``
switches on at ``lambda_i >= delta_high``, off below ``delta_low``, holds in between.
``Phi_Psi`` is not symmetric, so (22) is implemented with the generalised eigenvectors
``Phi_Xi v = lambda M v`` normalised by ``V^T M V = I`` (``V V^T = M^-1``): with every
``psi_i = 1`` it is the paper's own reduction (33), ``-mu M^-1 Xi^T C_z^T (...)``, with partial
excitation it freezes exactly the under-excited generalised directions (D1 of the explicit
mode, :mod:`sinewatch.estimators._adaptive_multisine_explicit`, says why).

Two modes, chosen by ``band_hz``:

* **automatic design** (``band_hz`` given; this module's kernels): the user gives n, the band
  ``[f_lo, f_hi]`` the components lie in and whether there is an offset; everything else is
  derived below (AD1-AD8). One step per sample, no sub-steps, no matrix exponential, no
  eigen-decomposition while every direction is excited and none above AD5's cap. For n = 1 and
  n = 2 the same steps are written out (:func:`auto_kernel_n1`, :func:`auto_kernel_n2`: the state
  in registers, (23), (25) and AD5's cap in closed form), several times faster than the general
  kernel and equal to it to rounding.
* **explicit gains** (no ``band_hz``): the paper's per-example gains in ``omega_unit_rad_s``
  units, RK4 sub-steps; kept unchanged so that recordings made with it replay bit for bit.

Automatic design (every rate in units of ``w_ref = 2 pi f_hi``, scaled time ``tau = w_ref t``;
``beta = f_lo / f_hi``; the constants are ``DESIGN``):

AD1 Initial frequencies spread geometrically over the band, ``omegah_i(0) = beta^(1 - (i - 1/2)/n)``,
    and ``a_i = -omegah_i(0)^2``, so ``thetah(0) = 0``: the observer poles are placed for the
    frozen model at the initial estimates (the paper needs ``a_i`` distinct and non-zero, (4);
    a small ``|theta*|`` is what its conditions (36), (39) reward: ``theta_bar`` enters them as
    ``3 p_bar theta_bar``).
AD2 Observer poles, ``2n (+1)`` distinct, geometric in ``[p_min, p_max] sqrt(omegah_1(0))``
    (the geometric mean of the lowest initial frequency and the band's top). The paper's
    examples place them between 0.1 and 1 times the lowest tone; anchored there alone they are
    too fast for a narrow band, anchored at the top too slow for a wide one (measured on the
    paper's examples and a 5:1 band).
AD3 Filter (12): ``F_f = -omegah_{j+1}(0)``, ``B_f = -F_f`` (unit DC gain; the paper: -5/4.5,
    -6/6, -2/1 for tones between 2 and 7 rad/s).
AD4 ``rho`` (23) is in the units of ``Xi`` (signal units over rate squared), unknown in advance:
    ``rho^2 = rho_rel * smoothed tr(Xi^T Xi) / n``, floored at ``(min_amplitude / (omegah_1(0)
    |p_fast|))^2`` (the size of ``Xi`` for a tone at ``min_amplitude``), so that ``lambda_i``
    measures how much of ``Xi`` the output sees whatever the amplitude and the design.
    ``rho`` also sets how hard the law (22) drives a component whose tone is gone: its column
    ``xi_i`` shrinks with its state, and its gain goes as ``|xi_i| / (|xi_i|^2 + rho^2)``.
    ``rho_rel = 0.1`` let the idle component of Example 2 drift from 2 to 2.6 rad/s towards the
    remaining tone and share it (amplitude still 0.08 at 240 s); ``0.2`` holds it below
    2.35 rad/s and fades it (amplitude below 0.03 from 190 s; with AD5's cap below 2.02 rad/s,
    faded from 124 s); ``0.5`` slows Example 1 three times (measured,
    tests/test_adaptive_multisine_auto.py).
AD5 ``mu`` (22): the excited parameter error decays at ``mu lambda_i`` (proof of Theorem 4.1,
    ``-mu delta_low |theta~|^2``), and Theorem 4.1 needs the adaptation slower than the observer
    (the cross terms of (36) grow with ``mu p_bar``). ``mu = kappa |slowest pole| / lambda_typ``,
    and no direction adapts faster than ``kappa |slowest pole|``: while ``tr(M^-1 Phi_Xi) =
    sum_i lambda_i`` (a bound of lambda_1 from the factors of M, n triangular solves) exceeds
    ``lambda_typ``, (22) runs on the generalised eigenvectors with ``psi_i`` scaled by
    ``min(1, lambda_typ / lambda_i)``: the rate of direction i is ``min(mu lambda_i, kappa
    |slowest pole|)``. The lambda_i depend on n and the offset far more than on the tones: the
    sum averages 0.27 in Example 1, 0.12 in the experiment, 0.03 in Example 2, 0.007 for n = 5
    in 2-20 Hz, and reaches 0.16 at n = 5 as the dwell (AD7) ends, while Xi (17) is still
    building up. With ``mu`` alone (``kappa = 0.1``, no cap) Example 1 adapted up to 3 times
    faster than its slowest pole (estimates swinging between 1.3 and 4 rad/s for 5 s, the
    settling time a matter of the trajectory) and n = 5 without offset, noise-free and started
    at the true frequencies, was thrown 30 % off them within 30 ms of the dwell's end, into an
    ordering that its partly excited directions (2 of 5 above delta_high) did not undo in 60 s
    (measured). ``lambda_typ`` is thus the excitation above which a direction adapts at the
    full rate (below it, the paper's law unchanged); ``kappa = 0.2``: 0.3 lets that n = 5
    case walk away again (19 %), 0.25 settles the experiment in 24 s at one of four noise
    seeds (tests/test_adaptive_multisine_auto.py measures the figures). ``mu_A`` (11): the
    amplitude filter runs at the slowest observer pole at ``omegah_1(0)``.
AD6 Frequency clips (Remark 3.1) at the band, widened by ``band_margin``, and the components
    kept ordered and ``separation`` apart (two on one line form an unobservable pair, and the
    re-placement AD8 needs distinct frequencies); the projection ball (19)-(21) is the one the
    clips imply.
AD7 The settling dwell (D4 of the explicit mode): ``thetah`` adapts only ``dwell_poles /
    |slowest pole|`` after the start and after the signal's return (start-up transients are
    output error the law would read as parameter error); nothing adapts while the signal is
    absent (its AC power over one period of ``omegah_1(0)`` below ``min_amplitude^2 / 2`` or a
    quarter of its power over ten periods).
AD8 Re-centring: the observer (16) runs ``F_x(a) - L_x C_x + G_x thetah = F_x(a - thetah) - L_x
    C_x``, so its poles are the placed ones only at ``thetah = 0``; with ``L_x`` fixed and the
    estimates far from ``-a`` some of its modes decay 30 times slower than placed (measured on
    Example 1). When some ``|thetah_i|`` exceeds ``recentre |a_i|``, ``a <- a - thetah``,
    ``thetah <- 0`` and ``L_x`` is placed again for the new ``a`` (closed form, :func:`_place`):
    the same estimates, the same state, and ``theta*`` (hence ``theta_bar`` in (36)) shrinks to
    the estimation error as the estimates converge.

Discretisation (the paper: forward Euler at Ts = 0.3 ms). Forward Euler on an undamped
oscillator grows by ``sqrt(1 + (h omega)^2)`` per step; here every oscillator pair of
(16)-(17) is stepped with symplectic Euler (``x_{2i-1}`` first, then ``x_{2i}`` from the new
``x_{2i-1}``), the rest with forward Euler, one step of ``h = w_ref / fs`` per sample. With the
output error at zero, the observer is then the exact recursion of a sampled sinusoid of
frequency ``omega_d`` with ``2 sin(omega_d h / 2) = h sqrt(Omegah)``: the reported frequency is
``omega_d`` (no discretisation bias at any ``h omega < 2``), and (9)-(10) use the exact sampled
relations ``x_{2i-1} = A sin(phi)``, ``h x_{2i} + x_{2i-1} (1 - cos delta) = A cos(phi) sin delta``
(``delta = omega_d h``) for the instantaneous amplitude ``A_i,inst`` and the phase.

Outputs (both modes): a component whose amplitude falls below ``max(min_amplitude,
fade_ratio max_j A_j)`` is faded (``component_faded``): frequency and phase NaN; ``converged``
needs the dwell passed, every component present, apart, and its smoothed ``|Omegah -
smoothed Omegah|`` below ``2 convergence_tol Omegah``. Extras per sample:
``excitation_level`` (lambda_i, (N, n)), ``adaptation_enabled`` (psi_i), ``component_faded``,
``signal_present`` and ``observer_reset`` ((N,)). The residual is the a-priori output error
``y_k - C_x zh_k``. Speed: ``sinewatch bench kernels --estimators adaptive-multisine`` (the
class's ``bench_note`` gives the figures).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import Field, model_validator

from sinewatch.estimators import _adaptive_multisine_auto as auto
from sinewatch.estimators import _adaptive_multisine_explicit as explicit
from sinewatch.estimators import register
from sinewatch.estimators._adaptive_multisine_auto import (
    DESIGN,
    EXPLICIT_ONLY,
    MIN_SAMPLES_PER_PERIOD,
    adaptive_multisine_kernel,
    auto_design,
)
from sinewatch.estimators._adaptive_multisine_bank import adaptive_multisine_n2_bank_kernel, run_adaptive_multisine_bank
from sinewatch.estimators._adaptive_multisine_small import (
    auto_kernel_n1,
    auto_kernel_n2,
)
from sinewatch.estimators.bank import register_bank
from sinewatch.estimators.base import Estimator, EstimatorParams, NonNegativeFinite, PositiveFinite, Track
from sinewatch.schemas.errors import ParameterError

# the design constants the benches read and the kernels, where users of the estimator look for them
__all__ = [
    "DESIGN",
    "MIN_SAMPLES_PER_PERIOD",
    "PAPER_DESIGN",
    "AdaptiveMultisine",
    "AdaptiveMultisineParams",
    "adaptive_multisine_kernel",
]

# The paper's tunings for n = 2 (Section V): the explicit mode's defaults.
# With bias: Example 2 (its initial frequencies are not given; (3.5, 2.5) is ours); without:
# Example 1 (initial frequencies 3 and 4 rad/s as in the paper). Units: rad/s with
# omega_unit_rad_s = 1.
PAPER_DESIGN = {
    True: {
        "a": [-2.0, -1.0],
        "poles": [-0.6, -0.5, -0.3, -1.0, -10.0],
        "filter_poles": [-6.0],
        "filter_gains": [6.0],
        "mu": 70.0,
        "rho": 0.3,
        "mu_a": 0.1,
        "omega0": [3.5, 2.5],
    },
    False: {
        "a": [0.0, -0.5],
        "poles": [-2.0, -0.7, -0.5, -0.2],
        "filter_poles": [-5.0],
        "filter_gains": [4.5],
        "mu": 6.0,
        "rho": 0.2,
        "mu_a": 0.15,
        "omega0": [3.0, 4.0],
    },
}

#: A finite fraction in [0, 1) (the ratios and thresholds below; 0 switches a test off).
_Fraction = Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)]


class AdaptiveMultisineParams(EstimatorParams):
    """With ``band_hz``: the automatic design, from n, the band and ``bias`` (the fields marked
    "explicit mode" are then rejected). Without: the explicit gains, rates in units of
    ``omega_unit_rad_s``, amplitudes in ``amplitude_unit``; left unset, the design (a .. omega0)
    is the paper's tuning for n = 2 (Example 2 with bias, Example 1 without)."""

    n_sinusoids: int = Field(2, ge=1, le=8, description="n, the number of sinusoids modelled")
    bias: bool = Field(True, description="Model the offset A0 (state x_{2n+1}); False: zero-mean signal")
    band_hz: tuple[float, float] | None = Field(
        None,
        description="[f_lo, f_hi] (Hz) the n frequencies lie in: selects the automatic design; "
        "unset: the explicit mode (the fields below marked so)",
    )
    omega_unit_rad_s: PositiveFinite = Field(
        1.0,
        description="Angular frequency (rad/s) that counts as 1 in every rate parameter; 1 = the paper's units",
    )
    amplitude_unit: PositiveFinite = Field(
        1.0, description="Signal value that counts as 1 (the input is divided by it)"
    )
    a: list[float] | None = Field(None, description="a_i of (4): distinct, and non-zero with bias")
    poles: list[float] | None = Field(
        None, description="2n (+1 with bias) distinct negative real poles of F_x - L_x C_x (16)"
    )
    filter_poles: list[float] | None = Field(None, description="n-1 distinct negative poles of F_f (diagonal), (12)")
    filter_gains: list[float] | None = Field(None, description="n-1 non-zero entries of B_f, (12)")
    mu: PositiveFinite | None = Field(None, description="Frequency adaptation gain mu, (22)")
    rho: PositiveFinite | None = Field(None, description="Regularisation rho, (23)")
    mu_a: PositiveFinite | None = Field(None, description="Amplitude adaptation gain mu_A, (11)")
    omega0: list[float] | None = Field(None, description="Initial frequencies omegah_i(0), in (0, omega_max)")
    delta_low: float = Field(3e-5, allow_inf_nan=False, description="Lower switching threshold of (25)")
    delta_high: float = Field(3e-4, allow_inf_nan=False, description="Upper switching threshold of (25)")
    omega_max: PositiveFinite = Field(10.0, description="Frequency bound omega_bar (Assumption 1); sets theta_bar")
    omega_ranges: list[tuple[float, float]] | None = Field(
        None, description="Optional per-component frequency clips [lo, hi] (Remark 3.1)"
    )
    adaptation_delay: NonNegativeFinite | None = Field(
        None,
        description="Settling dwell (scaled time) after start-up, total dis-excitation or loss of signal "
        "before thetah adapts; default 2 / |slowest observer pole|",
    )
    level_time: PositiveFinite = Field(2.0, description="Time constant (scaled) of the signal-level gate")
    level_ratio: _Fraction = Field(
        0.25,
        description="The signal counts as lost when its AC power (over level_time) falls below this "
        "fraction of its power over 10 level_time",
    )
    min_separation: _Fraction = Field(
        0.05,
        description="Components are kept at least this fraction of the higher frequency apart (0: off)",
    )
    min_amplitude: NonNegativeFinite = Field(
        0.01,
        description="Amplitude (in amplitude_unit) below which a component is faded and the signal absent",
    )
    fade_ratio: _Fraction = Field(
        0.02,
        description="A component is also faded below this fraction of the largest amplitude",
    )
    convergence_time: PositiveFinite = Field(10.0, description="Smoothing time (scaled) of the convergence test")
    convergence_tol: float = Field(
        0.02,
        gt=0,
        lt=1,
        allow_inf_nan=False,
        description="converged once the smoothed |omegah - smoothed omegah| is below this fraction of omegah",
    )

    @model_validator(mode="after")
    def _check(self) -> AdaptiveMultisineParams:
        n = self.n_sinusoids
        if not 0 < self.delta_low < self.delta_high < 1:
            raise ValueError(
                f"expected 0 < delta_low < delta_high < 1, got delta_low={self.delta_low}, delta_high={self.delta_high}"
            )
        if self.band_hz is not None:
            lo, hi = self.band_hz
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
                raise ValueError(f"band_hz: expected finite 0 < f_lo < f_hi, got {self.band_hz}")
            # set to other than their defaults (a dumped state carries every field)
            fixed = sorted(k for k in EXPLICIT_ONLY if getattr(self, k) != type(self).model_fields[k].default)
            if fixed:
                raise ValueError(
                    f"expected no {', '.join(fixed)} with band_hz (the automatic design sets them; "
                    "they belong to the explicit mode)"
                )
        elif n != 2:
            missing = [k for k in auto._DESIGN_KEYS if getattr(self, k) is None]
            if missing:
                raise ValueError(
                    f"expected an explicit design for n_sinusoids={n} (the paper tunes n = 2), "
                    f"got no {', '.join(missing)}"
                )

        def _finite_list(name: str, v: list[float] | None, length: int) -> None:
            if v is None:
                return
            if len(v) != length:
                raise ValueError(f"{name}: expected {length} values, got {len(v)}")
            if not all(math.isfinite(x) for x in v):
                raise ValueError(f"{name}: expected finite values, got {v}")

        _finite_list("a", self.a, n)
        _finite_list("poles", self.poles, 2 * n + int(self.bias))
        _finite_list("filter_poles", self.filter_poles, n - 1)
        _finite_list("filter_gains", self.filter_gains, n - 1)
        _finite_list("omega0", self.omega0, n)
        for name, v in (("poles", self.poles), ("filter_poles", self.filter_poles)):
            if v is not None:
                if any(p >= 0 for p in v):
                    raise ValueError(f"{name}: expected values in the left half-plane (< 0), got {v}")
                if len(set(v)) != len(v):
                    raise ValueError(f"{name}: expected distinct values, got {v}")
        if self.filter_gains is not None and any(b == 0 for b in self.filter_gains):
            raise ValueError(f"filter_gains: expected non-zero values (controllability), got {self.filter_gains}")
        if self.omega_ranges is not None:
            if len(self.omega_ranges) != n:
                raise ValueError(f"omega_ranges: expected {n} [lo, hi] pairs, got {len(self.omega_ranges)}")
            for lo, hi in self.omega_ranges:
                if not (0 <= lo < hi <= self.omega_max):
                    raise ValueError(
                        f"omega_ranges: expected 0 <= lo < hi <= omega_max={self.omega_max}, got [{lo}, {hi}]"
                    )
        return self

    @property
    def f_min_hz(self) -> float | None:
        """The lowest frequency expected: the band's bottom in the automatic mode (the pipeline
        sizes its signal-presence window on it), None in the explicit mode."""
        return self.band_hz[0] if self.band_hz is not None else None

    def design(self) -> dict[str, Any]:
        """The effective a, poles, filter poles and gains (lists), mu, rho, mu_a (floats) and
        omega0 (list)."""
        base = PAPER_DESIGN[self.bias]
        out: dict[str, Any] = {}
        for k in auto._DESIGN_KEYS:
            v = getattr(self, k)
            out[k] = (list(v) if isinstance(v, list) else v) if v is not None else base[k]
        return out


@register
class AdaptiveMultisine(
    Estimator[AdaptiveMultisineParams], kernel=adaptive_multisine_kernel, name="adaptive-multisine"
):
    """Adaptive observer for n biased sinusoids with excitation-based switching (Chen et al. 2018)"""

    paper = (
        'B. Chen, G. Pin, W. M. Ng, S. Y. Hui, T. Parisini, "An adaptive observer-based robust estimator '
        'of multi-sinusoidal signals", IEEE Trans. Automatic Control 63(6), 2018'
    )
    # The paper's Example 2 (tones at 3 and 2 rad/s, amplitudes 4 and 3, offset 1), time
    # compressed: the tones are at 15 and 10 Hz; the automatic design from n = 2 and a band.
    example_sample_rate_hz = 750.0
    example_frequency_hz = 15.0
    # In automatic mode its memory is already a settling bound from a cold start (the design's
    # settling dwell, AD7, plus the convergence test's smoothing), as grip-mixing's is: one memory
    # of signal (validity rules 5). With two, the paper's Example 2 served for 30 s (tones at 2 and
    # 3 rad/s, a memory of 5.7 s) ended without a valid estimate.
    REFILL_MEMORIES: ClassVar[int] = 1
    example_params: ClassVar[dict[str, Any]] = {"n_sinusoids": 2, "band_hz": (5.0, 25.0)}
    # Printed by ``sinewatch bench kernels`` under its table.
    bench_note: ClassVar[str] = (
        "adaptive-multisine at n = 2 (the example) runs at 0.53-0.55x the streaming FFT, not 1x "
        "(`sinewatch bench kernels --block 1024 --estimators adaptive-multisine`, five runs: 53-56 "
        "ns/sample against 29-30): each sample is one chain of dependent arithmetic that the CPU "
        "cannot overlap with the next. The observer (16) and the sensitivity filters (17) step with "
        "the law (22) of the same sample, and the next sample's law needs M = Xi^T Xi + rho^2 I of "
        "the new Xi, the eigenvalues of (23) (a square root) and a division; the state (~45 "
        "numbers) and the constants do not fit in the registers. ~47 ns/sample in the kernel "
        "(products fused with fma(), the eigenvector replaced by the projector (M^-1 Phi_Xi - "
        "lambda_2 I) / (lambda_1 - lambda_2)), ~6.5 us a block of Python call and Track. n = 1: 38 "
        "ns/sample. n >= 3 runs the general kernel: some direction is then always under-excited, so "
        "every sample takes the generalised eigen-decomposition (Jacobi): 0.8 us/sample at n = 3, "
        "3.1 us at n = 5."
    )
    # Printed by ``sinewatch bench kernels --bank N`` when the bank is below its target.
    bank_note: ClassVar[str] = (
        "the bank (n = 2 of the automatic mode; other modes run their channels one by one) runs 8 "
        "channels through auto_kernel_n2's per-sample functions as two 256-bit vectors on an AVX2 "
        "host: 1.6x one channel at a time, not the 4x that 2x the FFT needs. Vectorised, every branch "
        "of a sample is computed and selected, so the divisions and square roots of the law (22) with "
        "one direction on or capped (10 vdivpd and 5 vsqrtpd a vector step in the kernel's assembly) "
        "sit on every sample's chain, which a channel alone skips; the state (43 numbers a lane) and "
        "the constants exceed the 16 vector registers (spills); lanes i and i + 4 in one loop body "
        "(two chains overlapped) measured 45 against 42-44 ns a channel-sample (the lanes' step "
        "alone, load 5-11, 2-core AMD EPYC VM (AVX2)). Computing that rare branch in a scalar fix-up "
        "pass instead cannot pay: with the branch taken out of the lanes' step altogether (its upper "
        "bound; wrong results, timed only) the kernel alone measured 41.1 against 44.0 ns a "
        "channel-sample (0.95x; 1.08x against 1.02x the streaming FFT in the same paired rounds, "
        "1024-sample blocks, 8 channels, load 7-12): the common path itself, not the branch, is "
        "what stays under 2x"
    )

    @classmethod
    def example_signal(cls, n: int, seed: int = 0) -> np.ndarray:
        """1 + 4 sin(2 pi 15 t) + 3 sin(2 pi 10 t + 0.5) + uniform noise in [-0.1, 0.1]
        (Example 2 of the paper before its t = 120 s, time compressed 10 pi times)."""
        rng = np.random.default_rng(seed)
        t = np.arange(n) / cls.example_sample_rate_hz
        return (
            1.0
            + 4.0 * np.sin(2 * np.pi * 15.0 * t)
            + 3.0 * np.sin(2 * np.pi * 10.0 * t + 0.5)
            + rng.uniform(-0.1, 0.1, n)
        )

    @property
    def n_components(self) -> int:
        return self.params.n_sinusoids

    @property
    def automatic(self) -> bool:
        """True in the automatic-design mode (``band_hz`` given)."""
        return self.params.band_hz is not None

    def _check_params(self) -> None:
        p = self.params
        if p.band_hz is None:
            explicit.check(p, self.sample_rate_hz)
            return
        # the observer's injection and the filters are forward Euler: the band's top (with its
        # margin) needs 10 samples per period for them to stay stable (measured: a tone at 100 Hz
        # in a 20-120 Hz band is exact to 1e-10 at 1.5 kHz and diverges at 1 kHz)
        top = p.band_hz[1] * (1.0 + DESIGN["band_margin"])
        if top > self.sample_rate_hz / MIN_SAMPLES_PER_PERIOD:
            raise ParameterError(
                f"band_hz: expected f_hi (1 + {DESIGN['band_margin']}) <= sample_rate_hz / {MIN_SAMPLES_PER_PERIOD:g}"
                f" = {self.sample_rate_hz / MIN_SAMPLES_PER_PERIOD:.6g} Hz, got {top:.6g} Hz"
            )

    def _setup(self) -> None:
        p = self.params
        # n = 1, 2 of the automatic mode: the kernels written out for them (_run), called from
        # Python rather than through adaptive_multisine_kernel, so that the explicit mode's kernel
        # (recordings replay it bit for bit) is compiled alone, as before they existed
        self._small_n_kernel: Callable[..., tuple[Any, ...]] | None = None
        if p.band_hz is None:
            d = explicit.setup(p, self.sample_rate_hz)
            self._cf, self._ci = d["cf"], d["ci"]
            self._nf, self._nz, self._theta0 = d["nf"], d["nz"], d["theta0"]
            self.L_x = d["L_x"]
            self.theta_bar = d["theta_bar"]
            self.substeps = d["substeps"]
            self.settling_time = d["settling_time"]
            self._constants = (self._cf, self._ci)
            return
        n, bias = p.n_sinusoids, p.bias
        d = auto_design(n, bias, p.band_hz)
        self.design = d
        a = np.asarray(d["a"], dtype=np.float64)
        nx = 2 * n + int(bias)
        nf = n - 1
        nz = nx + nf
        Fx, Cx = explicit.observer_matrices(a, bias)
        poles = np.asarray(d["poles"], dtype=np.float64)
        # (16): L_x by pole placement (Algorithm 1's initialisation), in the closed form the
        # kernel re-places it with (AD8); checked against the eigenvalues it gives
        tmp = np.concatenate([a, np.zeros(nx)])
        auto._place(tmp, 0, n, poles, n, int(bias))
        Lx = tmp[n:].copy()
        got = np.sort(np.linalg.eigvals(Fx - np.outer(Lx, Cx)).real)
        if not np.allclose(got, np.sort(poles), rtol=1e-3, atol=0.0):
            raise ParameterError(f"band_hz: the observer poles {list(poles)} could not be placed (got {list(got)})")
        w_lo, w_hi = d["w_lo"], d["w_hi"]
        # the ball of (19)-(21): with a re-centred (AD8) |thetah_i| stays below the band's span
        tbar = math.sqrt(n) * (w_hi * w_hi - w_lo * w_lo)
        h = d["w_ref"] / self.sample_rate_hz
        consts = np.zeros(auto._N_K)
        consts[auto._K_H] = h
        consts[auto._K_MU] = d["mu"]
        consts[auto._K_RHO2] = d["rho_rel"] ** 2
        consts[auto._K_MUA] = d["mu_a"]
        consts[auto._K_DHI] = p.delta_high
        consts[auto._K_DLO] = p.delta_low
        consts[auto._K_TBAR] = tbar
        consts[auto._K_OMU] = d["w_ref"]
        consts[auto._K_MINA] = p.min_amplitude
        consts[auto._K_FADE] = p.fade_ratio
        consts[auto._K_CALPHA] = -math.expm1(-h / d["convergence_time"])
        consts[auto._K_CTOL] = p.convergence_tol
        consts[auto._K_DELAY] = d["dwell"]
        consts[auto._K_ZMAX] = 1e4
        consts[auto._K_LALPHA] = -math.expm1(-h / d["level_time"])
        consts[auto._K_OMLO] = w_lo * w_lo
        consts[auto._K_OMHI] = w_hi * w_hi
        consts[auto._K_RC] = DESIGN["recentre"]
        consts[auto._K_SEP] = (1.0 + DESIGN["separation"]) ** 2
        # |xi_i| ~ A / (omega p) for a tone of amplitude A at omega through poles p: the floor of
        # rho is min_amplitude's
        # the input's mean and AC power (signal presence, the guard) over one period of the
        # lowest initial frequency: shorter, they follow the waveform itself
        consts[auto._K_PALPHA] = -math.expm1(-h / (2.0 * math.pi / d["omega0"][0]))
        consts[auto._K_LCAP] = d["lambda_cap"]
        consts[auto._K_XIFLOOR] = (p.min_amplitude / (d["omega0"][0] * -max(d["poles"]))) ** 2
        self._cf = np.concatenate([consts, poles, np.asarray(d["filter_poles"]), np.asarray(d["filter_gains"])])
        self._ci = np.array([n, nx, nf, nz, 0, int(bias), 1], dtype=np.int64)
        self._small_n_kernel = {1: auto_kernel_n1, 2: auto_kernel_n2}.get(n)
        self._constants = (self._cf, self._ci)
        self._nf, self._nz = nf, nz
        self._a0 = a
        self.L_x = Lx
        self.theta_bar = tbar
        self.substeps = 1
        self.settling_time = d["dwell"] / d["w_ref"]  # seconds

    @property
    def memory_samples(self) -> int:
        """Automatic mode: the settling dwell (AD7) plus the convergence test's smoothing time;
        explicit mode: the base class's default."""
        if not self.automatic:
            return super().memory_samples
        d = self.design
        seconds = (float(d["dwell"]) + float(d["convergence_time"])) / float(d["w_ref"])
        return max(1, math.ceil(seconds * self.sample_rate_hz))

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``s``, explicit mode: :func:`sinewatch.estimators._adaptive_multisine_explicit.initial_state`.
        Automatic mode: yf (nf) | zh (nz) | Xi (nz n, xi_i contiguous) | thetah (n) | Ah (n) |
        psi (n) | smoothed Omegah (n) | smoothed |Omegah - smoothed Omegah| (n) | the scalars
        _S_CLOCK (dwell clock), _S_MEAN, _S_POW (input mean and AC power), _S_STARTED,
        _S_XI (smoothed tr(Xi^T Xi) / n), _S_POWL (AC power over ten times as long) | a (n)
        and L_x (nx), re-centred and re-placed as the estimates move (AD8); thetah(0) = 0."""
        n, nf, nz = self.params.n_sinusoids, self._nf, self._nz
        if not self.automatic:
            return {"s": explicit.initial_state(n, nf, nz, self._theta0)}
        nx = nz - nf
        s = np.zeros(nf + nz + nz * n + 5 * n + auto._N_S + n + nx)
        oa = nf + nz + nz * n + 5 * n + auto._N_S
        s[oa : oa + n] = self._a0
        s[oa + n :] = self.L_x
        return {"s": s}

    def _run(
        self, samples: np.ndarray, state: dict[str, np.ndarray], last_only: bool
    ) -> tuple[Track, dict[str, np.ndarray]]:
        if self._small_n_kernel is None:
            return super()._run(samples, state, last_only)
        out, ext, sse, s = self._small_n_kernel(samples, state["s"], self._cf, self._ci, last_only)
        return self._track((out, ext, sse), samples), {"s": s}

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out, ext, sse = outputs
        c = self._columns
        # the flags are 0.0 or 1.0: one conversion for the four (a comparison each cost ~0.8 us a block)
        flags = ext[c[5]].astype(bool)
        return Track(
            frequency_hz=out[c[0]],
            amplitude=out[c[1]],
            phase_rad=out[c[2]],
            offset=out[c[3]],
            converged=out[c[4]].astype(bool),
            residual_rms=math.sqrt(sse / block.shape[0]),
            extras={
                "excitation_level": ext[c[6]],
                "adaptation_enabled": flags[c[6]],
                "component_faded": flags[c[1]],
                "signal_present": flags[c[7]],
                "observer_reset": flags[c[8]],
            },
        )

    @functools.cached_property
    def _columns(self) -> tuple[tuple[slice, Any], ...]:
        """The index of each field in the kernel's outputs, built once (an index built per block
        cost 70 ns of the 170 each of the ten views takes): out's frequencies, amplitudes, phases,
        offset, converged; ext's flags; lambda_i (and in the flags psi_i), present, reset."""
        n, all_rows = self.params.n_sinusoids, slice(None)
        return tuple(
            (all_rows, i)
            for i in (
                slice(0, n),
                slice(n, 2 * n),
                slice(2 * n, 3 * n),
                3 * n,
                3 * n + 1,
                slice(n, None),
                slice(0, n),
                2 * n,
                2 * n + 1,
            )
        )


# n = 2 of the automatic mode only (run_adaptive_multisine_bank); other channels run one by one
register_bank(AdaptiveMultisine, adaptive_multisine_n2_bank_kernel, n_outputs=3, run=run_adaptive_multisine_bank)
