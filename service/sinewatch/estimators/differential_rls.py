"""``differential-rls``: differential signal model + recursive (extended) least squares for
the frequency, its rate of change (ROCOF), phase and amplitude of one sinusoid.

Paper: "Differential signal model and sampling techniques for recursive (extended)
least-squares estimation of frequency, frequency derivatives, phase and amplitude" (the
authors and the year are not recorded here: the copy this was built from does not print
them). Most equations are missing from that copy; those used here were rebuilt from the
text and each is checked numerically in ``tests/test_differential_rls.py``.

Rebuilt equations
-----------------
Measurements, eqs. (1)-(2): in-phase and quadrature components relative to a reference
oscillator, taken at t_k = t_{k-1} + dt_k, written as one complex sample::

    y(k) = A sin(w t_k + phi) + n_i(k),  z(k) = A cos(w t_k + phi) + n_q(k)
    c(k) = z(k) + j y(k) = A e^{j(w t_k + phi)} + n(k),   n = n_q + j n_i      (1)-(2)

(w = omega_d, the offset between the signal and the reference.) Taylor expansion around
t_{k-1}, eq. (3): ``sin(w t_{k-1} + phi + w dt_k) = sum_m (w dt_k)^m / m! sin(w t_{k-1} + phi
+ m pi/2)``, and the same for cos, give the differential model, eqs. (4)-(7)::

    v(k) = c(k) - c(k-1) = (e^{j w dt_k} - 1) c(k-1) + xi(k)                      (4)
    xi(k) = n(k) - e^{j w dt_k} n(k-1)                                           (5)
    v(k) = x(k)' theta + xi(k) + O((w dt_k)^{n+1} / (n+1)!)                      (6)
    theta = (w, w^2, ..., w^n),  x_m(k) = (j dt_k)^m / m! c(k-1)                 (7)

i.e. two real equations per sample, in-phase ``y(k)-y(k-1) = dt z w - dt^2/2 y w^2 - dt^3/6
z w^3 + ...`` and quadrature ``z(k)-z(k-1) = -dt y w - dt^2/2 z w^2 + dt^3/6 y w^3 + ...``
(y, z at k-1). With dt_k constant the columns of w and w^3 (and of w^2 and w^4) are
proportional: the information matrix has rank 2 (Section 4). Nonuniform cyclic sampling
(Section 5) cycles dt_k through ceil(n/2) distinct values (here dt (1 - j s), j = 0, 1, ...,
s = ``cycle_spacing``, the paper's T, 0.9 T, 0.8 T).

Frequency derivative, eqs. (24)-(25): with ``w(t) = w0 + lam0 t`` the phase increment is
``alpha_k = w0 dt_k + lam0 g_k``, ``g_k = (t_k^2 - t_{k-1}^2) / 2``, and ``c(k) = e^{j alpha_k}
c(k-1) + ...``, so::

    v(k) = sum_{m=1..n} (j alpha_k)^m / m! c(k-1) + xi(k)
         = sum_{a+b=m<=n} [j^m C(m,b)/m! dt_k^a g_k^b c(k-1)] w0^a lam0^b + xi(k)  (25)

theta holds every monomial ``w0^a lam0^b`` (n = 2: w0, lam0, w0^2, w0 lam0, lam0^2: the
paper's "(w dt)^3 and higher negligible"). Times are counted from a time origin that is
moved to the present at every re-centring (below).

Least squares with exponential data weighting lam, eq. (8), in recursive form (12)::

    P(k) = [P(k-1) - P x x' P / (lam + x' P x)] / lam,  theta^(k) = theta^(k-1) + P(k) x e(k)

(each complex sample is two real updates; lam applied once per sample).

Extended least squares, eqs. (11)-(13). The coloured noise is a moving average of n,
``xi(k) = D(k, z^-1) n(k)`` with ``D = 1 - e^{j w dt_k} z^-1`` (11) (as 2x2 real:
D11 = D22 = 1 - cos(w dt) z^-1, D12 = -D21 = -sin(w dt) z^-1). With E^_k = 1 + sum_p r_p
theta^_p (the estimated ``e^{j w dt_k}``, normalised to |E^| = 1)::

    v_bar(k) = v(k) + (E^_k - r1) n^(k-1),   e(k) = v_bar(k) - x(k)' theta^(k-1)     (12)
    n^(k) = v(k) + rho E^_k n^(k-1) - x(k)' theta^(k)                               (13)

r1 = 0 is the paper's white-noise case (v_bar = v + E^ n^). r1 = lag-1 correlation of the
(oversampled, hence coloured) noise removes only the part of xi correlated with the
regressor c(k-1), as the paper's Section 5 does ("the remaining measurements are only used
for the estimate of the n(k-1) term ... so as to eliminate it"); with the demodulator's
low-pass r1 is computed from its impulse response. rho < 1 is the paper's passivity
artifice (an independent noise added for estimating n^ turns, by spectral factorisation,
the unit-circle root of D into rho): (13) is then ``n^ = c - s^``, ``s^(k) = E^ [rho s^(k-1) +
(1 - rho) c(k-1)]``. The first ``ls_start`` samples are plain least squares (Section 3).

Oversampling, eq. (14): ideal low-pass noise of bandwidth B_N has ``R(tau) = sigma^2
sin(2 pi B_N tau) / (2 pi B_N tau)``; at dt = T_sN / M (T_sN = 1 / (2 B_N)),
``E[(n(k) - n(k-1))^2] = 2 sigma^2 (1 - sinc(1/M))``: 0.033 sigma^2 at M = 10 as the paper
says; at M = 5 it is 0.129 sigma^2 (the paper's 0.065 is 1 - sinc(1/5), without the 2).

Error covariance, eq. (19): ``Cov(theta~) = sigma^2 P``; with weighting, sigma^2 P / (1 + lam).
The reported ``frequency_std_hz`` is that, with sigma^2 the weighted a-priori error power.

Phase and amplitude, eqs. (21)-(23): referred to the end of the data, ``c(j) =
e^{-j w (t_k - t_j)} a(k) + n(j)`` with ``a(k) = A e^{j phi(t_k)} = q + j p`` (21)-(22),
estimated by exponentially weighted least squares with w replaced by w^; recursively
``a^(k) = e^{j alpha^_k} a^(k-1) + (c(k) - e^{j alpha^_k} a^(k-1)) / S(k)``,
``S(k) = lam_a S(k-1) + 1``; then ``A^ = |a^| = sqrt(p^2 + q^2)``, ``phi^ = atan2(p, q)`` (23).

Re-centring (Sections 7 and 10: "a periodic adjustment of the reference oscillator
frequency by the estimate", so that the truncation error of (6) vanishes): every
``recenter_every`` decimated samples, once confident (std below the threshold), the
reference moves by ``dw = w^(t_k)`` (and its ramp by ``dl = lam0^`` when lam0^ stands 3 sigma
out of its noise) and the time origin to t_k. theta is
re-expressed exactly: ``w' = w + lam0 Delta - dw``, ``lam0' = lam0 - dl`` make every monomial
``w'^a lam0'^b`` an affine function of the old ones, ``theta' = T theta + b0``, ``P' = T P T'``.

Real input (this module's front end)
------------------------------------
A real channel ``x = B + A sin(psi + phi_d)`` is mixed with the reference oscillator
(phase psi, frequency w_ref, ramp lam_ref), ``m = 2j (x - B^) e^{-j psi}``, and low-passed
(4th-order Butterworth, bandwidth B_N = ``bandwidth_hz`` = Omega_d / 2 pi), so that
``LPF(m) = A e^{j phi_d} = c``; B^ is the same low-pass applied to x. c is decimated every
``round(fs / (2 B_N M))`` input samples (M = ``oversampling``, Section 5), cycled as above
when n > 2. When the reference is re-centred, the low-pass state is moved to the new
frequency (the steady state of a DF2T biquad for ``X z^n`` is ``z1 = (H - b0) X z``,
``z2 = (b2 - a2 H) X``), so that the filter output continues as if the reference had always
been there. Outputs are compensated for the low-pass response H at the estimated offset
and held between decimated samples with the phase advanced at the estimated frequency:
at every input sample ``frequency = (w_ref + w^ + lam0^ s) / 2 pi``, ``phase = psi + arg(a^ / H)
+ w^ s + lam0^ s^2 / 2`` (s = time since the last decimated sample), ``rocof_hz_per_s =
(lam_ref + lam0^) / 2 pi`` (NaN without ``rocof_model``).

I/Q input (``input = "iq"``: the paper's own setting)
---------------------------------------------------
A channel whose blocks carry two columns, the in-phase ``y`` (column 0) and the quadrature
``z`` (column 1) of eqs. (1)-(2), measured against an external oscillator at
``nominal_frequency_hz`` (0 for a baseband signal, as in Section 10), skips the demodulator:
``c = z + j y`` is taken every ``round(fs / (2 B_N M))`` input samples (cycled as above when
n > 2: the paper's T, 0.9 T come from decimating a uniform stream) and rotated by a digital
reference oscillator, which re-centring moves exactly as the analogue one (within
``tracking_range_hz`` of the external one). ``bandwidth_hz`` is B_N, the bound on the offset
(the I/Q front end's bandwidth, Omega_d / 2 pi); r1 defaults to ``sinc(1/M)``, the ideal
low-pass noise of eq. (14) (``noise_correlation = 0`` for white noise, eq. 11's model). Outputs:
``frequency_hz = nominal + (w_ref + w^ + lam0^ s) / 2 pi``, ``phase_rad`` the phase of the pair
(``y = A sin(phase)``, relative to the external oscillator), ``offset`` 0 (the model has none),
``rocof_hz_per_s`` as above; ``residual_rms`` is the in-phase column's one-step prediction error.
The column count must match ``input`` (InputError ``shape_mismatch`` otherwise). Through the
registry this reproduces the offline Section 10 runs (tests/test_differential_rls.py,
``test_served_*``).

Internally times are in units of T0 (the longest decimated interval) and every equation
is divided by the RMS amplitude of c (weighted with lam^4, taken before c(k-1) so that the
weight is independent of the equation's own noise, and never below |c(k-1)| / 2), so that P
is scale-free. Safeguards (not in the paper): no forgetting while c carries no information
(zero input); a signal 60 dB below its mean power is absent (NaN, no learning; back at 40 dB,
hysteresis against the low-pass ringing); when it comes back, or jumps 20 dB, the core waits
for the low-pass to settle and restarts with theta^ as prior; theta^ is reset if it leaves
|w dt| < pi or goes non-finite; ELS runs only while the offset estimate is within the
band (beyond it the residual is truncation error and the whitening feedback ran away).
sigma^2 for eq. (19) is the a-priori error power weighted with lam^4, so that a transient
is forgotten 4x faster than theta. ``converged`` = at least 2p updates,
``frequency_std_hz < convergence_rel_std * bandwidth_hz`` and |offset| within the bandwidth.

Deviations: the block-Hankel fast solution (9)-(10) is not needed by the recursive form;
the subsequence algorithm (15)-(18) is replaced by the r1-weighted whitening above; the
frequency smoother of Section 10 is replaced by re-centring. docs/estimators/differential-rls.md
has the measured figures beside the paper's.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from sinewatch.estimators import register
from sinewatch.estimators._differential_rls_bank import differential_rls_bank_kernel
from sinewatch.estimators._differential_rls_core import (
    CORE_SIZE,
    K_HOLD,
    K_MIN_AMP,
    K_W_NOM,
    K_W_RANGE,
    K_WARM,
    TWO_PI,
    band_limited_iq_noise,
    baseband_estimate,
    core_constants,
    cyclic_intervals,
    monomial_table,
)
from sinewatch.estimators._differential_rls_front import (
    F_BB_RE,
    F_BS_RE,
    F_LO_RE,
    F_LS_IM,
    F_LS_RE,
    F_WREF,
    FE_SIZE,
    decimation_pattern,
    differential_rls_iq_kernel,
    differential_rls_kernel,
    lowpass_noise_correlation,
    settling_samples,
)
from sinewatch.estimators.bank import column_tracks, register_bank
from sinewatch.estimators.base import Estimator, EstimatorParams, Track, track_from_columns
from sinewatch.schemas.errors import InputError, ParameterError

# the offline Section 10 runs and the kernels, where users of the estimator look for them
__all__ = [
    "DifferentialRls",
    "DifferentialRlsParams",
    "band_limited_iq_noise",
    "baseband_estimate",
    "cyclic_intervals",
    "differential_rls_iq_kernel",
    "differential_rls_kernel",
]


# Field declarations and the class attributes below (paper, example, notes) read like other
# estimators' (a shape the duplicates tool pairs): declarations, not logic to share. Likewise the
# validators: each checks its own range and says so in its own words (expected vs got).
class DifferentialRlsParams(EstimatorParams):
    input: Literal["real", "iq"] = Field(
        "real",
        description="'real': one column, demodulated against the reference oscillator; 'iq': two columns, "
        "in-phase y = A sin(phase) and quadrature z = A cos(phase) (the paper's eqs. 1-2)",
    )
    nominal_frequency_hz: float = Field(
        50.0,
        description="Initial frequency of the reference oscillator (the demodulation carrier), Hz; with "
        "input = 'iq', the frequency of the oscillator the I/Q were taken against (0: baseband)",
    )
    bandwidth_hz: float = Field(
        5.0,
        description="Low-pass bandwidth B_N after demodulation = the largest frequency offset "
        "from the reference handled at once (Omega_d / 2 pi), Hz",
    )
    oversampling: float = Field(
        10.0,
        description="M = T_sN / dt: decimated samples per Nyquist interval T_sN = 1 / (2 B_N) "
        "(Section 5); the decimation factor is round(fs / (2 B_N M))",
    )
    n_terms: int = Field(2, description="n: terms of the Taylor expansion of e^{j w dt} (eqs. 3-7)")
    rocof_model: bool = Field(
        True, description="Estimate the frequency derivative (eqs. 24-25) and ramp the reference with it"
    )
    forgetting_factor: float = Field(0.98, description="Exponential data weighting lambda, 0 < lambda <= 1")
    phase_forgetting_factor: float = Field(
        0.9, description="Exponential weighting of the phase/amplitude stage (eqs. 21-23), 0 < lambda_a <= 1"
    )
    els: bool = Field(True, description="Extended least squares whitening of the coloured noise (eqs. 11-13)")
    els_damping: float = Field(
        0.9, description="rho in [0, 1): whitening filter 1 - rho E z^-1 (the paper's passivity artifice)"
    )
    ls_start: int = Field(20, description="Decimated samples of plain least squares before ELS starts")
    cycle_spacing: float = Field(
        0.1, description="Nonuniform cyclic sampling: dt_j = dt (1 - j spacing), j < ceil(n/2), when n > 2"
    )
    recenter_every: int = Field(
        10, description="Re-centre the reference on the estimate every this many decimated samples (0: never)"
    )
    tracking_range_hz: float | None = Field(
        None, description="How far the reference may move from nominal, Hz; default: bandwidth_hz"
    )
    noise_correlation: float | None = Field(
        None,
        description="r1, lag-1 correlation of the noise at the decimated rate (ELS, eqs. 11-13); default: "
        "'real': from the demodulator's low-pass; 'iq': sinc(1/M), ideal low-pass noise of bandwidth B_N (eq. 14)",
    )
    p0: float = Field(1e4, description="Initial covariance P(0) = p0 I (amplitude-normalised units)")
    convergence_rel_std: float = Field(
        0.01, description="converged once the frequency standard deviation < this * bandwidth_hz"
    )
    min_amplitude: float = Field(1e-6, description="Below this amplitude the estimate is undefined (NaN)")

    @field_validator("bandwidth_hz", "p0", "convergence_rel_std")
    @classmethod
    def _positive(cls, v: float) -> float:
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"expected a finite value > 0, got {v}")
        return v

    @field_validator("nominal_frequency_hz")
    @classmethod
    def _nominal(cls, v: float) -> float:
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"expected a finite value >= 0, got {v}")
        return v

    @field_validator("noise_correlation")
    @classmethod
    def _r1(cls, v: float | None) -> float | None:
        if v is not None and not (math.isfinite(v) and -1.0 < v < 1.0):
            raise ValueError(f"expected -1 < noise_correlation < 1, got {v}")
        return v

    @model_validator(mode="after")
    def _carrier(self) -> DifferentialRlsParams:
        if self.input == "real" and self.nominal_frequency_hz <= 0.0:
            raise ValueError(
                f"nominal_frequency_hz: expected > 0 with input = 'real' (the demodulation carrier), "
                f"got {self.nominal_frequency_hz}"
            )
        return self

    @field_validator("oversampling")
    @classmethod
    def _m(cls, v: float) -> float:
        if not (math.isfinite(v) and v >= 1.0):
            raise ValueError(f"expected oversampling M >= 1, got {v}")
        return v

    @field_validator("n_terms")
    @classmethod
    def _n(cls, v: int) -> int:
        if not 1 <= v <= 6:
            raise ValueError(f"expected 1 <= n_terms <= 6, got {v}")
        return v

    @field_validator("forgetting_factor", "phase_forgetting_factor")
    @classmethod
    def _lam(cls, v: float) -> float:
        if not (0.0 < v <= 1.0):
            raise ValueError(f"expected 0 < forgetting factor <= 1, got {v}")
        return v

    @field_validator("els_damping")
    @classmethod
    def _rho(cls, v: float) -> float:
        if not (0.0 <= v < 1.0):
            raise ValueError(f"expected 0 <= els_damping < 1, got {v}")
        return v

    @field_validator("cycle_spacing")
    @classmethod
    def _sp(cls, v: float) -> float:
        if not (0.0 < v < 1.0):
            raise ValueError(f"expected 0 < cycle_spacing < 1, got {v}")
        return v

    @field_validator("ls_start", "recenter_every")
    @classmethod
    def _nonneg(cls, v: int) -> int:
        if v < 0:
            raise ValueError(f"expected an integer >= 0, got {v}")
        return v

    @field_validator("tracking_range_hz", "min_amplitude")
    @classmethod
    def _nonneg_f(cls, v: float | None) -> float | None:
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise ValueError(f"expected a finite value >= 0, got {v}")
        return v


@register
class DifferentialRls(Estimator[DifferentialRlsParams], kernel=differential_rls_kernel, name="differential-rls"):
    """Differential signal model + recursive extended least squares, with ROCOF. input = "real": one
    column, quadrature-mixed against a re-centred reference oscillator; input = "iq": two columns,
    in-phase y = A sin(phase) and quadrature z = A cos(phase) taken against an external oscillator at
    nominal_frequency_hz (0: baseband, the paper's setting); a block with the other column count is
    rejected (shape_mismatch)"""

    paper = (
        '"Differential signal model and sampling techniques for recursive (extended) least-squares '
        'estimation of frequency, frequency derivatives, phase and amplitude"'
    )
    example_frequency_hz = 50.3
    example_params: ClassVar[dict[str, Any]] = {"nominal_frequency_hz": 50.0, "bandwidth_hz": 5.0}
    # Printed by ``sinewatch bench kernels`` under its table.
    bench_note: ClassVar[str] = " ".join(
        """
        differential-rls is below the streaming FFT (about 0.55x: ~60 ns/sample against ~34 at 1024-sample
        blocks, `sinewatch bench kernels --estimators differential-rls`): it is one recursion, sample after
        sample, with nothing a block transform could share. Every input sample steps the reference oscillator,
        the quadrature demodulator's three channels of two cascaded biquads and the one-step prediction (~26
        ns); every decimated sample (every 10th in the example) runs the pair of RLS updates (12) on 5
        parameters, the ELS noise recursion (13), the phase stage (21)-(23) and the low-pass compensation, with
        9 sin/cos/hypot/sqrt calls and 4 complex divisions in one dependency chain (~330 ns). The arithmetic
        order is fixed (recordings replay bit for bit), so the chain is neither reassociated nor vectorised.
        """.split()
    )
    # Printed by ``sinewatch bench kernels --bank N`` when the bank is below its target.
    bank_note: ClassVar[str] = (
        "the bank vectorises the per-input-sample work across 8 channels (the demodulator's six biquads, the "
        "prediction and the two rotators, packed operations on ymm registers): timed alone (the bank kernel "
        "with the decimated stage switched off, 1024-sample blocks, 8 channels) it costs 14.3 ns a sample and "
        "channel, 3.15x the streaming FFT in the same paired rounds (2-core AMD EPYC VM (AVX2), load 4-10). The "
        "decimated stage is not vectorised: once every 10 input samples each channel runs the RLS pair (12) on "
        "5 parameters, the ELS recursion (13), the phase stage (21)-(23), the re-centring and the low-pass "
        "compensation, one dependent chain with sin, cos, atan2, hypot and sqrt from the C library (a "
        "vectorised version would round differently) and branches that differ between channels: ~590 ns a "
        "decimated sample and channel, 59 of the bank kernel's 73.6 ns a channel-sample (0.60x the FFT), "
        "nearly three times the whole budget of 2x the FFT (~21 ns). Compiled without reference counting "
        "(its atomic counts took ~20 % of a profile's samples) that stage measured 0.99-1.11x its time in "
        "three paired runs (load 4-8): the counts wait on the chain, they do not lengthen it. 2x needs the "
        "decimated stage itself lane-major (the RLS and phase arithmetic as vectors, the library calls "
        "scalar per lane), not built"
    )

    @classmethod
    def params_for(cls, sample_rate_hz: float, hints: dict[str, Any]) -> dict[str, Any]:
        """Parameters for a bench scenario (``sinewatch bench accuracy``): reference at the
        nominal frequency, low-pass bandwidth 10 % of it, tracking range covering the
        scenario's frequency range as far as the demodulator allows, M <= 10."""
        nom = tuple(hints["nominal_frequency_hz"])
        n_inputs = hints.get("n_inputs", 1)
        if n_inputs == 2 and len(nom) == 1:
            # I/Q blocks (the paper's own setting): the baseband frequency and the design come with
            # the scenario (its suggested parameters, applied after these); no demodulator to fit
            return {"input": "iq"}
        if len(nom) != 1 or n_inputs != 1:
            raise ParameterError(
                f"expected one component on one (real) or two (I/Q) inputs, got {len(nom)} components "
                f"on {n_inputs} inputs"
            )
        f0 = float(nom[0])
        lo, hi = hints["frequency_range_hz"]
        bw = 0.1 * f0
        rng = min(max(f0 - float(lo), float(hi) - f0, bw), f0 - 2.0 * bw, 0.45 * sample_rate_hz - f0 - bw)
        m = min(10.0, sample_rate_hz / (2.0 * bw))
        if rng < 0.0 or m < 1.0:
            raise ParameterError(f"expected room for the demodulator below Nyquist, got f0 = {f0} Hz "
                                 f"at {sample_rate_hz} Hz")  # fmt: skip
        return {"nominal_frequency_hz": f0, "bandwidth_hz": bw, "tracking_range_hz": rng, "oversampling": m}

    @property
    def n_inputs(self) -> int:
        """1 with input = 'real', 2 (in-phase, quadrature) with input = 'iq'."""
        return 2 if self.params.input == "iq" else 1

    def _as_block(self, samples: Any) -> np.ndarray:
        """The block checked against ``input``: a typed error that names the parameter when
        the columns disagree with it (before the generic checks of the base class)."""
        if isinstance(samples, np.ndarray) and samples.ndim >= 1:
            cols = samples.shape[1] if samples.ndim == 2 else (1 if samples.ndim == 1 else -1)
            if cols != self.n_inputs:
                want = "2 columns (in-phase, quadrature)" if self.params.input == "iq" else "1 column"
                raise InputError(
                    f"samples: expected {want} with input = {self.params.input!r}, got shape {samples.shape}",
                    kind="shape_mismatch",
                )
        return super()._as_block(samples)

    def _run(
        self, samples: np.ndarray, state: dict[str, np.ndarray], last_only: bool
    ) -> tuple[Track, dict[str, np.ndarray]]:
        """Real input: the class kernel (:func:`differential_rls_kernel`), as the base class
        calls it; I/Q input: :func:`differential_rls_iq_kernel`, called the same way (block,
        state arrays, constants without the demodulator's low-pass, last_only). Two kernels
        rather than one that branches, so that a channel compiles only its own."""
        if self.params.input == "real":
            return super()._run(samples, state, last_only)
        kern: Callable[..., tuple[Any, ...]] = differential_rls_iq_kernel
        result = kern(samples, *state.values(), *self._constants[1:], last_only)
        n_outputs = len(result) - len(state)
        return self._track(result[:n_outputs], samples), dict(zip(state, result[n_outputs:]))  # noqa: B905

    def presence_samples(self, samples: np.ndarray) -> np.ndarray:
        """I/Q input: the magnitude |z + j y| with alternating sign, so that the presence
        detector's AC RMS over its (even, :attr:`presence_cycle_hz`) window reads the
        amplitude whatever the baseband frequency; real input: column 0."""
        if self.params.input == "real" or samples.ndim == 1:
            return super().presence_samples(samples)
        sign = np.where(np.arange(samples.shape[0]) % 2 == 0, 1.0, -1.0)
        return np.asarray(np.hypot(samples[:, 0], samples[:, 1]) * sign, dtype=np.float64)

    @property
    def presence_cycle_hz(self) -> float | None:
        """I/Q input: a window of 4 samples (see :meth:`presence_samples`)."""
        return self.sample_rate_hz / 4.0 if self.params.input == "iq" else None

    def _check_params(self) -> None:
        p = self.params
        fs = self.sample_rate_hz
        rng = p.bandwidth_hz if p.tracking_range_hz is None else p.tracking_range_hz
        if p.input == "iq":
            # complex samples at fs hold offsets within (-fs/2, fs/2) of the external oscillator
            if rng + p.bandwidth_hz >= fs / 2:
                raise ParameterError(
                    f"tracking_range_hz: expected tracking range + bandwidth below half the I/Q sample rate "
                    f"({fs / 2} Hz), got {rng} + {p.bandwidth_hz} = {rng + p.bandwidth_hz}"
                )
        else:
            top = p.nominal_frequency_hz + rng + p.bandwidth_hz
            if top >= fs / 2:
                raise ParameterError(
                    f"nominal_frequency_hz: expected nominal + tracking range + bandwidth below Nyquist "
                    f"({fs / 2} Hz), got {p.nominal_frequency_hz} + {rng} + {p.bandwidth_hz} = {top}"
                )
            if p.nominal_frequency_hz - rng - p.bandwidth_hz <= 0:
                raise ParameterError(
                    f"bandwidth_hz: expected nominal - tracking range - bandwidth > 0, got "
                    f"{p.nominal_frequency_hz} - {rng} - {p.bandwidth_hz}"
                )
        if p.rocof_model and p.n_terms > 4:
            raise ParameterError(f"n_terms: expected <= 4 with rocof_model (n(n+3)/2 parameters), got {p.n_terms}")
        decimation_pattern(fs, p.bandwidth_hz, p.oversampling, p.n_terms, p.cycle_spacing)

    def _setup(self) -> None:
        p = self.params
        fs = self.sample_rate_hz
        iq = p.input == "iq"
        self._cyc = np.array(
            decimation_pattern(fs, p.bandwidth_hz, p.oversampling, p.n_terms, p.cycle_spacing), dtype=np.int64
        )
        d0 = float(self._cyc[0])
        T0 = d0 / fs
        self._tab = monomial_table(p.n_terms, p.rocof_model)
        n_par = self._tab.shape[0]
        # the demodulator's low-pass (real input; passed but unused with I/Q input)
        from scipy import signal  # here, not with the module: listing the estimators need not import it (~1 s CPU)

        self._sos = np.ascontiguousarray(signal.butter(4, p.bandwidth_hz, fs=fs, output="sos"))
        rng = p.bandwidth_hz if p.tracking_range_hz is None else p.tracking_range_hz
        if p.noise_correlation is not None:
            r1 = p.noise_correlation
        elif iq:  # ideal low-pass noise of bandwidth B_N sampled at T_sN / M, eq. (14)
            r1 = float(np.sinc(1.0 / p.oversampling))
        else:
            r1 = lowpass_noise_correlation(self._sos, fs, p.bandwidth_hz, int(self._cyc[0]))
        c = core_constants(
            fs=fs,
            T0=T0,
            lam=p.forgetting_factor,
            lam_a=p.phase_forgetting_factor,
            rho=p.els_damping,
            ls_start=p.ls_start,
            p0=p.p0,
            n_par=n_par,
            conv_std=p.convergence_rel_std * p.bandwidth_hz * TWO_PI * T0,
            w_bb_max=TWO_PI * p.bandwidth_hz * T0,
            recenter_every=p.recenter_every,
            els=p.els,
            derivative=p.rocof_model,
            r1=r1,
        )
        c[K_W_NOM] = TWO_PI * p.nominal_frequency_hz
        c[K_W_RANGE] = TWO_PI * rng
        c[K_MIN_AMP] = p.min_amplitude
        if not iq:  # I/Q input: no low-pass to settle
            c[K_WARM] = settling_samples(self._sos, fs, p.bandwidth_hz)
            c[K_HOLD] = math.ceil(c[K_WARM] / d0)
        self._consts = c
        self._constants = (self._sos, self._tab, self._cyc, self._consts)

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``fe`` (FE_SIZE,): the front end, slots named F_*. Real input: reference phase
        (rad), frequency (rad/s) and ramp (rad/s^2), offset, the low-pass delays, the
        snapshot at the last decimated step, the rotators. I/Q input: F_PSI, F_WREF, F_LREF
        hold the digital reference's phase (rad), offset from the external oscillator (rad
        per T0) and ramp (rad per T0^2), F_BB_* the predicted c and F_BS_* its per-sample
        step, the snapshot slots as for real input (F_SNAP_W, F_SNAP_L: offset from the
        external oscillator), the others unused. ``core`` (CORE_SIZE,): the baseband
        estimator, slots named by the constants above (c(k-1), n^, a^, the weighted
        powers, counters, flags); ``theta`` (p,): the parameter estimate (monomials w^a
        lam^b, :func:`monomial_table`); ``P`` (p, p): its covariance; ``ist`` (3,) int64:
        input samples since the last decimated one, position in the decimation cycle, and
        (real) samples seen while the low-pass warms up / (I/Q) 1 once the first sample
        was taken."""
        n_par = self._tab.shape[0]
        fe = np.zeros(FE_SIZE)
        if self.params.input == "real":
            w = TWO_PI * self.params.nominal_frequency_hz
            fe[F_WREF] = w
            fe[F_LO_RE] = 1.0
            fe[F_LS_RE] = math.cos(w / self.sample_rate_hz)
            fe[F_LS_IM] = math.sin(w / self.sample_rate_hz)
            fe[F_BB_RE] = 1.0
        fe[F_BS_RE] = 1.0
        return {
            "fe": fe,
            "core": np.zeros(CORE_SIZE),
            "theta": np.zeros(n_par),
            "P": np.eye(n_par) * self.params.p0,
            "ist": np.zeros(3, dtype=np.int64),
        }

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out, ext, sse = outputs
        rocof = ext[:, 0] if self.params.rocof_model else np.full(ext.shape[0], np.nan)
        extras = {
            "rocof_hz_per_s": rocof,
            "frequency_std_hz": ext[:, 1],
            "reference_frequency_hz": ext[:, 2],
        }
        track = track_from_columns(out, sse, block.shape[0], extras)
        if self.params.rocof_model:  # first class too (Estimate v2), the extra kept
            track.rocof_hz_per_s = rocof[:, None]
        return track

    def _bank_tracks(self, outputs: tuple[Any, ...], block: np.ndarray) -> Sequence[Track]:
        """:meth:`_track` of every channel of a bank (:func:`differential_rls_bank_kernel`'s outputs)."""
        out, ext, sse = outputs
        on = self.params.rocof_model
        extras = {
            "rocof_hz_per_s": ext[:, :, 0] if on else np.full(ext.shape[:2], np.nan),
            "frequency_std_hz": ext[:, :, 1],
            "reference_frequency_hz": ext[:, :, 2],
        }
        return column_tracks(out, sse, block.shape[0], extras, rocof=ext[:, :, 0:1] if on else None)


register_bank(DifferentialRls, differential_rls_bank_kernel, n_outputs=3, tracks=DifferentialRls._bank_tracks)
