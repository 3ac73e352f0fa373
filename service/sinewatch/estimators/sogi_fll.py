"""``sogi-fll``: second-order generalized integrator with a frequency-locked loop and a
DC-offset integrator, for one biased sinusoid (the power-electronics favourite).

None of the papers sinewatch implements describes it: Chen, Pin, Ng, Hui, Parisini, "An
adaptive observer-based robust estimator of multi-sinusoidal signals" (IEEE Trans.
Automatic Control, 2018), Section I, names this family as the usual way PLL/ANF methods are "augmented ... towards a second-order
generalized integrator-based orthogonal signal generator (OSG-SOGI)" to cope with a dc
offset. The structure and the FLL normalisation follow

* [R] P. Rodriguez, A. Luna, I. Candela, R. Mujal, R. Teodorescu, F. Blaabjerg,
  "Multiresonant frequency-locked loop for grid synchronization of power converters
  under distorted grid conditions", IEEE Trans. Ind. Electron. 58(1), 127-138, 2011
  (SOGI-QSG, FLL, gain normalisation);
* the DC-offset rejection is the usual extra integrator on the SOGI error (the
  "SOGI with DC loop", cf. Karimi-Ghartemani et al., IEEE Trans. Power Electron. 27(1),
  2012, reference [9] of Chen et al.).

Continuous-time model (omega' is the estimated angular frequency)::

    e_v        = v - v' - d                                        (1) error
    dv'/dt     = omega' (k e_v - qv')                              (2) SOGI
    dqv'/dt    = omega' v'                                         (3) quadrature
    dd/dt      = k_dc omega' e_v                                   (4) DC integrator
    domega'/dt = -Gamma k omega' e_v qv' / (v'^2 + qv'^2)          (5) normalised FLL [R]

Derivation of the normalisation (5), rebuilt and checked numerically: with
``s = j omega`` the transfer functions are ``E = s (s^2 + omega'^2) / D(s)`` and
``Q = qv'/v = k omega'^2 s / D(s)`` with ``D(s) = s^3 + (k + k_dc) omega' s^2 + omega'^2 s +
k_dc omega'^3``. Near lock ``D(j omega') = -k omega'^3`` (as for the plain SOGI), so the
mean of ``e_v qv'`` is ``V^2 (omega' - omega) / (k omega')`` for an input of amplitude V at
omega, and (5) becomes ``domega'/dt = -Gamma (omega' - omega)``: a first-order loop with
time constant ``1/Gamma`` whatever the amplitude, frequency or sample rate. ``D`` is
Hurwitz for k, k_dc > 0 (Routh: ``(k + k_dc) * 1 > k_dc``); the default ``k_dc = 0.25``
is near the fastest-settling choice for ``k = sqrt(2)`` (poles at ``omega' (-0.81,
-0.43 +- 0.36 j)``; the optimum 0.22 gives a slowest pole at -0.53 omega'). The offset
output d has zero steady-state error for a constant offset (integral action), and
``E(0) = Q(0) = 0`` so the offset does not leak into the FLL error.

Discretisation, sample period h, per sample n (given omega' from sample n-1):

* (T) the linear part (1)-(4) by the trapezoidal rule (Tustin) with frequency
  pre-warping: the matrix ``omega' M`` (M below) is replaced by ``omega_c M`` with
  ``omega_c = (2/h) tan(omega' h / 2)``, so that the discrete SOGI's notch and its 90 deg
  quadrature lie exactly at omega' (at z = exp(j omega' h) the trapezoidal integrator
  ``(h/2)(z+1)/(z-1)`` equals ``1/(j omega_c)``, so ``qv'/v' = omega_c/(j omega_c) = -j``
  and |qv'| = |v'| exactly). With ``x = (v', qv', d)``, ``a = tan(omega' h / 2)``::

      M = [[-k, -1, -k], [1, 0, 0], [-k_dc, 0, -k_dc]],   b = (k, 0, k_dc)
      (I - a M) x[n] = (I + a M) x[n-1] + a b (v[n] + v[n-1])          (T)

  solved in closed form (row 2 gives qv', row 3 gives d, row 1 gives v'). Tustin is
  A-stable: no step-size limit on the SOGI at any omega' h < pi. Forward Euler would
  neither be stable at high omega' h nor put the resonance at omega'.
* (F) the FLL (5) in the warped domain: near lock the mean of ``e_v qv'`` is
  ``V^2 (omega_c - Omega) / (k omega_c)`` and ``d omega_c / d omega' = 1 + a^2``, so the
  FLL rate ``u[n] = -Gamma k (sin(omega' h)/h) e_v[n] qv'[n] / (v'^2 + qv'^2)`` (the
  denominator as modified by (N) below; ``omega_c / (1 + a^2) = sin(omega' h) / h``)
  keeps the loop's linearised rate at Gamma; integrated by the trapezoidal rule
  ``omega'[n] = omega'[n-1] + (h/2)(u[n] + u[n-1])``, then clamped to the frequency
  range. The FLL uses omega'[n-1] in step n: the one-sample loop delay of any explicit
  loop, small for ``Gamma h << 1`` (validated: ``Gamma h <= 0.25``; measured t63 =
  1/Gamma within 3 % at 5 samples per cycle with Gamma h = 0.2). The first-order picture
  holds while Gamma stays below the SOGI's own bandwidth ``k omega / 2``; everything
  scales with the nominal frequency, so with ``g = Gamma / f_nominal`` (Gamma in 1/s,
  f in Hz) measured: g <= 1 first order (t63 = 1/Gamma within 5 % at 1-50 Hz, 4 Hz-50 kHz
  sampling), g = 2 overshoots 20 %, g = 4 by 41 %, g = 6 diverges. Hence the default
  ``Gamma = f_nominal`` (a time constant of one nominal cycle; Rodriguez et al. use 46 at
  50 Hz) and the limit ``Gamma <= k omega_nominal / 2`` (4.4 f_nominal at k = sqrt 2).
* (N) optional amplitude memory (a sinewatch addition to [R], off by default): the
  denominator ``A^2`` of (5) becomes ``max(A^2, P/2)`` with ``P`` = A^2 low-passed over
  ``fll_amplitude_memory_cycles`` nominal cycles. Locked, ``P = A^2`` and (5) is [R]'s
  exactly (harmonic or noise ripple on A^2 stays well inside the factor 2, so it adds
  no bias: measured -1.9e-4 Hz with a 5 % third harmonic either way). When the signal
  collapses, the SOGI's decaying transient has an O(1) normalised error that drives [R]'s
  FLL into its clamp within ~20 ms; with 2 cycles of memory a 90 % sag kicks the
  frequency 9.2 Hz instead of hitting the 25 Hz clamp, but the reduced gain then slows
  the recovery (back within 0.01 Hz after 251 ms instead of 171 ms; offset steps 129
  instead of 96 ms), so it is off by default (docs/estimators/sogi-fll.md has the table).
* below ``min_amplitude`` the FLL holds (``u = 0``).

Outputs (``y = offset + A sin(phase)``): with ``v' = A sin(theta)``, ``qv' = -A cos(theta)``::

    amplitude = hypot(v', qv'),  phase = atan2(v', -qv'),  frequency = omega'/(2 pi),
    offset = d.

Frequency and phase are NaN while ``amplitude <= min_amplitude``. The Track residual is
the one-step prediction error ``v[n] - (d + v' cos(omega' h) - qv' sin(omega' h))`` from
the state before sample n. ``converged`` requires amplitude > min_amplitude, a smoothed
relative error ``rel = sqrt(LPF(e_v^2 / A^2)) < max_relative_error`` and the FLL's own
prediction of the frequency still to go, ``|LPF(u)| / Gamma`` (a first-order loop moves
``Gamma`` times its remaining error per second), below ``frequency_tolerance_hz``; the
low-pass filters have a time constant of ``convergence_cycles`` nominal cycles (the u
filter as two cascaded first-order stages of half that each: same delay, but the FLL's
ripple at twice the frequency, which harmonics cause, is attenuated 40 dB/decade) and the
relative error starts at 1, so a fresh estimator is not converged.

Extras (per sample): ``relative_error_rms`` (the ``rel`` above) and ``rocof_hz_per_s``
(``LPF(u) / (2 pi)``, the FLL's smoothed frequency rate: on a frequency ramp of R Hz/s the
frequency lags by R / Gamma and this reads R).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from sinewatch.estimators import detmath, lanes, register
from sinewatch.estimators.bank import bank_outputs, column_tracks, register_bank
from sinewatch.estimators.base import (
    Estimator,
    EstimatorParams,
    NonNegativeFinite,
    PositiveFinite,
    Track,
    kernel,
    require_below_nyquist,
    track_from_columns,
)
from sinewatch.schemas.errors import ParameterError


class SogiFllParams(EstimatorParams):
    nominal_frequency_hz: PositiveFinite = Field(50.0, description="Initial FLL frequency (Hz)")
    k: PositiveFinite = Field(
        math.sqrt(2.0),
        description="SOGI damping gain (dimensionless; sqrt(2) is the usual choice)",
    )
    k_dc: PositiveFinite = Field(0.25, description="DC-offset integrator gain, relative to omega'")
    gamma: PositiveFinite | None = Field(
        None,
        description="Normalised FLL gain Gamma (1/s): the frequency error decays as exp(-Gamma t). "
        "Default: the nominal frequency's value in Hz (a time constant of one nominal cycle, "
        "50 1/s at 50 Hz); at most k pi nominal (the SOGI's bandwidth)",
    )
    fll_amplitude_memory_cycles: NonNegativeFinite = Field(
        0.0,
        description="FLL normalised by max(A^2, P/2), P = A^2 low-passed over this many nominal "
        "cycles: bounds the frequency kick of a deep sag or signal loss, at the cost of a "
        "slower recovery; 0 (default) = plain A^2 (Rodriguez)",
    )
    min_frequency_hz: PositiveFinite | None = Field(None, description="FLL lower clamp (default 0.5 x nominal)")
    max_frequency_hz: PositiveFinite | None = Field(
        None, description="FLL upper clamp (default 1.5 x nominal; < Nyquist)"
    )
    min_amplitude: NonNegativeFinite = Field(
        1e-6,
        description="Below this amplitude the FLL holds and frequency/phase are NaN",
    )
    max_relative_error: PositiveFinite = Field(
        0.2,
        description="converged requires the smoothed RMS SOGI error below this x amplitude",
    )
    frequency_tolerance_hz: PositiveFinite | None = Field(
        None,
        description="converged requires the FLL's predicted remaining frequency error below this "
        "(default 0.002 x nominal: 0.1 Hz at 50 Hz)",
    )
    convergence_cycles: PositiveFinite = Field(
        1.0,
        description="Time constant of the convergence low-pass filters, in nominal cycles",
    )


@kernel(inline="always")
def _sogi_fll_tan(w: float, consts: np.ndarray | tuple[float, ...]) -> float:
    """(T) the pre-warped step's ``a = tan(omega' h / 2)``: one tan and the half-angle identities
    instead of sin and cos (shorter loop-carried chain), by :func:`sinewatch.estimators.detmath.tan`
    (plain arithmetic, no library call), so that a bank vectorises it across its lanes and each
    lane rounds as the single kernel."""
    return detmath.tan(0.5 * w * consts[0])


@kernel(inline="always")
def _sogi_fll_step(
    vn: float,
    a: float,
    vp: float,
    qv: float,
    d: float,
    w: float,
    v_prev: float,
    u_prev: float,
    ms: float,
    lu1: float,
    lu: float,
    pa: float,
    consts: np.ndarray | tuple[float, ...],
) -> tuple[float, float, float, float, float, float, float, float, float, float, float, float]:
    """One sample ``vn`` of the SOGI-FLL from ``a`` (:func:`_sogi_fll_tan` of omega') and the
    state ``(v', qv', d, omega', v[n-1], u[n-1], LPF(e^2/A^2), LPF(u) stage 1, LPF(u) stage 2,
    P)``; return the new state, then ``A^2`` and the one-step prediction error. The one
    definition of the recursion, called by the single-channel kernel and by the bank (so the two
    agree bit for bit by construction)."""
    h, k, kd, gam = consts[0], consts[1], consts[2], consts[3]
    w_min, w_max, a_min = consts[4], consts[5], consts[6]
    alpha, alpha2, beta = consts[9], consts[10], consts[11]
    a_min2 = a_min * a_min
    gam2k_h = 2.0 * gam * k / h
    a2 = a * a
    inv1a2 = 1.0 / (1.0 + a2)
    sn = 2.0 * a * inv1a2  # sin(omega' h)
    cs = (1.0 - a2) * inv1a2  # cos(omega' h)
    # one-step prediction from the state before v[n]
    e_pred = vn - (d + vp * cs - qv * sn)
    usum = vn + v_prev
    r0 = vp + a * (k * (usum - vp - d) - qv)  # (I + aM) x[n-1] + a b (v[n] + v[n-1])
    r1 = qv + a * vp
    r2 = d + a * kd * (usum - vp - d)
    akd1 = 1.0 + a * kd
    g = 1.0 / akd1
    # row 1 with rows 2-3 substituted, multiplied through by (1 + a k_dc)
    vp = (akd1 * (r0 - a * r1) - a * k * r2) / (akd1 * (1.0 + a * k + a2) - a2 * k * kd)
    qv = r1 + a * vp
    d = g * (r2 - a * kd * vp)
    ev = vn - vp - d  # (1)
    amp2 = vp * vp + qv * qv
    pa += beta * (amp2 - pa)  # (N) amplitude memory P = LPF(A^2)
    # (F) normalised FLL, trapezoidal integration, held below min_amplitude;
    # -Gamma k (sin(omega' h)/h) e qv / max(A^2, P), sin(omega' h) = 2a / (1 + a^2).
    # Selects, not branches (every value computed, then kept or not: the same bits), so that a
    # bank runs the step for 8 lanes as one vector
    live = amp2 > a_min2
    half_pa = 0.5 * pa  # max(A^2, P/2) as Python's max picks it (a select: numba's max is a call,
    den = half_pa if half_pa > amp2 else amp2  # which LLVM inlines only after it vectorises)
    u_live = -gam2k_h * a * ev * qv / ((1.0 + a2) * den)
    u = u_live if live else 0.0
    # silence: flush what decays to subnormals (slow arithmetic), and the relative error
    # restarts as on a fresh estimator
    quiet = (not live) and amp2 < 1e-200
    dead = quiet and amp2 < 1e-300
    vp = 0.0 if dead else vp
    qv = 0.0 if dead else qv
    amp2 = 0.0 if dead else amp2
    d = 0.0 if quiet and abs(d) < 1e-150 else d
    lu1 = 0.0 if quiet and abs(lu1) < 1e-150 else lu1
    pa = 0.0 if quiet and pa < 1e-200 else pa
    lu = 0.0 if quiet and abs(lu) < 1e-150 else lu
    ms = 1.0 if quiet else ms
    w = w + 0.5 * h * (u + u_prev)
    w = w_min if w < w_min else w  # the clamp to the frequency range
    w = w_max if w > w_max else w
    u_prev = u
    v_prev = vn
    # convergence filters
    floor = a_min2 if a_min2 > amp2 else amp2  # max(amp2, a_min2, 1e-300), as Python's max
    floor = 1e-300 if 1e-300 > floor else floor
    ms += alpha * (ev * ev / floor - ms)
    lu1 += alpha2 * (u - lu1)
    lu += alpha2 * (lu1 - lu)
    return vp, qv, d, w, v_prev, u_prev, ms, lu1, lu, pa, amp2, e_pred


@kernel(inline="always")
def _sogi_fll_row(
    vp: float, qv: float, d: float, w: float, ms: float, lu: float, amp2: float, consts: np.ndarray | tuple[float, ...]
) -> tuple[float, float, float, float, float, float, float]:
    """One output row from the state after a sample: the ``out`` columns of
    :func:`sogi_fll_kernel` (frequency, amplitude, phase, offset, converged), then its extras
    (relative error, rocof)."""
    gam, a_min, rel_max, f_tol = consts[3], consts[6], consts[7], consts[8]
    amp = math.sqrt(amp2)
    rel = math.sqrt(ms)
    if amp > a_min:
        ok = rel < rel_max and abs(lu) / (2.0 * math.pi * gam) < f_tol
        f, ph, conv = w / (2.0 * math.pi), math.atan2(vp, -qv), 1.0 if ok else 0.0
    else:
        f, ph, conv = np.nan, np.nan, 0.0
    return f, amp, ph, d, conv, rel, lu / (2.0 * math.pi)


@kernel
def sogi_fll_kernel(
    v: np.ndarray, state: np.ndarray, consts: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Run the SOGI-FLL over block ``v`` from ``state``; return
    ``(out, extras, sse, new_state)``.

    ``state`` is the ``x`` array (layout: :meth:`SogiFll._initial_state`); ``consts`` =
    (h, k, k_dc, Gamma, omega_min, omega_max, min_amplitude, max_relative_error,
    frequency_tolerance_hz, alpha of the error filter, alpha of each of the two u filter
    stages, beta of the amplitude memory (N)).
    ``out`` columns: frequency_hz, amplitude, phase_rad, offset, converged (0/1);
    ``extras`` columns: relative_error_rms, rocof_hz_per_s. Pure.
    """
    vp, qv, d, w, v_prev, u_prev, ms, lu1, lu, pa = (
        state[0], state[1], state[2], state[3], state[4], state[5], state[6], state[7], state[8],
        state[9],
    )  # fmt: skip
    n = v.shape[0]
    out = np.empty((1 if last_only else n, 5))
    ext = np.empty((1 if last_only else n, 2))
    sse = 0.0
    for j in range(n):
        vp, qv, d, w, v_prev, u_prev, ms, lu1, lu, pa, amp2, e_pred = _sogi_fll_step(
            v[j], _sogi_fll_tan(w, consts), vp, qv, d, w, v_prev, u_prev, ms, lu1, lu, pa, consts
        )
        sse += e_pred * e_pred
        if last_only and j != n - 1:
            continue
        row = 0 if last_only else j
        out[row, 0], out[row, 1], out[row, 2], out[row, 3], out[row, 4], ext[row, 0], ext[row, 1] = _sogi_fll_row(
            vp, qv, d, w, ms, lu, amp2, consts
        )
    new_state = np.array([vp, qv, d, w, v_prev, u_prev, ms, lu1, lu, pa])
    return out, ext, sse, new_state


@register
class SogiFll(Estimator[SogiFllParams], kernel=sogi_fll_kernel, name="sogi-fll"):
    """SOGI quadrature generator + normalised FLL + DC integrator (power-electronics PLL family)"""

    example_sample_rate_hz = 5000.0
    example_params: ClassVar[dict[str, Any]] = {"nominal_frequency_hz": 50.0}
    # Printed by ``sinewatch bench kernels`` under its table. Its ratio and ns/sample: ``sinewatch bench kernels --block 1024 --estimators sogi-fll``
    # (the kernel alone: that ns/sample less the per-block call, ~5-7 us / 1024).
    bench_note: ClassVar[str] = (
        "sogi-fll is below the streaming FFT (about 0.7x at 1024-sample blocks): each sample is "
        "one loop-carried chain, omega'(n-1) -> a = tan(omega' h/2) (T) -> the Tustin solve (a "
        "division) -> e_v, qv' -> the FLL rate u (a division, (F)) -> omega'(n), so samples "
        "cannot overlap; the tan alone has ~28 ns of latency here and the chain ~45 ns, more "
        "than the FFT's ~33 ns per sample whatever the rest of the loop does (reordering the "
        "arithmetic to shorten it would change the outputs, which stay bit for bit)."
    )

    # Printed by ``sinewatch bench kernels --bank N`` when the bank stays below twice the FFT.
    bank_note: ClassVar[str] = (
        "the bank runs 8 lanes in one lane-major work array, the tan (sinewatch.estimators.detmath.tan, "
        "plain arithmetic, the single kernel's too) and the whole step as one zmm vector (six vdivpd, no "
        "call in the lane loop), 3.4-3.8x one channel and 1.8-2.2x the streaming FFT in paired rounds "
        "under load 2-3; the kernel is ~60 % of the call: per sample one vector chain, omega' -> tan "
        "(~30 dependent flops and a division) -> the Tustin solve (a division) -> the FLL rate (a "
        "division) -> omega', for 8 channels at once, and the rest is update_bank's Python a frame "
        "(the channels' Tracks, the states gathered and scattered, the checks). Without AVX-512 (the "
        "bench's first lines name the host's vector width) the 8 lanes are two 256-bit vectors, stepped "
        "in one loop body so that their chains overlap: 1.81x the FFT on a 2-core AMD EPYC VM (AVX2, "
        "load 4.5-5.6), 1.67x as a loop of 8"
    )

    def _check_params(self) -> None:
        p = self.params
        fs = self.sample_rate_hz
        require_below_nyquist("nominal_frequency_hz", p.nominal_frequency_hz, fs)
        f_lo = 0.5 * p.nominal_frequency_hz if p.min_frequency_hz is None else p.min_frequency_hz
        f_hi = 1.5 * p.nominal_frequency_hz if p.max_frequency_hz is None else p.max_frequency_hz
        require_below_nyquist("max_frequency_hz", f_hi, fs)
        if not f_lo < f_hi:
            raise ParameterError(f"min_frequency_hz: expected < max_frequency_hz = {f_hi} Hz, got {f_lo}")
        if not f_lo <= p.nominal_frequency_hz <= f_hi:
            raise ParameterError(
                f"nominal_frequency_hz: expected within [{f_lo}, {f_hi}] Hz, got {p.nominal_frequency_hz}"
            )
        gamma = p.nominal_frequency_hz if p.gamma is None else p.gamma
        g_max = p.k * math.pi * p.nominal_frequency_hz  # k omega_nom / 2
        if gamma > g_max:
            raise ParameterError(
                f"gamma: expected <= k omega_nominal / 2 = {g_max:g} 1/s (the SOGI's bandwidth; "
                f"the FLL diverges beyond), got {gamma}"
            )
        if gamma > 0.25 * fs:
            raise ParameterError(
                f"gamma: expected <= 0.25 x sample rate = {0.25 * fs:g} 1/s (discrete FLL), got {gamma}"
            )
        self._f_range = (f_lo, f_hi)
        self.gamma = gamma
        self.frequency_tolerance_hz = (
            0.002 * p.nominal_frequency_hz if p.frequency_tolerance_hz is None else p.frequency_tolerance_hz
        )

    def _setup(self) -> None:
        p = self.params
        h = 1.0 / self.sample_rate_hz
        f_lo, f_hi = self._f_range
        tau = p.convergence_cycles / p.nominal_frequency_hz
        alpha = -math.expm1(-h / tau)  # e^2/A^2 filter: one stage, time constant tau
        alpha2 = -math.expm1(-2.0 * h / tau)  # u filter: two stages of tau/2 each
        mem = p.fll_amplitude_memory_cycles
        beta = 1.0 if mem == 0 else -math.expm1(-h * p.nominal_frequency_hz / mem)  # (N)
        self._constants = (
            np.array(
                [h, p.k, p.k_dc, self.gamma, 2 * math.pi * f_lo, 2 * math.pi * f_hi,
                 p.min_amplitude, p.max_relative_error, self.frequency_tolerance_hz, alpha, alpha2, beta]
            ),
        )  # fmt: skip

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``x`` (10,): v', qv', d, omega', v[n-1], u[n-1], LPF(e^2/A^2), LPF(u) stage 1,
        LPF(u) stage 2, P = LPF(A^2) (the amplitude memory of (N))."""
        w0 = 2.0 * math.pi * self.params.nominal_frequency_hz
        return {"x": np.array([0.0, 0.0, 0.0, w0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])}

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out, ext, sse = outputs
        e = ext.T  # e[i] is the column ext[:, i], one index operation
        extras = {"relative_error_rms": e[0], "rocof_hz_per_s": e[1]}
        # rocof first class too (Estimate v2), the extra kept
        return track_from_columns(out, sse, block.shape[0], extras, rocof_hz_per_s=ext[:, 1:2])

    def _bank_tracks(self, outputs: tuple[Any, ...], block: np.ndarray) -> Sequence[Track]:
        """:meth:`_track` of every channel of a bank (:func:`sogi_fll_bank_kernel`'s outputs)."""
        out, ext, sse = outputs
        extras = {"relative_error_rms": ext[:, :, 0], "rocof_hz_per_s": ext[:, :, 1]}
        return column_tracks(out, sse, block.shape[0], extras, rocof=ext[:, :, 1:2])


# ---- bank: the channels of a frame together (sinewatch.estimators.bank) -------------------
LANES = 8  # channels advanced together: one 512-bit vector of doubles
# rows of the bank's lane-major work array S (one row of LANES doubles each): the state x in its
# order (rows 0-9), A^2 after the sample, the sum of squared prediction errors, then two sample
# rows used in turn (sample k + 1 is written into the row sample k does not read), and the row
# the two-vector lane loop reads its sample from (_RYV: see _bank_lanes_256)
_RAMP2, _RSSE, _RY, _RYV = 10, 11, 12, 14
_ROWS = 15


@kernel(inline="always")
def _bank_lane(S: np.ndarray, lane: int, ry: int, c: tuple[float, ...]) -> None:
    """One sample of lane ``lane`` of ``S`` (its sample in row ``ry``): :func:`_sogi_fll_tan` and
    :func:`_sogi_fll_step`, the single kernel's functions, on the lane's state in place."""
    L = LANES
    vp, qv, d, w, v_prev, u_prev, ms, lu1, lu, pa, amp2, e_pred = _sogi_fll_step(
        S[ry * L + lane], _sogi_fll_tan(S[3 * L + lane], c), S[lane], S[L + lane], S[2 * L + lane],
        S[3 * L + lane], S[4 * L + lane], S[5 * L + lane], S[6 * L + lane], S[7 * L + lane], S[8 * L + lane],
        S[9 * L + lane], c,
    )  # fmt: skip
    S[lane], S[L + lane], S[2 * L + lane], S[3 * L + lane], S[4 * L + lane] = vp, qv, d, w, v_prev
    S[5 * L + lane], S[6 * L + lane], S[7 * L + lane], S[8 * L + lane], S[9 * L + lane] = u_prev, ms, lu1, lu, pa
    S[_RAMP2 * L + lane] = amp2
    S[_RSSE * L + lane] += e_pred * e_pred


@kernel(refcount=False)
def _bank_lanes_512(S: np.ndarray, k: int, c: tuple[float, ...]) -> None:
    """Sample ``k`` of every lane: loops of literal trip count over one array at constant offsets
    (the sample's row a constant in each), which LLVM vectorises 8 doubles wide. The constants
    come as a tuple, not an array: loads from a second array would need a run-time overlap check
    that LLVM does not add to so short a loop. A function of its own without reference counting:
    inlined into the bank kernel, each inlined helper's use of S took and released a reference
    (NRT calls in the lane loop, which then stays scalar)."""
    detmath.prefer_512_bit_vectors()  # 8 lanes: one 512-bit vector
    if k % 2 == 0:
        for lane in range(LANES):
            _bank_lane(S, lane, _RY, c)
    else:
        for lane in range(LANES):
            _bank_lane(S, lane, _RY + 1, c)


@kernel(refcount=False)
def _bank_lanes_256(S: np.ndarray, k: int, c: tuple[float, ...]) -> None:
    """:func:`_bank_lanes_512` where the 8 lanes are two 256-bit vectors (AVX2; no AVX-512): as a
    loop of 8 lanes, the two vectors' steps ran one after the other, each waiting on its own
    dependent chain (omega' -> tan -> the Tustin solve -> the FLL rate); here lanes ``lane`` and
    ``lane + 4`` are stepped in one loop body, so the two independent chains overlap. The sample's
    row is first copied as one vector into the one row _RYV that this loop reads (written a step
    before, the copy's load does not stall; a loop per row, as _bank_lanes_512 has, would double
    the lane step the compiler builds)."""
    L = LANES
    lanes.copy_lanes(S, _RYV * L, S, (_RY + k % 2) * L)
    for lane in range(lanes.HALF):
        _bank_lane(S, lane, _RYV, c)
        _bank_lane(S, lane + lanes.HALF, _RYV, c)


# on this host (a constant per host and numba's cache, which is kept per CPU): only the chosen
# one is ever compiled
_bank_lanes = _bank_lanes_256 if lanes.VECTORS == 2 else _bank_lanes_512


@kernel(inline="always")
def _bank_row(S: np.ndarray, lane: int, c: tuple[float, ...], out: np.ndarray, ext: np.ndarray, row: int) -> None:
    """Row ``row`` of one channel's ``out`` and ``ext`` from lane ``lane`` (:func:`_sogi_fll_row`:
    square roots and the phase's atan2, per channel)."""
    L = LANES
    r = _sogi_fll_row(
        S[lane], S[L + lane], S[2 * L + lane], S[3 * L + lane], S[6 * L + lane], S[8 * L + lane],
        S[_RAMP2 * L + lane], c,
    )  # fmt: skip
    out[row, 0], out[row, 1], out[row, 2], out[row, 3], out[row, 4] = r[:5]
    ext[row, 0], ext[row, 1] = r[5], r[6]


@kernel
def sogi_fll_bank_kernel(
    v: np.ndarray, state: np.ndarray, consts: np.ndarray, last_only: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`sogi_fll_kernel` for C channels at once: ``v`` (N, C), ``state`` (10, C) (each
    column one channel's ``x``); returns ``out`` (C, rows, 5), ``extras`` (C, rows, 2), ``sse``
    (C,) and the new state (10, C). Channels go ``LANES`` at a time through a lane-major work
    array (:func:`_bank_lanes`): the tan and the whole step of the 8 lanes as one vector, their
    8 recursions' chains side by side; the rows per channel after each sample (or the last)."""
    detmath.prefer_512_bit_vectors()  # 8 lanes: one 512-bit vector
    n, nc = v.shape
    out, ext, sse = bank_outputs(n, nc, 2, last_only)
    new_state = np.empty((10, nc))
    c = (consts[0], consts[1], consts[2], consts[3], consts[4], consts[5], consts[6], consts[7], consts[8],
         consts[9], consts[10], consts[11])  # fmt: skip
    L = LANES
    S = lanes.aligned_lanes(_ROWS * L)  # rows on 64-byte boundaries: a row is one cache line
    ys = lanes.aligned_lanes(n * L)
    for g in range(0, nc, L):
        width = min(L, nc - g)
        S[:] = 0.0  # lanes past the last channel run on zeros, their results dropped
        ys[:] = 0.0
        for i in range(10):
            for lane in range(width):
                S[i * L + lane] = state[i, g + lane]
        for k in range(n):  # row by row: v (N, C) is read in its own order
            for lane in range(width):
                ys[k * L + lane] = v[k, g + lane]
        for lane in range(L):  # sample 0's row
            S[_RY * L + lane] = ys[lane]
        for k in range(n):
            # sample k + 1 into the row sample k does not read: written a step before it is read
            # as a vector (read at once, 8 scalar stores would stall its load)
            nxt = min(k + 1, n - 1) * L
            r_next = (_RY + 1 - k % 2) * L
            for lane in range(L):
                S[r_next + lane] = ys[nxt + lane]
            _bank_lanes(S, k, c)
            if not last_only:
                for lane in range(width):
                    _bank_row(S, lane, c, out[g + lane], ext[g + lane], k)
        if last_only:
            for lane in range(width):
                _bank_row(S, lane, c, out[g + lane], ext[g + lane], 0)
        for lane in range(width):
            sse[g + lane] = S[_RSSE * L + lane]
            for i in range(10):
                new_state[i, g + lane] = S[i * L + lane]
    return out, ext, sse, new_state


register_bank(SogiFll, sogi_fll_bank_kernel, n_outputs=3, tracks=SogiFll._bank_tracks)
