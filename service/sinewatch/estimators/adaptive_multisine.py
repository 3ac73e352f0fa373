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

from sinewatch.estimators import _adaptive_multisine_explicit as explicit
from sinewatch.estimators import register
from sinewatch.estimators.base import Estimator, EstimatorParams, NonNegativeFinite, PositiveFinite, Track, fma, kernel
from sinewatch.schemas.errors import ParameterError

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
_DESIGN_KEYS = ("a", "poles", "filter_poles", "filter_gains", "mu", "rho", "mu_a", "omega0")

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
            missing = [k for k in _DESIGN_KEYS if getattr(self, k) is None]
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
        for k in _DESIGN_KEYS:
            v = getattr(self, k)
            out[k] = (list(v) if isinstance(v, list) else v) if v is not None else base[k]
        return out


# ---- automatic design ---------------------------------------------------------------------------
#: The fields only the explicit mode reads (rejected with ``band_hz``).
EXPLICIT_ONLY = (
    "omega_unit_rad_s",
    "amplitude_unit",
    *_DESIGN_KEYS,
    "omega_max",
    "omega_ranges",
    "adaptation_delay",
    "level_time",
    "level_ratio",
    "min_separation",
    "convergence_time",
)

#: Samples per period of the band's top (with its margin) the automatic mode needs.
MIN_SAMPLES_PER_PERIOD = 10.0

#: The constants of the automatic design AD1-AD8 (module docstring), dimensionless.
DESIGN = {
    "p_min": 0.65,  # AD2: slowest observer pole / sqrt(omegah_1(0))
    "p_max": 1.3,  # AD2: fastest observer pole / sqrt(omegah_1(0))
    "rho_rel": 0.2,  # AD4: rho^2 = rho_rel * smoothed tr(Xi^T Xi) / n
    "kappa": 0.2,  # AD5: mu = kappa |slowest pole| / lambda_typ; no direction adapts faster
    "lambda_typ": 0.008,  # AD5: the excitation above which a direction's rate is capped
    "band_margin": 0.1,  # AD6: the clips are [f_lo (1 - m), f_hi (1 + m)]
    "separation": 0.15,  # AD6: adjacent components at least this fraction apart
    "dwell_poles": 2.0,  # AD7: dwell = this / |slowest pole|
    "recentre": 0.02,  # AD8: re-centre when some |thetah_i| exceeds this fraction of |a_i|
    "convergence_poles": 10.0,  # smoothing time of the convergence test = this / |slowest pole|
    "level_poles": 1.0,  # smoothing time of tr(Xi^T Xi) (AD4) = this / |slowest pole|
}


def auto_design(n: int, bias: bool, band_hz: tuple[float, float]) -> dict[str, Any]:
    """AD1-AD7: a, poles, F_f, B_f, omega0 (lists), mu, rho_rel, mu_a, dwell, times (floats),
    in units of ``w_ref = 2 pi f_hi``; ``w_ref`` itself in rad/s."""
    lo, hi = band_hz
    beta = lo / hi
    w0 = [beta ** (1.0 - (i + 0.5) / n) for i in range(n)]  # AD1
    nx = 2 * n + int(bias)
    anchor = math.sqrt(w0[0])  # geometric mean of the lowest initial frequency and f_hi
    p_lo, p_hi = DESIGN["p_min"] * anchor, DESIGN["p_max"] * anchor
    poles = [-p_lo * (p_hi / p_lo) ** (j / (nx - 1)) for j in range(nx)] if nx > 1 else [-p_lo]  # AD2
    slow = p_lo
    return {
        "w_ref": 2.0 * math.pi * hi,
        "a": [-w * w for w in w0],
        "poles": poles,
        "filter_poles": [-w0[j + 1] for j in range(n - 1)],  # AD3
        "filter_gains": [w0[j + 1] for j in range(n - 1)],
        "omega0": w0,
        "mu": DESIGN["kappa"] * slow / DESIGN["lambda_typ"],  # AD5
        "lambda_cap": DESIGN["lambda_typ"],
        "rho_rel": DESIGN["rho_rel"],
        "mu_a": slow / (w0[0] * w0[0]),
        "dwell": DESIGN["dwell_poles"] / slow,  # AD7
        "convergence_time": DESIGN["convergence_poles"] / slow,
        "level_time": DESIGN["level_poles"] / slow,
        "w_lo": beta * (1.0 - DESIGN["band_margin"]),  # AD6
        "w_hi": 1.0 + DESIGN["band_margin"],
    }


# packed constants of the automatic mode: ``ci`` = n, nx, nf, nz, 0, bias, 1 (the mode flag);
# ``cf`` = the scalars below, then the observer poles (nx), F_f (nf), B_f (nf).
_K_H, _K_MU, _K_RHO2, _K_MUA, _K_DHI, _K_DLO, _K_TBAR, _K_OMU = 0, 1, 2, 3, 4, 5, 6, 7
_K_MINA, _K_FADE, _K_CALPHA, _K_CTOL, _K_DELAY, _K_ZMAX, _K_LALPHA = 8, 9, 10, 11, 12, 13, 14
_K_OMLO, _K_OMHI, _K_RC, _K_SEP, _K_XIFLOOR, _K_PALPHA, _K_LCAP = 15, 16, 17, 18, 19, 20, 21
_N_K = 22
_I_MODE = 6
# the scalars of the automatic mode's state, after the per-component part
_S_CLOCK, _S_MEAN, _S_POW, _S_STARTED, _S_XI, _S_POWL = 0, 1, 2, 3, 4, 5
_N_S = 6


@kernel
def _gen_eig(G: np.ndarray, n: int) -> None:
    """``Phi v = lambda M v`` with ``M = R R^T``, on the packed ``G`` (5, n, n): ``G[0]`` Phi,
    ``G[1]`` R (lower), ``G[2]`` scratch, out: ``G[3]`` W (columns), ``G[4, 0]`` lambda
    (decreasing). ``S = R^-1 Phi R^-T`` by closed form (n = 2) or cyclic Jacobi; ``v = R^-T w``.
    One array argument: numba counts a reference per array passed (an atomic operation each)."""
    for i in range(n):  # S = R^-1 Phi (forward substitution, row by row: one division a row)
        inv = 1.0 / G[1, i, i]
        for j in range(n):
            acc = G[0, i, j]
            for k in range(i):
                acc -= G[1, i, k] * G[2, k, j]
            G[2, i, j] = acc * inv
    for j in range(n):  # S <- S R^-T (forward substitution, column by column)
        inv = 1.0 / G[1, j, j]
        for i in range(n):
            acc = G[2, i, j]
            for k in range(j):
                acc -= G[2, i, k] * G[1, j, k]
            G[2, i, j] = acc * inv
    if n == 2:  # closed form: the eigenvalues of [[a, b], [b, c]] and the rotation that diagonalises it
        a = G[2, 0, 0]
        b = 0.5 * (G[2, 0, 1] + G[2, 1, 0])
        c = G[2, 1, 1]
        half = 0.5 * (a - c)
        r = math.sqrt(half * half + b * b)
        G[4, 0, 0] = 0.5 * (a + c) + r
        G[4, 0, 1] = 0.5 * (a + c) - r
        if r == 0.0:
            cs, sn = 1.0, 0.0
        elif half >= 0.0:  # first eigenvector (cos, sin) of the larger eigenvalue
            t = b / (half + r)
            cs = 1.0 / math.sqrt(1.0 + t * t)
            sn = t * cs
        else:
            t = b / (r - half)
            sn = 1.0 / math.sqrt(1.0 + t * t)
            cs = t * sn
        G[3, 0, 0] = cs
        G[3, 1, 0] = sn
        G[3, 0, 1] = -sn
        G[3, 1, 1] = cs
        return
    for i in range(n):  # symmetric up to rounding: symmetrise, or Jacobi never meets its tolerance
        for j in range(i):
            v = 0.5 * (G[2, i, j] + G[2, j, i])
            G[2, i, j] = v
            G[2, j, i] = v
    for i in range(n):
        for j in range(n):
            G[3, i, j] = 1.0 if i == j else 0.0
    for _sweep in range(30):
        off = 0.0
        tot = 0.0
        for i in range(n):
            tot += G[2, i, i] * G[2, i, i]
            for j in range(i + 1, n):
                off += G[2, i, j] * G[2, i, j]
        if off <= 1e-30 * tot or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = G[2, p, q]
                if apq == 0.0:
                    continue
                theta = (G[2, q, q] - G[2, p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):
                    skp = G[2, k, p]
                    skq = G[2, k, q]
                    G[2, k, p] = c * skp - s * skq
                    G[2, k, q] = s * skp + c * skq
                for k in range(n):
                    spk = G[2, p, k]
                    sqk = G[2, q, k]
                    G[2, p, k] = c * spk - s * sqk
                    G[2, q, k] = s * spk + c * sqk
                for k in range(n):
                    wkp = G[3, k, p]
                    wkq = G[3, k, q]
                    G[3, k, p] = c * wkp - s * wkq
                    G[3, k, q] = s * wkp + c * wkq
    for i in range(n):
        G[4, 0, i] = G[2, i, i]
    for i in range(n):  # selection sort, decreasing
        best = i
        for j in range(i + 1, n):
            if G[4, 0, j] > G[4, 0, best]:
                best = j
        if best != i:
            tmp = G[4, 0, i]
            G[4, 0, i] = G[4, 0, best]
            G[4, 0, best] = tmp
            for k in range(n):
                tmp = G[3, k, i]
                G[3, k, i] = G[3, k, best]
                G[3, k, best] = tmp


@kernel
def _place(s: np.ndarray, oa: int, oL: int, poles: np.ndarray, n: int, bias: int) -> None:
    """L_x with eig(F_x - L_x C_x) = poles for F_x = blockdiag(J_i, 0), a = s[oa : oa + n] < 0,
    into s[oL : oL + nx]. Closed form (matrix determinant lemma): with D(s) = s^b prod(s^2 -
    a_k) and P(s) = prod(s - p_m), ``l_2i + j w_i l_2i-1 = P(j w_i) / D_i(j w_i)`` at
    ``w_i = sqrt(-a_i)``, ``D_i = D / (s^2 - a_i)``, and ``l_bias = P(0) / prod(-a_k)``."""
    nx = 2 * n + bias
    for i in range(n):
        om = -s[oa + i]
        w = math.sqrt(om)
        sj = complex(0.0, w)
        pv = complex(1.0, 0.0)
        for m in range(nx):
            pv *= sj - poles[m]
        dv = sj if bias else complex(1.0, 0.0)
        for k in range(n):
            if k != i:
                dv *= -s[oa + k] - om
        r = pv / dv
        s[oL + 2 * i + 1] = r.real
        s[oL + 2 * i] = r.imag / w
    if bias:
        p0 = 1.0
        for m in range(nx):
            p0 *= -poles[m]
        d0 = 1.0
        for k in range(n):
            d0 *= -s[oa + k]
        s[oL + nx - 1] = p0 / d0


@kernel(inline="always")
def _input_level(
    yk: float, started: float, mean: float, pw: float, pwl: float, p_alpha: float, min_a: float
) -> tuple[float, float, float, float, bool]:
    """AD4 and AD7's input level, one sample: (started, mean, AC power, its slow mean, present).
    The signal is present above ``min_a`` and above a quarter of its power over ten times as
    long (a signal that stops is absent within ~1.4 periods of omegah_1(0)). Scalars only, so
    every kernel inlines it without reference counting."""
    if started == 0.0:
        started = 1.0
        mean = yk
    mean += p_alpha * (yk - mean)
    dy = yk - mean
    pw += p_alpha * (dy * dy - pw)
    pwl += 0.1 * p_alpha * (dy * dy - pwl)
    return started, mean, pw, pwl, 2.0 * pw >= min_a * min_a and pw >= 0.25 * pwl


@kernel(inline="always")
def _frequency_and_phase(om: float, x1: float, cph: float, h: float, om_u: float) -> tuple[float, float]:
    """(8) and (10) for one component from ``Omegah = om > 0``: the frequency in Hz of the sampled
    oscillator, omega_d from ``2 sin(omega_d h / 2) = h sqrt(Omegah)``, and the phase from
    ``x_{2i-1} = A sin(phi)`` and ``cph = A cos(phi) sin(omega_d h)``."""
    cd = 1.0 - 0.5 * h * h * om  # cos(omega_d h)
    wd = 2.0 / h * math.asin(min(0.5 * h * math.sqrt(om), 1.0))
    return wd * om_u / (2.0 * math.pi), math.atan2(x1, cph / math.sqrt(max(1.0 - cd * cd, 1e-300)))


@kernel(inline="always")
def _component_outputs(
    om: float, x1: float, x2: float, A: float, wb: float, dv: float, h: float, mu_a: float, c_alpha: float,
    c_tol: float,
) -> tuple[bool, float, float, float, float, bool]:  # fmt: skip
    """One component's outputs at t_k from ``Omegah = om``, ``x_{2i-1} = x1``, ``x_{2i} = x2``:
    (ok: om > 0, A cos(phi) sin(omega_d h) for (10), A (9)/(11), smoothed Omegah, its smoothed
    deviation, settled: deviation within 2 convergence_tol). Scalars: inlined, no reference counts."""
    if not om > 0.0:
        return False, 0.0, A, wb, dv, False
    cd = 1.0 - 0.5 * h * h * om  # cos(omega_d h)
    sd2 = max(1.0 - cd * cd, 1e-300)  # sin^2(omega_d h)
    num = h * x2 + x1 * (1.0 - cd)  # A cos(phi) sin(omega_d h)
    A += min(h * mu_a * om, 1.0) * (math.sqrt(x1 * x1 + num * num / sd2) - A)  # (9), (11)
    wb += c_alpha * (om - wb)
    dv += c_alpha * (abs(om - wb) - dv)
    return True, num, A, wb, dv, dv <= 2.0 * c_tol * wb


@kernel
def auto_kernel(
    y: np.ndarray, state: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """The automatic mode over block ``y`` from ``state``: ``(out, extras, sse, new_state)``,
    columns as :func:`adaptive_multisine_kernel`. One symplectic-Euler step of (12), (16),
    (17), (19)-(22) and (11) per sample. ``M = L D L^T`` (no square root) serves the law (22)
    while every direction is on, and the excitation test (23)-(25) is then the sign of the
    pivots of ``Phi_Xi - delta_low M`` (positive definite: every lambda_i >= delta_low, all
    stay on); otherwise the generalised eigen-decomposition on ``R = L D^(1/2)``. No compiled
    helper taking arrays is called per sample: numba counts a reference (an atomic operation)
    per array passed, which cost about 20 % of the loop."""
    n, nx, nf, nz, bias = ci[0], ci[1], ci[2], ci[3], ci[5]
    h = cf[_K_H]
    mu, rho2rel, mu_a = cf[_K_MU], cf[_K_RHO2], cf[_K_MUA]
    d_hi, d_lo, tbar = cf[_K_DHI], cf[_K_DLO], cf[_K_TBAR]
    om_u, min_a, fade = cf[_K_OMU], cf[_K_MINA], cf[_K_FADE]
    c_alpha, c_tol, delay, zmax, l_alpha = cf[_K_CALPHA], cf[_K_CTOL], cf[_K_DELAY], cf[_K_ZMAX], cf[_K_LALPHA]
    oFf = _N_K + nx
    oBf = oFf + nf
    oz = nf
    oxi = oz + nz
    oth = oxi + nz * n
    oA = oth + n
    ops = oA + n
    owb = ops + n
    odv = owb + n
    osc = odv + n
    oa_c = osc + _N_S  # a (n), re-centred (AD8)
    oL = oa_c + n  # L_x (nx), re-placed with a
    om_lo, om_hi, rc, sep = cf[_K_OMLO], cf[_K_OMHI], cf[_K_RC], cf[_K_SEP]
    xi_floor = cf[_K_XIFLOOR]
    p_alpha = cf[_K_PALPHA]
    lcap = cf[_K_LCAP]
    poles = cf[_N_K : _N_K + nx]
    s = state.copy()
    nrow = 1 if last_only else y.shape[0]
    out = np.empty((nrow, 3 * n + 2))
    ext = np.empty((nrow, 3 * n + 2))
    cx = np.empty((n, n))  # C_z Xi
    M = np.empty((n, n))
    T = np.empty((n, n))
    L = np.zeros((n, n))  # M = L D L^T, L unit lower
    D = np.empty(n)
    Dinv = np.empty(n)
    # the generalised eigen-problem's packed arrays (one argument for _gen_eig): Phi_Xi, R, scratch,
    # W, lambda; views made once per block (in the loop each would count a reference)
    G = np.zeros((5, n, n))
    Phi = G[0]
    R = G[1]
    W = G[3]
    lam = G[4, 0]
    ev = np.empty(n)  # C_z zh - eta
    g = np.empty(n)
    q = np.empty(n)
    td = np.empty(n)  # thetah'
    xo = np.empty(n)  # new x_{2i-1} of zh
    dz = np.empty(nz)
    two_pi = 2.0 * math.pi
    tb2 = tbar * tbar
    sse = 0.0
    nsamp = y.shape[0]
    for k in range(nsamp):
        yk = y[k]
        write = (not last_only) or k == nsamp - 1
        j = 0 if last_only else k
        # AD4: smoothed mean and AC power of the input; AD7: is the signal present
        s[osc + _S_STARTED], s[osc + _S_MEAN], s[osc + _S_POW], s[osc + _S_POWL], present = _input_level(
            yk, s[osc + _S_STARTED], s[osc + _S_MEAN], s[osc + _S_POW], s[osc + _S_POWL], p_alpha, min_a
        )
        # output error C_z zh - eta (16), (22)
        c = s[oz + nx - 1] if bias else 0.0
        for i in range(n):
            c += s[oz + 2 * i]
        ev[0] = c - yk
        sse += ev[0] * ev[0]
        for jj in range(1, n):
            ev[jj] = s[oz + nx + jj - 1] - s[jj - 1]
        # C_z Xi, M = Xi^T Xi + rho^2 I, Phi_Xi = (C_z Xi)^T C_z Xi (23)
        for i in range(n):
            b = oxi + i * nz
            acc = s[b + nx - 1] if bias else 0.0
            for r in range(n):
                acc += s[b + 2 * r]
            cx[0, i] = acc
            for jj in range(1, n):
                cx[jj, i] = s[b + nx + jj - 1]
        for i in range(n):
            bi = oxi + i * nz
            for i2 in range(i + 1):
                bj = oxi + i2 * nz
                acc = 0.0
                for r in range(nz):
                    acc += s[bi + r] * s[bj + r]
                M[i, i2] = acc
                acc = 0.0
                for r in range(n):
                    acc += cx[r, i] * cx[r, i2]
                Phi[i, i2] = acc
                Phi[i2, i] = acc
        # AD4: rho^2 relative to the smoothed size of Xi, floored
        tr = 0.0
        for i in range(n):
            tr += M[i, i]
        # (the smoothed size up to the previous sample: this sample's joins the smoother after,
        # so that the kernels written out for n = 1, 2 know rho^2 before they know M)
        rho2 = rho2rel * max(s[osc + _S_XI], xi_floor)
        s[osc + _S_XI] += l_alpha * (tr / n - s[osc + _S_XI])
        for i in range(n):
            M[i, i] += rho2
        # M = L D L^T (no square root, one division per pivot); M >= rho^2 I guards rounding.
        # Written out here: a compiled helper taking arrays costs atomic reference counts per call
        for jj in range(n):
            d = M[jj, jj]
            for kk in range(jj):
                d -= L[jj, kk] * L[jj, kk] * D[kk]
            d = max(d, rho2)
            D[jj] = d
            inv = 1.0 / d
            Dinv[jj] = inv
            for i in range(jj + 1, n):
                acc = M[i, jj]
                for kk in range(jj):
                    acc -= L[i, kk] * L[jj, kk] * D[kk]
                L[i, jj] = acc * inv
        # (25): while every psi_i is on, all stay on iff T = Phi_Xi - delta_low M > 0, i.e. every
        # pivot of its L D L^T is positive (T, overwritten by the elimination, holds them)
        n_on = 0
        for i in range(n):
            if s[ops + i] != 0.0:
                n_on += 1
        fast = False
        if n_on == n:
            for i in range(n):
                for i2 in range(i + 1):
                    T[i, i2] = Phi[i, i2] - d_lo * M[i, i2]
            fast = True
            for jj in range(n):
                d = T[jj, jj]
                if not d > 0.0:
                    fast = False
                    break
                if jj < n - 1:
                    inv = 1.0 / d
                    for i in range(jj + 1, n):
                        f = T[i, jj] * inv
                        for i2 in range(jj + 1, i + 1):
                            T[i, i2] -= f * T[i2, jj]
        # AD5: every lambda_i <= tr(M^-1 Phi_Xi) = sum_r |D^-1/2 L^-1 (C_z Xi)^T e_r|^2; above
        # lambda_cap the law (22) runs on the eigen-decomposition, each rate capped (below)
        lsum = 0.0
        for r in range(n):
            for i in range(n):
                acc = cx[r, i]
                for kk in range(i):
                    acc -= L[i, kk] * q[kk]
                q[i] = acc
                lsum += acc * acc * Dinv[i]
        capped = lsum > lcap
        if not fast or write or capped:
            for jj in range(n):  # the Cholesky factor R = L D^(1/2) of M
                rj = math.sqrt(D[jj])
                R[jj, jj] = rj
                for i in range(jj + 1, n):
                    R[i, jj] = L[i, jj] * rj
            _gen_eig(G, n)
        if not fast:
            n_on = 0
            for i in range(n):
                if lam[i] >= d_hi:
                    s[ops + i] = 1.0
                elif lam[i] < d_lo:
                    s[ops + i] = 0.0
                if s[ops + i] != 0.0:
                    n_on += 1
        # AD7: settling dwell from the start and from the signal's return; while the signal is
        # absent nothing adapts on the observer's free response, and the convergence test
        # starts over (its smoothed deviation is reset to 100 %). Not re-armed by a total
        # dis-excitation: with one component lambda_1 passes zero twice a period.
        if not present:
            for i in range(n):
                s[odv + i] = abs(s[owb + i])
            s[osc + _S_CLOCK] = 0.0
        else:
            s[osc + _S_CLOCK] = min(s[osc + _S_CLOCK] + h, delay)
        adapting = s[osc + _S_CLOCK] >= delay and n_on > 0
        # (22) thetah'_unc = -mu V Psi V^T Xi^T C_z^T e, V V^T = M^-1
        for i in range(n):
            td[i] = 0.0
        if adapting:
            for i in range(n):  # g = (C_z Xi)^T e
                acc = 0.0
                for r in range(n):
                    acc += cx[r, i] * ev[r]
                g[i] = acc
            if n_on == n and not capped:  # td = M^-1 g = L^-T D^-1 L^-1 g
                for i in range(n):
                    acc = g[i]
                    for kk in range(i):
                        acc -= L[i, kk] * q[kk]
                    q[i] = acc
                for i in range(n - 1, -1, -1):
                    acc = q[i] * Dinv[i]
                    for kk in range(i + 1, n):
                        acc -= L[kk, i] * td[kk]
                    td[i] = acc
            else:  # td = R^-T W Psi W^T R^-1 g
                for i in range(n):  # q = R^-1 g
                    acc = g[i]
                    for kk in range(i):
                        acc -= R[i, kk] * q[kk]
                    q[i] = acc / R[i, i]
                for i in range(n):  # q <- W Psi W^T q
                    acc = 0.0
                    for kk in range(n):
                        acc += W[kk, i] * q[kk]
                    g[i] = acc * s[ops + i]
                    if lam[i] > lcap:  # AD5: rate mu lambda_i capped at mu lambda_typ = kappa |p|
                        g[i] *= lcap / lam[i]
                for i in range(n):
                    acc = 0.0
                    for kk in range(n):
                        acc += W[i, kk] * g[kk]
                    q[i] = acc
                for i in range(n - 1, -1, -1):  # R^-T q
                    acc = q[i]
                    for kk in range(i + 1, n):
                        acc -= R[kk, i] * td[kk]
                    td[i] = acc / R[i, i]
            tt = 0.0
            tu = 0.0
            for i in range(n):
                td[i] *= -mu
                tt += s[oth + i] * s[oth + i]
                tu += s[oth + i] * td[i]
            if tt >= tb2 and tu > 0.0:  # projection (19)-(21)
                for i in range(n):
                    td[i] -= s[oth + i] * tu / tb2
            for i in range(n):  # AD6: the band's clips (Remark 3.1)
                om2 = s[oth + i] - s[oa_c + i]
                if (om2 <= om_lo and td[i] < 0.0) or (om2 >= om_hi and td[i] > 0.0):
                    td[i] = 0.0
            for i in range(n - 1):  # AD6: the components stay ordered and apart
                lo2 = s[oth + i] - s[oa_c + i]
                hi2 = s[oth + i + 1] - s[oa_c + i + 1]
                if hi2 <= lo2 * sep and td[i + 1] < td[i]:
                    mid = 0.5 * (td[i] + td[i + 1])
                    td[i] = mid
                    td[i + 1] = mid
        # outputs at t_k, (8)-(10) with the sampled-oscillator relations; (11); convergence
        amax = 0.0
        for i in range(n):
            amax = max(amax, s[oA + i])
        thr = max(fade * amax, min_a)
        all_ok = adapting and present
        for i in range(n):
            om2 = s[oth + i] - s[oa_c + i]
            x1 = s[oz + 2 * i]
            x2 = s[oz + 2 * i + 1]
            ok = om2 > 0.0
            if ok:
                cd = 1.0 - 0.5 * h * h * om2  # cos(omega_d h)
                sd2 = max(1.0 - cd * cd, 1e-300)  # sin^2(omega_d h)
                num = h * x2 + x1 * (1.0 - cd)  # A cos(phi) sin(omega_d h)
                ainst = math.sqrt(x1 * x1 + num * num / sd2)
                s[oA + i] += min(h * mu_a * om2, 1.0) * (ainst - s[oA + i])  # (11)
                s[owb + i] += c_alpha * (om2 - s[owb + i])
                s[odv + i] += c_alpha * (abs(om2 - s[owb + i]) - s[odv + i])
                if not s[odv + i] <= 2.0 * c_tol * s[owb + i]:
                    all_ok = False
            else:
                all_ok = False
            faded = not s[oA + i] >= thr
            if faded:
                all_ok = False
            if write:
                if ok and not faded:
                    wd = 2.0 / h * math.asin(min(0.5 * h * math.sqrt(om2), 1.0))
                    out[j, i] = wd * om_u / two_pi
                    out[j, 2 * n + i] = math.atan2(x1, num / math.sqrt(sd2))
                else:
                    out[j, i] = math.nan
                    out[j, 2 * n + i] = math.nan
                out[j, n + i] = s[oA + i] if ok else math.nan
                ext[j, i] = lam[i]
                ext[j, n + i] = s[ops + i]
                ext[j, 2 * n + i] = 1.0 if faded else 0.0
        for i in range(n):  # two components on one line are not a converged estimate
            for i2 in range(i + 1, n):
                if not abs(s[owb + i] - s[owb + i2]) > 2.0 * c_tol * max(s[owb + i], s[owb + i2]):
                    all_ok = False
        if write:
            out[j, 3 * n] = s[oz + nx - 1] if bias else 0.0
            out[j, 3 * n + 1] = 1.0 if all_ok else 0.0
            ext[j, 3 * n] = 1.0 if present else 0.0
        # ---- step to t_{k+1}: (16) zh, with Xi thetah' from the current Xi
        any_td = False
        for i in range(n):
            if td[i] != 0.0:
                any_td = True
        for r in range(nz):
            dz[r] = 0.0
        if any_td:
            for i in range(n):
                b = oxi + i * nz
                for r in range(nz):
                    dz[r] += s[b + r] * td[i]
        inj = yk - c  # L (eta - C_z zh): L acts on the first output only
        for i in range(n):
            r = oz + 2 * i
            x1 = s[r] + h * (s[r + 1] + s[oL + 2 * i] * inj + dz[2 * i])
            s[r + 1] += h * ((s[oa_c + i] - s[oth + i]) * x1 + s[oL + 2 * i + 1] * inj + dz[2 * i + 1])
            s[r] = x1
            xo[i] = x1
        if bias:
            s[oz + nx - 1] += h * (s[oL + nx - 1] * inj + dz[nx - 1])
        for jj in range(nf):
            r = oz + nx + jj
            s[r] += h * (cf[oBf + jj] * c + cf[oFf + jj] * s[r] + dz[nx + jj])
        # (17) xi_i' = A_L xi_i + G_z_i(zh), G_z_i = -x_{2i-1} e_{2i}
        for i in range(n):
            b = oxi + i * nz
            cv = cx[0, i]
            for m in range(n):
                r = b + 2 * m
                x1 = s[r] + h * (s[r + 1] - s[oL + 2 * m] * cv)
                s[r + 1] += h * (s[oa_c + m] * x1 - s[oL + 2 * m + 1] * cv)
                s[r] = x1
            s[b + 2 * i + 1] -= h * xo[i]
            if bias:
                s[b + nx - 1] -= h * s[oL + nx - 1] * cv
            for jj in range(nf):
                r = b + nx + jj
                s[r] += h * (cf[oBf + jj] * cv + cf[oFf + jj] * s[r])
        # (12) the measured output's filter
        for jj in range(nf):
            s[jj] += h * (cf[oFf + jj] * s[jj] + cf[oBf + jj] * yk)
        # (19): thetah, kept in the band's clips and the ball
        for i in range(n):  # as Omegah_i, ordered, apart, inside the band (AD6)
            q[i] = s[oth + i] + h * td[i] - s[oa_c + i]
        q[0] = max(q[0], om_lo)
        for i in range(1, n):
            q[i] = max(q[i], q[i - 1] * sep)
        q[n - 1] = min(q[n - 1], om_hi)
        for i in range(n - 2, -1, -1):
            q[i] = min(q[i], q[i + 1] / sep)
        tt = 0.0
        far = False
        for i in range(n):
            s[oth + i] = s[oa_c + i] + q[i]
            tt += s[oth + i] * s[oth + i]
            if abs(s[oth + i]) > rc * abs(s[oa_c + i]):
                far = True
        if tt > tb2:
            f = tbar / math.sqrt(tt)
            for i in range(n):
                s[oth + i] *= f
        # AD8: re-centre a on the estimates and re-place L_x there (thetah -> 0)
        if far:
            for i in range(n):
                s[oa_c + i] -= s[oth + i]
                s[oth + i] = 0.0
            _place(s, oa_c, oL, poles, n, bias)
        # guard (D7 of the explicit mode): a frozen observer far from the truth can be
        # unstable; restart it from zero, thetah kept
        lim = zmax * (1.0 + abs(s[osc + _S_MEAN]) + math.sqrt(s[osc + _S_POW]))
        bad = False
        for r in range(oz, oxi):
            if not abs(s[r]) <= lim:  # also catches NaN
                bad = True
        if not abs(tr) < math.inf:  # tr(Xi^T Xi) of this sample: Xi finite
            bad = True
        if bad:
            for r in range(oth):
                s[r] = 0.0
            for i in range(n):
                if not abs(s[oth + i]) <= tbar:
                    s[oth + i] = 0.0
                s[ops + i] = 0.0
            s[osc + _S_CLOCK] = 0.0
        if write:
            ext[j, 3 * n + 1] = 1.0 if bad else 0.0
    return out, ext, sse, s


@kernel(inline="always")
def _place_one(om: float, dk: float, poles: np.ndarray, bias: int) -> tuple[float, float]:
    """:func:`_place` for one component, ``(l_2i-1, l_2i)`` from ``Omega_i = -a_i`` and ``dk``, the
    product of ``Omega_k - Omega_i`` over the other components (1 for n = 1): ``l_2i + j w_i
    l_2i-1 = P(j w_i) / D_i(j w_i)``. Inlined into :func:`auto_kernel_n1` and
    :func:`auto_kernel_n2`, so that a re-placement (AD8) calls nothing."""
    w = math.sqrt(om)
    sj = complex(0.0, w)
    pv = complex(1.0, 0.0)
    for m in range(poles.shape[0]):
        pv *= sj - poles[m]
    dv = sj if bias else complex(1.0, 0.0)
    dv *= dk
    r = pv / dv
    return r.imag / w, r.real


@kernel
def auto_kernel_n1(
    y: np.ndarray, state: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """:func:`auto_kernel` written out for n = 1, as :func:`auto_kernel_n2` for two: the state in
    locals, no output filter (n_f = 0), ``M`` and ``Phi_Xi`` scalars, so ``lambda_1 = Phi_Xi / M``
    (23) and (25) compares ``Phi_Xi`` with ``delta M``. Agrees with :func:`auto_kernel` to
    rounding (tests/test_adaptive_multisine_small_n.py)."""
    nx, bias = ci[1], ci[5]
    h = cf[_K_H]
    mu, rho2rel, mu_a = cf[_K_MU], cf[_K_RHO2], cf[_K_MUA]
    d_hi, d_lo, tbar = cf[_K_DHI], cf[_K_DLO], cf[_K_TBAR]
    om_u, min_a, fade = cf[_K_OMU], cf[_K_MINA], cf[_K_FADE]
    c_alpha, c_tol, delay, zmax, l_alpha = cf[_K_CALPHA], cf[_K_CTOL], cf[_K_DELAY], cf[_K_ZMAX], cf[_K_LALPHA]
    om_lo, om_hi, rc = cf[_K_OMLO], cf[_K_OMHI], cf[_K_RC]
    xi_floor, p_alpha, lcap = cf[_K_XIFLOOR], cf[_K_PALPHA], cf[_K_LCAP]
    poles = cf[_N_K : _N_K + nx]
    # offsets as in auto_kernel (nf = 0, nz = nx)
    oz = 0
    oxi = nx
    oth = 2 * nx
    oA, ops, owb, odv = oth + 1, oth + 2, oth + 3, oth + 4
    osc = oth + 5
    oa_c = osc + _N_S
    oL = oa_c + 1
    s = state.copy()
    # ---- the state as locals: zh = [x_1, x_2, A0], xi_1 likewise (17)
    z1, z2 = s[oz], s[oz + 1]
    z0 = s[oz + 2] if bias else 0.0
    p1, p2 = s[oxi], s[oxi + 1]
    p0 = s[oxi + 2] if bias else 0.0
    th1, A1, ps1, wb1, dv1 = s[oth], s[oA], s[ops], s[owb], s[odv]
    clock, mean, pw, started, sxi, pwl = (
        s[osc + _S_CLOCK],
        s[osc + _S_MEAN],
        s[osc + _S_POW],
        s[osc + _S_STARTED],
        s[osc + _S_XI],
        s[osc + _S_POWL],
    )
    a1 = s[oa_c]
    L1, L2 = s[oL], s[oL + 1]
    L0 = s[oL + 2] if bias else 0.0
    nrow = 1 if last_only else y.shape[0]
    out = np.empty((nrow, 5))
    ext = np.empty((nrow, 5))
    cph = np.empty(nrow)  # A_1 cos(phi_1) sin(omega_d h) per row, for (10)
    tb2 = tbar * tbar
    sse = 0.0
    nsamp = y.shape[0]
    for k in range(nsamp):
        yk = y[k]
        write = (not last_only) or k == nsamp - 1
        j = 0 if last_only else k
        # AD4: smoothed mean and AC power of the input; AD7: is the signal present
        started, mean, pw, pwl, present = _input_level(yk, started, mean, pw, pwl, p_alpha, min_a)
        # output error C_z zh - eta (16), (22)
        c = z0 + z1
        e0 = c - yk
        sse += e0 * e0
        # C_z Xi, M = Xi^T Xi + rho^2 (AD4), Phi_Xi = (C_z Xi)^2 (23)
        c01 = p0 + p1
        tr = p1 * p1 + p2 * p2 + p0 * p0
        rho2 = rho2rel * max(sxi, xi_floor)  # (as auto_kernel: the smoothed size before this sample)
        sxi += l_alpha * (tr - sxi)
        M11 = tr + rho2
        P11 = c01 * c01
        # (25) on lambda_1 = Phi_Xi / M >= delta iff Phi_Xi >= delta M
        if P11 >= d_hi * M11:
            ps1 = 1.0
        elif P11 < d_lo * M11:
            ps1 = 0.0
        # AD7: settling dwell, as in auto_kernel
        if not present:
            dv1 = abs(wb1)
            clock = 0.0
        else:
            clock = min(clock + h, delay)
        adapting = clock >= delay and ps1 != 0.0
        # (22) thetah'_unc = -mu M^-1 Xi^T C_z^T e; AD5: above lambda_cap the rate mu lambda_1 is
        # capped at mu lambda_cap, i.e. M^-1 becomes lambda_cap / Phi_Xi
        td1 = 0.0
        if adapting:
            if P11 > lcap * M11:
                td1 = -mu * lcap * c01 * e0 / P11
            else:
                td1 = -mu * c01 * e0 / M11
            tu = th1 * td1
            if th1 * th1 >= tb2 and tu > 0.0:  # projection (19)-(21)
                td1 -= th1 * tu / tb2
            om1 = th1 - a1  # AD6: the band's clips (Remark 3.1)
            if (om1 <= om_lo and td1 < 0.0) or (om1 >= om_hi and td1 > 0.0):
                td1 = 0.0
        # outputs at t_k, (8)-(10) with the sampled-oscillator relations; (11); convergence
        thr = max(fade * max(0.0, A1), min_a)
        all_ok = adapting and present
        om1 = th1 - a1
        ok1, num1, A1, wb1, dv1, settled = _component_outputs(om1, z1, z2, A1, wb1, dv1, h, mu_a, c_alpha, c_tol)
        all_ok = all_ok and settled
        faded1 = not A1 >= thr
        if faded1:
            all_ok = False
        if write:  # Omegah_1, x_1 and A cos(phi) sin(omega_d h): (8), (10) after the loop
            out[j, 0] = om1 if ok1 and not faded1 else math.nan
            out[j, 2] = z1
            cph[j] = num1
            out[j, 1] = A1 if ok1 else math.nan
            out[j, 3] = z0 if bias else 0.0
            out[j, 4] = 1.0 if all_ok else 0.0
            ext[j, 0] = P11 / M11
            ext[j, 1] = ps1
            ext[j, 2] = 1.0 if faded1 else 0.0
            ext[j, 3] = 1.0 if present else 0.0
        # ---- step to t_{k+1}: (16) zh, with Xi thetah' from the current Xi
        inj = yk - c  # L (eta - C_z zh)
        x1 = z1 + h * (z2 + L1 * inj + p1 * td1)
        z2 += h * ((a1 - th1) * x1 + L2 * inj + p2 * td1)
        z1 = x1
        if bias:
            z0 += h * (L0 * inj + p0 * td1)
        # (17) xi_1' = A_L xi_1 + G_z_1(zh), G_z_1 = -x_1 e_2
        xx = p1 + h * (p2 - L1 * c01)
        p2 += h * (a1 * xx - L2 * c01)
        p2 -= h * x1
        p1 = xx
        if bias:
            p0 -= h * L0 * c01
        # (19): thetah, kept in the band's clips (AD6), and by them in the ball (as in auto_kernel_n2)
        th1 = a1 + min(max(th1 + h * td1 - a1, om_lo), om_hi)
        # AD8: re-centre a on the estimate and re-place L_x there (thetah -> 0)
        if abs(th1) > rc * abs(a1):
            a1 -= th1
            th1 = 0.0
            L1, L2 = _place_one(-a1, 1.0, poles, bias)  # as _place, written out for n = 1
            if bias:
                pz = 1.0  # P(0)
                for m in range(nx):
                    pz *= -poles[m]
                L0 = pz / -a1
        # guard (D7 of the explicit mode): restart a diverged observer from zero, thetah kept
        lim = zmax * (1.0 + abs(mean))  # the bound without sqrt(AC power): the common case
        bad = not (abs(z1) <= lim and abs(z2) <= lim and abs(z0) <= lim)
        if bad:  # also NaN; then the full bound
            lim = zmax * (1.0 + abs(mean) + math.sqrt(pw))
            bad = not (abs(z1) <= lim and abs(z2) <= lim and abs(z0) <= lim)
        if not abs(tr) < math.inf:  # tr(Xi^T Xi) of this sample: Xi finite
            bad = True
        if bad:
            z1 = z2 = z0 = 0.0
            p1 = p2 = p0 = 0.0
            if not abs(th1) <= tbar:
                th1 = 0.0
            ps1 = 0.0
            clock = 0.0
        if write:
            ext[j, 4] = 1.0 if bad else 0.0
    # (8) omega_d from 2 sin(omega_d h / 2) = h sqrt(Omegah), (10) the phase: after the loop, so that
    # the loop calls no library function
    for j in range(nrow):
        om = out[j, 0]
        if om == om:  # not NaN: present, not faded
            out[j, 0], out[j, 2] = _frequency_and_phase(om, out[j, 2], cph[j], h, om_u)
        else:
            out[j, 2] = math.nan
    # ---- the locals back into the new state
    s[oz], s[oz + 1], s[oxi], s[oxi + 1] = z1, z2, p1, p2
    if bias:
        s[oz + 2], s[oxi + 2], s[oL + 2] = z0, p0, L0
    s[oth], s[oA], s[ops], s[owb], s[odv] = th1, A1, ps1, wb1, dv1
    s[osc + _S_CLOCK], s[osc + _S_MEAN], s[osc + _S_POW] = clock, mean, pw
    s[osc + _S_STARTED], s[osc + _S_XI], s[osc + _S_POWL] = started, sxi, pwl
    s[oa_c], s[oL], s[oL + 1] = a1, L1, L2
    return out, ext, sse, s


@kernel
def auto_kernel_n2(
    y: np.ndarray, state: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """:func:`auto_kernel` written out for n = 2 (the paper's examples and the bench's): the same
    steps on the same state layout, every state variable a local for the whole block (written
    back at its end) and every 2 x 2 product spelt out, so that the compiler keeps them in
    registers instead of a chain of loads and stores through ``s``. The generalised eigenvalues
    of (23) come in closed form each sample (one square root), so (25) needs no pivot test, and
    the law (22) with one direction on or capped takes the projector onto the first eigenvector
    in closed form instead of the eigenvector; products are fused (:func:`fma`), and the ball
    rescaling of thetah, which the band's clips make inactive, is left out. Agrees with
    :func:`auto_kernel` to rounding (tests/test_adaptive_multisine_small_n.py). With
    ``bias=False`` the A0 state, its sensitivities and its gain are held at zero, which adds exact
    zeros."""
    n, nx, bias = 2, ci[1], ci[5]
    h = cf[_K_H]
    mu, rho2rel, mu_a = cf[_K_MU], cf[_K_RHO2], cf[_K_MUA]
    d_hi, d_lo, tbar = cf[_K_DHI], cf[_K_DLO], cf[_K_TBAR]
    om_u, min_a, fade = cf[_K_OMU], cf[_K_MINA], cf[_K_FADE]
    c_alpha, c_tol, delay, zmax, l_alpha = cf[_K_CALPHA], cf[_K_CTOL], cf[_K_DELAY], cf[_K_ZMAX], cf[_K_LALPHA]
    om_lo, om_hi, rc, sep = cf[_K_OMLO], cf[_K_OMHI], cf[_K_RC], cf[_K_SEP]
    xi_floor, p_alpha, lcap = cf[_K_XIFLOOR], cf[_K_PALPHA], cf[_K_LCAP]
    Ff = cf[_N_K + nx]  # F_f and B_f of (12), n_f = 1
    Bf = cf[_N_K + nx + 1]
    poles = cf[_N_K : _N_K + nx]
    # offsets as in auto_kernel (nf = 1, nz = nx + 1)
    nz = nx + 1
    oz = 1
    oxi = oz + nz
    oth = oxi + 2 * nz
    oA, ops, owb, odv = oth + 2, oth + 4, oth + 6, oth + 8
    osc = oth + 10
    oa_c = osc + _N_S
    oL = oa_c + 2
    s = state.copy()
    # ---- the state as locals: yf (12); zh = [x_1 .. x_4, A0, yfh]; xi_1, xi_2 likewise (17)
    yf = s[0]
    z1, z2, z3, z4 = s[oz], s[oz + 1], s[oz + 2], s[oz + 3]
    z0 = s[oz + 4] if bias else 0.0
    zf = s[oz + nx]
    p1, p2, p3, p4 = s[oxi], s[oxi + 1], s[oxi + 2], s[oxi + 3]
    p0 = s[oxi + 4] if bias else 0.0
    pf = s[oxi + nx]
    b = oxi + nz
    q1, q2, q3, q4 = s[b], s[b + 1], s[b + 2], s[b + 3]
    q0 = s[b + 4] if bias else 0.0
    qf = s[b + nx]
    th1, th2 = s[oth], s[oth + 1]
    A1, A2 = s[oA], s[oA + 1]
    ps1, ps2 = s[ops], s[ops + 1]
    wb1, wb2 = s[owb], s[owb + 1]
    dv1, dv2 = s[odv], s[odv + 1]
    clock, mean, pw, started, sxi, pwl = (
        s[osc + _S_CLOCK],
        s[osc + _S_MEAN],
        s[osc + _S_POW],
        s[osc + _S_STARTED],
        s[osc + _S_XI],
        s[osc + _S_POWL],
    )
    a1, a2 = s[oa_c], s[oa_c + 1]
    L1, L2, L3, L4 = s[oL], s[oL + 1], s[oL + 2], s[oL + 3]
    L0 = s[oL + 4] if bias else 0.0
    nrow = 1 if last_only else y.shape[0]
    out = np.empty((nrow, 3 * n + 2))
    ext = np.empty((nrow, 3 * n + 2))
    cph = np.empty((nrow, 2))  # A_i cos(phi_i) sin(omega_d h) per row, for (10)
    tb2 = tbar * tbar
    itb2 = 1.0 / tb2
    isep = 1.0 / sep
    sse = 0.0
    nsamp = y.shape[0]
    for k in range(nsamp):
        yk = y[k]
        write = (not last_only) or k == nsamp - 1
        j = 0 if last_only else k
        # AD4: smoothed mean and AC power of the input; AD7: is the signal present
        started, mean, pw, pwl, present = _input_level(yk, started, mean, pw, pwl, p_alpha, min_a)
        # output error C_z zh - eta (16), (22)
        c = z0 + z1 + z3
        e0 = c - yk
        sse += e0 * e0
        e1 = zf - yf
        # C_z Xi (rows: y, yf), M = Xi^T Xi + rho^2 I, Phi_Xi = (C_z Xi)^T C_z Xi (23)
        c01 = p0 + p1 + p3
        c02 = q0 + q1 + q3
        # The loop's speed is the latency of its critical path: from thetah' through zh (16) to the
        # x_2 of xi_1 and the x_4 of xi_2 (17), the only entries of Xi that wait on this step's
        # law, then through M to the law (22) of the next. So those two enter M last, each
        # product is added by a fused multiply-add, and rho^2 is known before M is.
        # AD4: rho^2 relative to the smoothed size of Xi up to the previous sample, floored
        rho2 = rho2rel * max(sxi, xi_floor)
        m11 = fma(p1, p1, p3 * p3) + fma(p4, p4, fma(p0, p0, pf * pf))
        m22 = fma(q1, q1, q2 * q2) + fma(q3, q3, fma(q0, q0, qf * qf))
        M11 = fma(p2, p2, m11 + rho2)
        M21 = fma(q4, p4, fma(q2, p2, fma(q1, p1, fma(q3, p3, fma(q0, p0, qf * pf)))))
        M22 = fma(q4, q4, m22 + rho2)
        P11 = fma(c01, c01, pf * pf)
        P21 = fma(c02, c01, qf * pf)
        P22 = fma(c02, c02, qf * qf)
        tr = M11 + M22  # with rho^2: finite iff Xi is (the guard)
        sxi += l_alpha * (0.5 * fma(p2, p2, fma(q4, q4, m11 + m22)) - sxi)  # this sample's tr(Xi^T Xi) / 2
        # (25) without the eigenvalues: lambda_2 >= delta iff T = Phi_Xi - delta M >= 0 (T_11, T_22,
        # det T >= 0), lambda_1 < delta iff T < 0 (T_11 < 0 < det T): no division, no root
        t11 = P11 - d_hi * M11
        t22 = P22 - d_hi * M22
        t21 = P21 - d_hi * M21
        det_t = t11 * t22 - t21 * t21
        if not (t11 < 0.0 and det_t > 0.0):  # lambda_1 >= delta_high
            ps1 = 1.0
        if t11 >= 0.0 and t22 >= 0.0 and det_t >= 0.0:  # lambda_2 >= delta_high
            ps2 = 1.0
        t11 = P11 - d_lo * M11
        t22 = P22 - d_lo * M22
        t21 = P21 - d_lo * M21
        det_t = t11 * t22 - t21 * t21
        if t11 < 0.0 and det_t > 0.0:  # lambda_1 < delta_low
            ps1 = 0.0
        if not (t11 >= 0.0 and t22 >= 0.0 and det_t >= 0.0):  # lambda_2 < delta_low
            ps2 = 0.0
        n_on = int(ps1 != 0.0) + int(ps2 != 0.0)
        # AD7: settling dwell, as in auto_kernel
        if not present:
            dv1 = abs(wb1)
            dv2 = abs(wb2)
            clock = 0.0
        else:
            clock = min(clock + h, delay)
        adapting = clock >= delay and n_on > 0
        # the eigenvalues themselves (an output, and the law with one direction on or a rate
        # capped), (23)-(24) in closed form: det(Phi_Xi - lambda M) = det M lambda^2 - b lambda + det Phi_Xi
        # = 0 (det Phi_Xi = det(C_z Xi)^2), the smaller root as det Phi_Xi / (det M lambda_1)
        det_m = max(fma(M11, M22, -(M21 * M21)), M11 * rho2)  # M >= rho^2 I: det M >= M_11 rho^2
        bq = fma(P11, M22, fma(P22, M11, -2.0 * P21 * M21))  # det M tr(M^-1 Phi_Xi) = det M (lambda_1 + lambda_2)
        # the eigen-decomposition is needed while one direction of two is on, or AD5 caps a rate
        # (lambda_1 + lambda_2 above lambda_cap: auto_kernel's test), or for the output
        eig = adapting and (n_on == 1 or bq > lcap * det_m)
        lam1 = 0.0
        lam2 = 0.0
        sq = 0.0
        dc = 0.0
        root = 0.0
        if write or eig:  # lambda_1 = sq / (2 det M), lambda_2 = 2 det Phi_Xi / sq
            dc = fma(c01, qf, -(c02 * pf))
            root = math.sqrt(max(fma(bq, bq, -4.0 * det_m * (dc * dc)), 0.0))  # det M (lambda_1 - lambda_2)
            sq = bq + root
            if write and sq > 0.0:
                lam1 = 0.5 * sq / det_m
                lam2 = 2.0 * dc * dc / sq
        # (22) thetah'_unc = -mu V Psi V^T Xi^T C_z^T e, V V^T = M^-1
        td1 = 0.0
        td2 = 0.0
        if adapting:
            g1 = fma(c01, e0, pf * e1)  # g = (C_z Xi)^T e
            g2 = fma(c02, e0, qf * e1)
            if not eig:  # td = -mu M^-1 g, by the adjugate
                idet = -mu / det_m
                td1 = fma(M22, g1, -(M21 * g2)) * idet
                td2 = fma(M11, g2, -(M21 * g1)) * idet
            else:  # td = -mu V S V^T g, S = diag(s_i), s_i = psi_i min(1, lambda_cap / lambda_i) (AD5)
                # (lambda_1 > lambda_cap iff sq > 2 lambda_cap det M; lambda_2 likewise: no division
                # unless capped)
                s1 = ps1 * (2.0 * lcap * det_m / sq if sq > 2.0 * lcap * det_m else 1.0)
                s2 = ps2 * (lcap * sq / (2.0 * dc * dc) if 2.0 * dc * dc > lcap * sq else 1.0)
                # V S V^T = s_2 M^-1 + (s_1 - s_2) v_1 v_1^T (V V^T = M^-1, V^T M V = I), and
                # v_1 v_1^T = P_1 M^-1 with P_1 = (M^-1 Phi_Xi - lambda_2 I) / (lambda_1 - lambda_2), so
                # with u = adj(M) g = det M M^-1 g and w = adj(M) Phi_Xi u:
                # td = -mu (s_2 root u + (s_1 - s_2) (w - det M lambda_2 u)) / (det M root). No
                # eigenvector: the root and one division are all that wait on the eigenvalues.
                u1 = fma(M22, g1, -(M21 * g2))
                u2 = fma(M11, g2, -(M21 * g1))
                if root > 1e-6 * bq:
                    r1 = fma(P11, u1, P21 * u2)  # Phi_Xi u
                    r2 = fma(P21, u1, P22 * u2)
                    hl = 2.0 * det_m * (dc * dc) / sq  # det M lambda_2 (not (bq - root) / 2: no cancellation)
                    w1 = fma(-hl, u1, fma(M22, r1, -(M21 * r2)))
                    w2 = fma(-hl, u2, fma(M11, r2, -(M21 * r1)))
                    ds = s1 - s2
                    sr = s2 * root
                    qd = -mu / (det_m * root)
                    td1 = fma(sr, u1, ds * w1) * qd
                    td2 = fma(sr, u2, ds * w2) * qd
                else:  # lambda_1 = lambda_2 to rounding: every direction is an eigenvector, and
                    # V S V^T averaged over them is the mean of s_1 and s_2 times M^-1
                    idet = -mu * 0.5 * (s1 + s2) / det_m
                    td1 = u1 * idet
                    td2 = u2 * idet
            tt = fma(th1, th1, th2 * th2)
            tu = fma(th1, td1, th2 * td2)
            if tt >= tb2 and tu > 0.0:  # projection (19)-(21)
                td1 -= th1 * (tu * itb2)
                td2 -= th2 * (tu * itb2)
            om1 = th1 - a1  # AD6: the band's clips (Remark 3.1)
            om2 = th2 - a2
            if (om1 <= om_lo and td1 < 0.0) or (om1 >= om_hi and td1 > 0.0):
                td1 = 0.0
            if (om2 <= om_lo and td2 < 0.0) or (om2 >= om_hi and td2 > 0.0):
                td2 = 0.0
            if om2 <= om1 * sep and td2 < td1:  # AD6: the components stay ordered and apart
                mid = 0.5 * (td1 + td2)
                td1 = mid
                td2 = mid
        # outputs at t_k, (8)-(10) with the sampled-oscillator relations; (11); convergence
        thr = max(fade * max(0.0, A1, A2), min_a)
        all_ok = adapting and present
        om1 = th1 - a1
        ok1, num1, A1, wb1, dv1, settled = _component_outputs(om1, z1, z2, A1, wb1, dv1, h, mu_a, c_alpha, c_tol)
        all_ok = all_ok and settled
        faded1 = not A1 >= thr
        om2 = th2 - a2
        ok2, num2, A2, wb2, dv2, settled = _component_outputs(om2, z3, z4, A2, wb2, dv2, h, mu_a, c_alpha, c_tol)
        all_ok = all_ok and settled
        faded2 = not A2 >= thr
        if faded1 or faded2:
            all_ok = False
        if not abs(wb1 - wb2) > 2.0 * c_tol * max(wb1, wb2):  # two on one line: not converged
            all_ok = False
        if write:  # Omegah_i, x_{2i-1} and A cos(phi) sin(omega_d h): (8), (10) after the loop
            out[j, 0] = om1 if ok1 and not faded1 else math.nan
            out[j, 1] = om2 if ok2 and not faded2 else math.nan
            out[j, 4] = z1
            out[j, 5] = z3
            cph[j, 0] = num1
            cph[j, 1] = num2
            out[j, 2] = A1 if ok1 else math.nan
            out[j, 3] = A2 if ok2 else math.nan
            out[j, 6] = z0 if bias else 0.0
            out[j, 7] = 1.0 if all_ok else 0.0
            ext[j, 0] = lam1
            ext[j, 1] = lam2
            ext[j, 2] = ps1
            ext[j, 3] = ps2
            ext[j, 4] = 1.0 if faded1 else 0.0
            ext[j, 5] = 1.0 if faded2 else 0.0
            ext[j, 6] = 1.0 if present else 0.0
        # ---- step to t_{k+1}: (16) zh, with Xi thetah' from the current Xi
        inj = yk - c  # L (eta - C_z zh): L acts on the first output only
        x1 = fma(h, fma(L1, inj, z2) + fma(p1, td1, q1 * td2), z1)
        z2 = fma(h, fma(a1 - th1, x1, L2 * inj) + fma(p2, td1, q2 * td2), z2)
        z1 = x1
        x3 = fma(h, fma(L3, inj, z4) + fma(p3, td1, q3 * td2), z3)
        z4 = fma(h, fma(a2 - th2, x3, L4 * inj) + fma(p4, td1, q4 * td2), z4)
        z3 = x3
        if bias:
            z0 = fma(h, fma(L0, inj, fma(p0, td1, q0 * td2)), z0)
        zf = fma(h, fma(Bf, c, Ff * zf) + fma(pf, td1, qf * td2), zf)
        # (17) xi_i' = A_L xi_i + G_z_i(zh), G_z_i = -x_{2i-1} e_{2i}
        xx = fma(h, fma(-L1, c01, p2), p1)
        p2 = fma(-h, x1, fma(h, fma(a1, xx, -L2 * c01), p2))
        p1 = xx
        xx = fma(h, fma(-L3, c01, p4), p3)
        p4 = fma(h, fma(a2, xx, -L4 * c01), p4)
        p3 = xx
        if bias:
            p0 = fma(-h * L0, c01, p0)
        pf = fma(h, fma(Bf, c01, Ff * pf), pf)
        xx = fma(h, fma(-L1, c02, q2), q1)
        q2 = fma(h, fma(a1, xx, -L2 * c02), q2)
        q1 = xx
        xx = fma(h, fma(-L3, c02, q4), q3)
        q4 = fma(-h, x3, fma(h, fma(a2, xx, -L4 * c02), q4))
        q3 = xx
        if bias:
            q0 = fma(-h * L0, c02, q0)
        qf = fma(h, fma(Bf, c02, Ff * qf), qf)
        # (12) the measured output's filter
        yf = fma(h, fma(Ff, yf, Bf * yk), yf)
        # (19): thetah, kept in the band's clips; as Omegah_i, ordered, apart (AD6). The clips keep
        # thetah in the ball |thetah| <= theta_bar of (19)-(21) by themselves: Omegah_i in
        # [w_lo^2, w_hi^2] and a_i too (its initial value, and -Omegah_i at each re-centring), so
        # |thetah_i| = |a_i + Omegah_i| <= w_hi^2 - w_lo^2 = theta_bar / sqrt(n). auto_kernel's
        # rescaling onto the ball is left out: never active, it cost a root and a division on the
        # loop's critical path each sample (the compiler computed them before the test).
        w1 = max(fma(h, td1, th1) - a1, om_lo)
        w2 = min(max(fma(h, td2, th2) - a2, w1 * sep), om_hi)
        w1 = min(w1, w2 * isep)
        th1 = a1 + w1
        th2 = a2 + w2
        # AD8: re-centre a on the estimates and re-place L_x there (thetah -> 0)
        if abs(th1) > rc * abs(a1) or abs(th2) > rc * abs(a2):
            a1 -= th1
            a2 -= th2
            th1 = 0.0
            th2 = 0.0
            L1, L2 = _place_one(-a1, -a2 + a1, poles, bias)  # as _place, written out for n = 2
            L3, L4 = _place_one(-a2, -a1 + a2, poles, bias)
            if bias:
                pz = 1.0  # P(0)
                for m in range(nx):
                    pz *= -poles[m]
                L0 = pz / (-a1 * -a2)
        # guard (D7 of the explicit mode): restart a diverged observer from zero, thetah kept
        lim = zmax * (1.0 + abs(mean))  # the bound without sqrt(AC power): the common case
        bad = not (
            abs(z1) <= lim
            and abs(z2) <= lim
            and abs(z3) <= lim
            and abs(z4) <= lim
            and abs(z0) <= lim
            and abs(zf) <= lim
        )
        if bad:  # also NaN; then the full bound
            lim = zmax * (1.0 + abs(mean) + math.sqrt(pw))
            bad = not (
                abs(z1) <= lim
                and abs(z2) <= lim
                and abs(z3) <= lim
                and abs(z4) <= lim
                and abs(z0) <= lim
                and abs(zf) <= lim
            )
        if not abs(tr) < math.inf:  # tr(Xi^T Xi) of this sample: Xi finite
            bad = True
        if bad:
            yf = z1 = z2 = z3 = z4 = z0 = zf = 0.0
            p1 = p2 = p3 = p4 = p0 = pf = 0.0
            q1 = q2 = q3 = q4 = q0 = qf = 0.0
            if not abs(th1) <= tbar:
                th1 = 0.0
            if not abs(th2) <= tbar:
                th2 = 0.0
            ps1 = ps2 = 0.0
            clock = 0.0
        if write:
            ext[j, 7] = 1.0 if bad else 0.0
    # (8) omega_d from 2 sin(omega_d h / 2) = h sqrt(Omegah), (10) the phase: after the loop, so that
    # the loop calls no library function (a call would cost the loop its registers)
    for j in range(nrow):
        for i in range(n):
            om = out[j, i]
            if om == om:  # not NaN: present, not faded
                out[j, i], out[j, 4 + i] = _frequency_and_phase(om, out[j, 4 + i], cph[j, i], h, om_u)
            else:
                out[j, 4 + i] = math.nan
    # ---- the locals back into the new state
    s[0] = yf
    s[oz], s[oz + 1], s[oz + 2], s[oz + 3] = z1, z2, z3, z4
    s[oxi], s[oxi + 1], s[oxi + 2], s[oxi + 3] = p1, p2, p3, p4
    s[b], s[b + 1], s[b + 2], s[b + 3] = q1, q2, q3, q4
    if bias:
        s[oz + 4], s[oxi + 4], s[b + 4] = z0, p0, q0
    s[oz + nx], s[oxi + nx], s[b + nx] = zf, pf, qf
    s[oth], s[oth + 1], s[oA], s[oA + 1], s[ops], s[ops + 1] = th1, th2, A1, A2, ps1, ps2
    s[owb], s[owb + 1], s[odv], s[odv + 1] = wb1, wb2, dv1, dv2
    s[osc + _S_CLOCK], s[osc + _S_MEAN], s[osc + _S_POW] = clock, mean, pw
    s[osc + _S_STARTED], s[osc + _S_XI], s[osc + _S_POWL] = started, sxi, pwl
    s[oa_c], s[oa_c + 1] = a1, a2
    s[oL], s[oL + 1], s[oL + 2], s[oL + 3] = L1, L2, L3, L4
    if bias:
        s[oL + 4] = L0
    return out, ext, sse, s


@kernel
def adaptive_multisine_kernel(
    y: np.ndarray, state: np.ndarray, cf: np.ndarray, ci: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Run the estimator over block ``y`` from ``state``; return ``(out, extras, sse, new_state)``.

    ``ci[6]`` selects the mode: 1 the automatic design (:func:`auto_kernel`; for n = 1 and 2 the
    class runs the same written out, :func:`auto_kernel_n1`, :func:`auto_kernel_n2`), 0 the explicit gains
    (:func:`sinewatch.estimators._adaptive_multisine_explicit.explicit_kernel`).
    ``out`` columns: frequency_hz (n), amplitude (n), phase (n), offset, converged;
    ``extras``: lambda (n), psi (n), faded (n), signal present, observer reset. One row per
    sample, or only the last with ``last_only``. Pure: the inputs are not modified."""
    if ci[_I_MODE] == 1:
        return auto_kernel(y, state, cf, ci, last_only)
    return explicit.explicit_kernel(y, state, cf, ci, last_only)


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
        _place(tmp, 0, n, poles, n, int(bias))
        Lx = tmp[n:].copy()
        got = np.sort(np.linalg.eigvals(Fx - np.outer(Lx, Cx)).real)
        if not np.allclose(got, np.sort(poles), rtol=1e-3, atol=0.0):
            raise ParameterError(f"band_hz: the observer poles {list(poles)} could not be placed (got {list(got)})")
        w_lo, w_hi = d["w_lo"], d["w_hi"]
        # the ball of (19)-(21): with a re-centred (AD8) |thetah_i| stays below the band's span
        tbar = math.sqrt(n) * (w_hi * w_hi - w_lo * w_lo)
        h = d["w_ref"] / self.sample_rate_hz
        consts = np.zeros(_N_K)
        consts[_K_H] = h
        consts[_K_MU] = d["mu"]
        consts[_K_RHO2] = d["rho_rel"] ** 2
        consts[_K_MUA] = d["mu_a"]
        consts[_K_DHI] = p.delta_high
        consts[_K_DLO] = p.delta_low
        consts[_K_TBAR] = tbar
        consts[_K_OMU] = d["w_ref"]
        consts[_K_MINA] = p.min_amplitude
        consts[_K_FADE] = p.fade_ratio
        consts[_K_CALPHA] = -math.expm1(-h / d["convergence_time"])
        consts[_K_CTOL] = p.convergence_tol
        consts[_K_DELAY] = d["dwell"]
        consts[_K_ZMAX] = 1e4
        consts[_K_LALPHA] = -math.expm1(-h / d["level_time"])
        consts[_K_OMLO] = w_lo * w_lo
        consts[_K_OMHI] = w_hi * w_hi
        consts[_K_RC] = DESIGN["recentre"]
        consts[_K_SEP] = (1.0 + DESIGN["separation"]) ** 2
        # |xi_i| ~ A / (omega p) for a tone of amplitude A at omega through poles p: the floor of
        # rho is min_amplitude's
        # the input's mean and AC power (signal presence, the guard) over one period of the
        # lowest initial frequency: shorter, they follow the waveform itself
        consts[_K_PALPHA] = -math.expm1(-h / (2.0 * math.pi / d["omega0"][0]))
        consts[_K_LCAP] = d["lambda_cap"]
        consts[_K_XIFLOOR] = (p.min_amplitude / (d["omega0"][0] * -max(d["poles"]))) ** 2
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
        s = np.zeros(nf + nz + nz * n + 5 * n + _N_S + n + nx)
        oa = nf + nz + nz * n + 5 * n + _N_S
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
