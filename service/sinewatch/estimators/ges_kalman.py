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
kernel stays cheap; with the standard-deviation recursion (U1-U6; U and T in registers,
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

Reported standard deviations (``Track.std``; derived here, not in the paper): the actual
error of the state propagated to first order in the noise with the filter's own gains, the
noise variance read from the innovations (eq. U1-U6 in
:mod:`sinewatch.estimators._ges_kalman_kernels`, where the kernels are). Reported parameters
(beyond the paper, ``bias_correction``, on by default): those of x_hat less its second-order
bias sigma_hat^2 b (eq. B1-B4 there). The paper's gains are computed from the same noisy
samples as the state, and that correlation biases x_hat; the filter itself (its state, its
residual) is the paper's, bit for bit, either way.

Calibration (sd of error / reported sd about its mean; one value per trial at the end of
2 s). With the paper's Q = 1e-6 I at 1 kHz (1000 seeded trials: ``pytest -m slow
tests/test_ges_kalman_uncertainty.py``): 0.97 to 1.04 for frequency, amplitude, phase and
offset at 25 and 50.5 Hz, SNR 10 to 40 dB. At the defaults (Q scaled to the sample rate,
:func:`default_q`; R = 1e-2; the bias correction) on 49.5-50.5 Hz tones of amplitude 0.5-2 at
5 kHz, 0 to 60 dB (``sinewatch bench calibration --estimators ges-kalman --trials 1000``, the
table in docs/accuracy.md): sd and |mean| in band for every parameter; without the
correction the frequency's mean at 0 dB is +0.38 sd.

Where it does not hold: U1-U6 and B1-B4 are expansions in the noise (first and second
order), so a memory so short that x3_hat's own noise is large breaks them (the filter is
nonlinear in it): the paper's Q unscaled at 5 kHz (mean error / sd +5.6 for frequency at
0 dB, +2.5 at 10 dB, measured without the correction). Model error (a ramp, harmonics) reads
as noise in the innovations: it widens the reported sd and scales the correction with it,
which then describes the noise it assumes, not the model error.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
from pydantic import Field, field_validator

from sinewatch.estimators import register
from sinewatch.estimators._ges_kalman_bank import ges_kalman_bank_kernel
from sinewatch.estimators._ges_kalman_kernels import (
    BIAS_SIZE,
    LOG_CHI2_MEAN,
    NOISE_MEMORY,
    ROBUST_CAP,
    TINY,
    UNC_BASE,
    UNC_SIZE,
    _noise_means,
    _parameter_std,
    ges_kalman_kernel,
)
from sinewatch.estimators.bank import column_tracks, register_bank
from sinewatch.estimators.base import (
    Estimator,
    EstimatorParams,
    Track,
    TrackStd,
    decode_array,
    encode_array,
    track_from_columns,
)

PAPER_Q = 1e-6  # Section IV: Q = 1e-6 I at fs = 1 kHz, 100 Hz (w Ts = 0.2 pi)
PAPER_W_TS = 0.2 * math.pi
LEGACY_DEFAULTS: dict[str, Any] = {"q": PAPER_Q}  # the defaults of recordings made before default_q
# per ESTIMATOR_DEFAULTS_VERSION v, the defaults of recordings older than v (replay sets them)
DEFAULTS_BY_VERSION: dict[int, dict[str, Any]] = {2: LEGACY_DEFAULTS, 3: {"bias_correction": False}}


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
    bias_correction: bool = Field(
        True,
        description="Report the parameters of x_hat less its second-order bias sigma_hat^2 b (eq. B1-B4, not "
        "in the paper: the gains are computed from the same noisy samples as the state, which biases "
        "the frequency up at low SNR); false: the paper's x_hat as it is, and ~2x less work a sample",
    )

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


@register
class GesKalman(Estimator[GesKalmanParams], kernel=ges_kalman_kernel, name="ges-kalman"):
    """GES Kalman observer for one biased sinusoid"""

    paper = '"A globally exponentially stable (GES) discrete-time observer for the parameters of a biased sinusoid"'
    example_frequency_hz = 100.0  # the paper's Section IV
    example_params: ClassVar[dict[str, Any]] = {"q": PAPER_Q}  # and its Q, at its own w Ts = 0.2 pi
    # defaults of recordings made before ESTIMATOR_DEFAULTS_VERSION 2 (replay sets them), and
    # per version v those of recordings older than v
    defaults_before: ClassVar[dict[str, Any]] = LEGACY_DEFAULTS
    defaults_by_version: ClassVar[dict[int, dict[str, Any]]] = DEFAULTS_BY_VERSION
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
        "for u); the FFT shares its work across a frame instead. The bias correction (B1-B4, on by "
        "default) adds the 40-entry tensor M and b, ~550 flops a sample: bias_correction = false "
        "runs without it"
    )
    # Printed by ``sinewatch bench kernels --bank N`` when the bank stays below twice the FFT.
    bank_note: ClassVar[str] = (
        "the bank advances 8 channels as one 512-bit vector (lane-major state; the filter, T, U and "
        "the bias recursion (B1)-(B3) on zmm in its assembly, and the noise means' log (U5) in a "
        "vectorised loop of its own by sinewatch.estimators.detmath.log, plain arithmetic that the "
        "single kernel uses too: no library call) at ~1.8-2.5x one channel. The bias correction, on "
        "by default, is ~550 flops a sample and channel, more than the filter, T and U together; the "
        "means' recursion (U5)-(U5a) runs two lanes at a time (its exp, where the cap may bind, is "
        "the C library's), and the filter's two divisions sit on each lane's chain. 512-bit lanes "
        "against 256-bit ones, measured in turn under load 13-23: 1.07x (60 ns a channel-sample) and "
        "0.75x (106) the streaming FFT. Where the time goes (8 channels of 1024 samples, each part "
        "timed alone, load 8-17): the kernel is 84-86 % of update_bank, and the bias recursion half "
        "of the kernel (15-18 ns a channel-sample without it, 30-41 with it, the same signals in "
        "turn): its M (40 entries a lane) is read and written back through the work array by one "
        "pass for the head and pairs and four for the columns each sample. Twice the FFT (~20-25 ns "
        "a channel-sample, update_bank's Python of ~6 included) needs that recursion in one pass "
        "with M in registers, not built"
    )

    def _setup(self) -> None:
        p = self.params
        q = default_q(self.sample_rate_hz, p.reference_frequency_hz) if p.q is None else p.q
        q = q if isinstance(q, list) else [q] * 4
        bias = 1.0 if p.bias_correction else 0.0
        self._constants = (
            np.array([*q, p.r, 1.0 / self.sample_rate_hz, p.convergence_rel_std, float(NOISE_MEMORY), bias]),
        )

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``xP`` (20,): the state estimate x1..x4, then the 16 entries of its covariance P
        (row-major). ``unc`` (79,): the actual error covariance's parts T (16, row-major,
        from p0 I) and U (16, from 0), then the exponentially weighted sums <u>, w and
        <log u> (from 0), eq. (U1)-(U5a), then the bias recursion's M (40) and b (4) (from 0),
        eq. (B2)-(B3)."""
        P0 = np.eye(4) * self.params.p0
        return {
            "xP": np.concatenate([np.asarray(self.params.x0, dtype=np.float64), P0.ravel()]),
            "unc": np.concatenate([P0.ravel(), np.zeros(16), np.zeros(3), np.zeros(BIAS_SIZE)]),
        }

    def set_state(self, snapshot: Mapping[str, Any]) -> None:
        """As :meth:`Estimator.set_state`; snapshots of earlier builds are accepted: one
        without ``unc`` (only ``xP``) starts ``unc`` afresh (the filter's state does not
        depend on it; the reported sd settles within a few N_sigma samples, the bias
        correction within the filter's memory), one whose ``unc`` ends in the former
        (<e^2>, <1 + C U C^T>) pair continues from their ratio, one without the bias
        recursion's M and b (35 entries) starts them from 0."""
        state = snapshot.get("state")
        if isinstance(state, Mapping) and "xP" in state and "unc" not in state:
            fresh = self._initial_state()["unc"]
            snapshot = {**snapshot, "state": {**state, "unc": encode_array(fresh)}}
        elif isinstance(state, Mapping) and "unc" in state:
            unc = decode_array(state["unc"])
            if unc.shape == (UNC_BASE - 1,):  # (T, U, <e^2>, <1 + C U C^T>)
                s2 = unc[32] / unc[33] if unc[33] > 0 else self.params.r
                tail = [s2, 1.0, math.log(max(s2, TINY)) + LOG_CHI2_MEAN]  # <u>, w = 1, <log u>
                unc = np.concatenate([unc[:32], tail])
            if unc.shape == (UNC_BASE,):  # without M and b (B2)-(B3)
                unc = np.concatenate([unc, np.zeros(BIAS_SIZE)])
                snapshot = {**snapshot, "state": {**state, "unc": encode_array(unc)}}
        super().set_state(snapshot)

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out, sse, std = outputs
        track = track_from_columns(out, sse, block.shape[0])
        track.std = TrackStd(frequency_hz=std[:, 0:1], amplitude=std[:, 1:2], phase_rad=std[:, 2:3], offset=std[:, 3])
        return track

    def _bank_tracks(self, outputs: tuple[Any, ...], block: np.ndarray) -> Sequence[Track]:
        """:meth:`_track` of every channel of a bank (:func:`ges_kalman_bank_kernel`'s outputs)."""
        out, sse, std = outputs
        return column_tracks(out, sse, block.shape[0], std=std)


register_bank(GesKalman, ges_kalman_bank_kernel, n_outputs=3, tracks=GesKalman._bank_tracks)

# the names other modules and tests import from here (the kernels live in _ges_kalman_kernels)
__all__ = [
    "LEGACY_DEFAULTS",
    "LOG_CHI2_MEAN",
    "NOISE_MEMORY",
    "PAPER_Q",
    "ROBUST_CAP",
    "TINY",
    "UNC_BASE",
    "UNC_SIZE",
    "GesKalman",
    "GesKalmanParams",
    "_noise_means",
    "_parameter_std",
    "default_q",
    "ges_kalman_bank_kernel",
    "ges_kalman_kernel",
]
