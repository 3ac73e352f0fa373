"""``pmu``: synchrophasor, frequency and ROCOF on the reporting grid (IEEE C37.118.1).

The estimator reports, at the times ``k / Fs`` since the epoch (``Fs`` the reporting rate,
``k`` an integer), the synchrophasor ``X = (Xm / sqrt 2) e^{j phi}`` of the signal
``x(t) = Xm cos(2 pi f0 t + phi(t))`` (magnitude RMS, phase referred to the
nominal-frequency cosine at the report time, C37.118.1-2011 clause 4.2 eq. (1)-(3)),
its frequency ``f = f0 + (1 / 2 pi) dphi/dt`` and ROCOF ``df/dt`` (clause 4.3 eq. (4)-(5)).

Design: quadrature demodulation and a filter bank of a smooth lowpass kernel and its
first two time derivatives, evaluated at the report time, with iterative cancellation of
the negative-frequency image. References:

* [S] IEEE Std C37.118.1-2011, "IEEE Standard for Synchrophasor Measurements for Power
  Systems", and IEEE Std C37.118.1a-2014 (amendment): the quantities, Annex C's reference
  structure (quadrature demodulation at f0, symmetric FIR lowpass, phasor at the filter's
  centre) that (D) and (K) follow.
* [T] J. A. de la O Serna, "Dynamic Phasor Estimates for Power System Oscillations",
  IEEE Trans. Instrum. Meas. 56(5), 1648-1657, 2007: the phasor and its first two
  derivatives estimated by a bank of three FIR filters (the Taylor-Fourier filters, from
  a second-order Taylor model of the phasor over the window); here the bank is one
  kernel and its exact time derivatives (K'), and the Taylor model gives (C).
* [R] P. Romano, M. Paolone, "Enhanced Interpolated-DFT for Synchrophasor Estimation in
  FPGAs: Theory, Implementation, and Validation of a PMU Prototype", IEEE Trans.
  Instrum. Meas. 63(12), 2824-2836, 2014: iterative compensation of the spectral
  interference of the negative-frequency image (the e-IpDFT), applied here to the
  filter-bank outputs (I).
* [N] A. H. Nuttall, "Some Windows with Very Good Sidelobe Behavior", IEEE Trans.
  Acoust., Speech, Signal Process. 29(1), 84-91, 1981: the four-term window with a
  continuous first derivative (-93 dB sidelobes), used as the taper (K).

The papers' own equation numbers are not quoted: they were not at hand to check, so the
equations below carry this module's labels (D)..(R), each derived in place.

Symbols: ``fs`` sample rate, ``f0`` nominal frequency, ``Fs`` reporting rate, ``D``
decimation factor, ``fd = fs / D``, ``T`` kernel length (s), ``fc`` kernel cutoff (Hz),
``nu = f - f0`` the frequency offset.

(D)  demodulation and decimation. Sample ``n`` (counted from the time anchor, below):
     ``z_n = sqrt 2 x_n e^{-j 2 pi f0 n / fs}`` [S, Annex C eq. (C.1)] (the oscillator from
     a table of one period ``P = fs / gcd(fs, f0)`` samples, so exact at any n), then a
     triangle (two cascaded boxcars of D, the CIC2 response
     ``A(nu) = (sin(pi nu D / fs) / (D sin(pi nu / fs)))^2``) centred on every D-th sample:
     ``c_j = sum_{|i| < D} (D - |i|) / D^2 z_{jD + i}``. For ``x = sqrt 2 Re(X e^{j 2 pi
     f0 t})``, ``z = X + conj(X) e^{-j 4 pi f0 t}``: the phasor plus its image at
     ``-(2 f0 + nu)``.
(K)  kernel: ``w(t) = sinc(2 fc t) v(t / T)`` on ``|t| <= T/2``, ``v(u) = a0 + a1 cos 2 pi u +
     a2 cos 4 pi u + a3 cos 6 pi u`` [N]; unit gain: ``p(t) = sum_j w(t - t_j) c_j / (fd W(0))``
     with ``W`` the Fourier transform of w. For a tone ``c_j = e^{j 2 pi nu t_j}`` (Poisson
     summation, up to the aliases ``W(nu +- fd)``, see (B)): ``p(t) = G(nu) e^{j 2 pi nu t}``
     with ``G(nu) = A(nu) W(nu) / W(0)``.
(K') derivatives: ``p'(t) = sum_j w'(t - t_j) c_j / (fd W(0))`` and ``p''`` likewise with w'',
     so for a tone ``p' = (j 2 pi nu) p`` and ``p'' = (j 2 pi nu)^2 p`` exactly, whatever
     G's passband shape (this is what makes frequency unbiased off nominal). The kernels
     are tabulated per input-sample phase ``rho = n mod D`` (polyphase), so a report at any
     input sample costs three complex dot products of ``T fd`` taps.
(I)  image cancellation [R]: with ``X1 = p / G(nu)`` and ``nu = Im(p' / p) / 2 pi``, the
     image ``Xi = conj(X1) e^{-j 4 pi f0 t}`` at ``nu_i = -(2 f0 + nu)`` contributes
     ``(H0(nu_i), H1(nu_i), H2(nu_i)) Xi`` to ``(p, p', p'')``, H_k the exact responses of the
     sampled kernels (tabulated per rho; in exact arithmetic ``H_k = (j 2 pi nu_i)^k G``, but
     deep in the stopband the aliases of (B) dominate); subtract, re-estimate, twice (each
     pass multiplies the residual image by about ``|G(nu_i)| < 1e-3``; a third changed the
     steady-state ROCOF by < 1e-8 Hz/s).
(E)  estimates at the computing sample: ``nu = Im(p'/p) / 2 pi`` [S eq. (4)],
     ``ROCOF = Im(a2) / 2 pi`` with ``a2 = p''/p - (p'/p)^2 - b(nu)`` (= d nu / dt, [S eq. (5)]),
     ``X`` by (C).
(B)  ``b(nu)``: what ``p''/p - (p'/p)^2`` reads on a steady tone (zero in exact
     arithmetic). (K') holds up to the aliases of the sampled kernels, ``fd W(nu +- fd) e^{+-j 2 pi rho D / fs ...}``: tiny for w, but
     w'' multiplies them by ``(2 pi fd)^2``; they cancel on the symmetric phases (rho = 0,
     D/2) only. Measured before (B): up to 0.015 Hz/s at 52.3 Hz (rho = 1, Fs = 50). The
     responses of all three kernels per rho (and the image tables of (I)) are computed from
     the sampled kernels themselves, exactly, at design time.
(C)  second order [T, eq. (9)-(10): the phasor's Taylor terms]: with ``a2 = d^2 log X / dt^2``
     (its imaginary part is 2 pi ROCOF, its real part the curvature of log |X|), a phasor
     ``X(t - tau) ~ X e^{-a1 tau + a2 tau^2 / 2}`` reads ``p ~ X (G(nu) + a2 / 2 G2(nu))``
     with ``G2`` the response of ``t^2 w(t)``, so ``X = p / (G + a2 G2 / 2)`` with
     ``a2 = p''/p - (p'/p)^2 - b(nu)``. This is what recovers the measurement bandwidth
     (modulation) and ramps that the lowpass alone attenuates, and what lets the lowpass
     be narrow enough for the out-of-band test. Measured with ``sinewatch bench compliance
     --full``: 10 % AM at 5 Hz, Fs = 50: TVE 2.0 % with the first-order form
     ``G(nu)`` alone, 0.24 % with (C); the +-1 Hz/s ramp at Fs = 10: 1.25 % -> 0.04 %.
(R)  report time: the computing sample is the input sample nearest the grid time ``t_r``;
     ``X(t_r) = X e^{j 2 pi nu tau}``, ``f(t_r) = f + ROCOF tau`` (``|tau| <= 1 / 2 fs``).
     Absolute reference: ``phi = arg X - 2 pi f0 t_anchor`` (mod 2 pi, from integer ns).

(U)  standard deviations (derived here, not in the papers), from the signal itself. The noise
     variance sigma^2 of the raw samples is read by ``N_PROBES`` probes: the Nuttall taper of
     the window (no sinc) modulated to the raw frequencies ``(i + 1/2) f``, i = 0..3, f the
     estimated frequency, i.e. halfway between the tone's harmonics (and away from the offset
     and the image), over the same decimated samples c_j as the report. Their power over
     their exact gram (the taper convolved with the triangle of (D):
     ``E |P|^2 = 2 sigma^2 (R0 sum v_i^2 + 2 R1 sum v_i v_{i+1} cos(2 pi d D / fs))``, R0, R1
     the triangle's autocorrelation at lags 0 and D), averaged over the probes and over the
     reports with weights ``lambda^age`` (time constant ``NOISE_TIME_CONSTANT_S``: consecutive
     reports share most of their window, so a second of reports is a few independent windows,
     ~100 degrees of freedom) is sigma^2; what a transient or an interharmonic puts in the
     probes counts as noise, which is what the error bar should then cover. The outputs of (E)
     and (C) are then linearised in the kernels' noise ``e = (dp, dp', dp'')``, whose
     covariance is ``E[e e^H] = 2 sigma^2 Gamma``, ``Gamma_kl = sum_n h_k[n] h_l[n]`` the
     raw-domain gram of the three kernels (tabulated per phase; ``E[e e^T]`` is the kernels'
     response at 2 f0, nil): a reported y = Re or Im of ``c^T e`` has variance
     ``sigma^2 c^H Gamma c``. With r1 = p'/p: ``dnu = Im(dp'/p - r1 dp/p) / 2 pi``; ``da2 =
     dp''/p + (2 r1^2 - p''/p) dp/p - 2 r1 dp'/p``, ROCOF = Im(a2) / 2 pi;
     ``dX = dp / Dn - (p G2 / 2 Dn^2) da2`` (Dn = G + a2 G2 / 2), amplitude ``sqrt 2 Re(conj(u)
     dX)``, phase ``Im(conj(u) dX) / |X|`` (u = X / |X|), the RMS TVE ``sqrt(E |dX|^2) / |X|``;
     the offset ``sum_n h0[n] x_n`` has variance ``sigma^2 Gamma_00``. The image cancellation
     and the tables' own dependence on nu are left out (second order). The ROCOF's and TVE's
     standard deviations are in the reports' ``extras`` (``std_rocof_hz_per_s``, ``std_tve``,
     a fraction). P class (a three-cycle window, whose main lobe reaches the probes) is not
     calibrated by ``sinewatch bench calibration``.

Kernel choice per (class, f0, Fs): ``T = 9 / Fs`` (latency ``4.5 / Fs + 2 D / fs``, under the
M-class ``5 / Fs``) and ``fc`` a fraction of ``Fs / 2``: 0.26 (50 Hz) and 0.22 (60 Hz) at
Fs = f0, 0.375 below. The fractions were searched with the compliance bench (``sinewatch
bench compliance``, the smallest limit/worst ratio over every M-class row): a wider
passband helps modulation (TVE, FE), a narrower one the out-of-band FE; the figures are in
docs/pmu.md. P class uses a short three-cycle taper without the sinc (P-class latency
``2 / Fs``; not validated against the P-class limits by the bench, which models M class).

Time: reports are on the grid ``k / Fs`` since the epoch. The block's absolute start time
(``update(samples, t0_ns=...)``) anchors the sample count; without it the stream is
taken to start at t = 0. A block whose start time disagrees with the count by more than
half a sample (a gap in time) re-anchors the estimator: it restarts (its reports resume
after one kernel length). Every report is computed once the kernel's last tap has
arrived: the latency is ``T / 2 + 2 D / fs``.

(T)  converged: a report is converged when its magnitude is above ``min_amplitude`` and no
     transition has been seen for one kernel length (``ceil(T Fs)`` reports: the window of
     the report has refilled since). A report is a transition when it departs from the
     previous report's prediction (magnitude unchanged, frequency ``f + ROCOF / Fs``) by
     more than ``max(floor, 6 s)``, s the running mean of those departures (each clipped to
     the threshold; the plain mean of the first 20, then weight 0.05 a report), so that noise and sustained modulation raise the
     threshold with them while a step does not: floors 0.1 % of the magnitude and 0.006 Hz
     (module constants, from the C37.118.1 step tests: the first report of a step whose TVE
     exceeds 1 % already departs by more). The start, a restart on the grid (a gap in time,
     a reset) and an undefined report start it over; the first report after one is not
     converged (there is nothing to check it against). Consequences: converged is false
     from the first report a magnitude or phase step moves (before the step's instant, as
     the window reaches it) until one window after the last such report; a modulation at
     the edge of the measurement bandwidth reads as transitions until the scale has risen
     to it (about 1 s).

Per-sample outputs (the Track rows) hold the latest report, the phase advanced at its
frequency (``y = offset + A sin(phase)``, A = sqrt 2 |X|); ``offset`` is the kernel's DC
output on the raw samples. ``residual_rms`` is the one-step prediction error of that
held model. A row's ``converged`` is the kernel's magnitude test, whatever ``last_only``
(a row is the same row either way); the reports' own ``converged`` is (T). The reports themselves (``Track.reports``, a GridReports) carry the same
fields at the report times, the ROCOF in ``rocof_hz_per_s`` and the synchrophasor in
``extras`` (``synchrophasor_magnitude``, RMS, and ``synchrophasor_angle_rad``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from sinewatch.estimators import register
from sinewatch.estimators.base import (
    Estimator,
    EstimatorParams,
    GridReports,
    Track,
    TrackStd,
    concat_tracks,
    cyclic_next,
    decode_array,
    encode_array,
    kernel,
    track_from_columns,
    wrap_pi,
)
from sinewatch.schemas.errors import ParameterError

# [N] four-term window, continuous first derivative (-93 dB sidelobes)
NUTTALL = (0.355768, 0.487396, 0.144232, 0.012604)

M_CLASS_RATES = {50: (10, 25, 50), 60: (10, 12, 15, 20, 30, 60)}
# P class: the same rates; 100/120 frames/s would need a window under 2 cycles (latency 2 / Fs)
P_CLASS_RATES = M_CLASS_RATES

# M class: T = 9 / Fs (latency 4.5 / Fs + 2 ms < 5 / Fs); fc as a fraction of Fs / 2.
M_WINDOW_REPORTS = 9.0
M_CUTOFF_FRACTION = {50: 0.26, 60: 0.22}  # at Fs = f0 (docs/pmu.md: the search)
M_CUTOFF_LOW_RATE = 0.375  # Fs < f0
P_WINDOW_CYCLES = 3.0
# below 10 samples a nominal cycle the second harmonic folds onto the image band (D)
MIN_SAMPLES_PER_CYCLE = 10

TABLE_STEP_HZ = 0.04
N_IMAGE_PASSES = 2

# converged (T): a report is a transition when it departs from the previous report's
# prediction by more than max(floor, TRANSITION_K x the running scale of such departures).
# Floors from the C37.118.1 step tests (``sinewatch bench compliance``): at the first report
# whose TVE exceeds 1 % the magnitude has moved >= 0.12 % from the report before (10 %
# steps) or the frequency >= 0.0075 Hz from its prediction (10 degree steps), where the
# steady, harmonic, ramp and out-of-band tests move < 0.06 % and < 0.0056 Hz.
TRANSITION_MAG_FLOOR = 1e-3  # relative change of the RMS magnitude
TRANSITION_FREQ_FLOOR_HZ = 6e-3
TRANSITION_K = 6.0
TRANSITION_ALPHA = 0.05  # weight of each report in the running scale (~20 reports)


class PmuParams(EstimatorParams):
    nominal_frequency_hz: Literal[50, 60, "auto"] = Field(
        50,
        description="Nominal frequency f0 (Hz): 50 or 60; 'auto': found from the signal (its first "
        "0.2 s with a signal, the spectral peak between 40 and 70 Hz: 50 below 55 Hz, else 60)",
    )
    reporting_rate_hz: int | None = Field(
        None,
        description="Reports per second Fs (default f0). M class: 10, 25, 50 at 50 Hz; "
        "10, 12, 15, 20, 30, 60 at 60 Hz (the same for P class)",
    )
    performance_class: Literal["M", "P"] = Field("M", description="C37.118.1 performance class")
    min_amplitude: float = Field(
        1e-9, ge=0, allow_inf_nan=False, description="converged requires the RMS magnitude > this"
    )


@dataclass(frozen=True)
class Design:
    """Everything derived from (fs, f0, Fs, class), computed once per configuration."""

    fs: float
    f0: int
    f_osc: float  # the demodulation oscillator's frequency: f0, or within fs / P^2 of it (oscillator)
    reporting_rate: int
    decimation: int
    window_s: float
    cutoff_hz: float
    osc: np.ndarray  # (P, 2) cos, sin of 2 pi f0 n / fs
    weights: np.ndarray  # (Q, 6), Q = lcm(P, D): (D) folded per sample phase, see demod_weights
    kernels: np.ndarray  # (D, 3, M) w, w', w'' per input-sample phase, over fd W(0)
    m_lo: int  # tap m runs m_lo..m_lo + M - 1; c index = q - m
    g_pass: np.ndarray  # (D, T) complex: kernel 0's response on nu_pass0 + i * TABLE_STEP_HZ
    a2_bias: np.ndarray  # (D, T) complex: what a2 of (E) reads on a steady tone (kernel aliasing, (B))
    g_chirp: np.ndarray  # (D, T) complex: kernel 0's response to t^2 e^{j 2 pi nu t} (C)
    nu_pass0: float
    g_image: np.ndarray  # (D, 3, T) complex: the three kernels' responses on nu_image0 + i * step
    nu_image0: float
    noise_gram: np.ndarray  # (D, 3, 3): (U) the kernels' raw-domain noise gram, per phase
    probe_taper: np.ndarray  # (D, M): (U) the noise probes' taper, per phase
    probe_gram: np.ndarray  # (D, 2): (U) the probes' gram terms S0, S1 per phase, with the triangle's R0, R1

    @property
    def n_taps(self) -> int:
        return int(self.kernels.shape[2])

    @property
    def latency_s(self) -> float:
        """Report time to the arrival of the last sample it needs (worst case over phases)."""
        d = self.decimation
        return ((-self.m_lo) * d + d - 1 + 0.5) / self.fs


def _sinc_derivs(t: np.ndarray, b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s = sin(bt)/(bt) and its first two derivatives (series near t = 0)."""
    bt = b * t
    small = np.abs(bt) < 1e-3
    safe = np.where(small, 1.0, bt)
    ts = np.where(small, 1.0, t)
    s = np.where(small, 1.0 - bt**2 / 6.0, np.sin(safe) / safe)
    s1 = np.where(small, -b * bt / 3.0, (safe * np.cos(safe) - np.sin(safe)) / (safe * ts))
    s2 = np.where(
        small,
        -(b**2) / 3.0 + b**2 * bt**2 / 10.0,
        ((2.0 - safe**2) * np.sin(safe) - 2.0 * safe * np.cos(safe)) / (safe * ts * ts),
    )
    return s, s1, s2


def demod_weights(osc: np.ndarray, d: int) -> np.ndarray:
    """(D) as six multiply-adds per sample: for the sample phase ``q = n mod lcm(P, D)``
    (``rho = q mod D``), the weights of ``x_n`` in the two triangles it feeds,
    ``(D - rho) / D^2`` (c_j) and ``rho / D^2`` (c_{j+1}), times ``sqrt 2 e^{-j 2 pi f0 n / fs}``
    (re, im) and alone (the raw-sample DC triangle): columns cur re, cur im, next re,
    next im, cur dc, next dc."""
    period = osc.shape[0]
    q = np.arange(period * d // math.gcd(period, d))
    rho = q % d
    c, s = osc[q % period, 0], osc[q % period, 1]
    cur, nxt = (d - rho) / (d * d), rho / (d * d)
    r2 = math.sqrt(2.0)
    return np.ascontiguousarray(np.stack([cur * r2 * c, -cur * r2 * s, nxt * r2 * c, -nxt * r2 * s, cur, nxt], axis=1))


def _kernel(t: np.ndarray, window_s: float, cutoff_hz: float | None) -> np.ndarray:
    """(3, len(t)): w, w', w'' of (K) at times t (zero outside |t| <= T/2)."""
    big_t = window_s
    inside = np.abs(t) <= 0.5 * big_t
    v = np.zeros_like(t)
    v1 = np.zeros_like(t)
    v2 = np.zeros_like(t)
    for k, a in enumerate(NUTTALL):
        om = 2.0 * np.pi * k / big_t
        v += a * np.cos(om * t)
        v1 -= a * om * np.sin(om * t)
        v2 -= a * om * om * np.cos(om * t)
    if cutoff_hz is None:
        w = np.stack([v, v1, v2])
    else:
        s, s1, s2 = _sinc_derivs(t, 2.0 * np.pi * cutoff_hz)
        w = np.stack([s * v, s1 * v + s * v1, s2 * v + 2.0 * s1 * v1 + s * v2])
    return np.where(inside, w, 0.0)


def _w_transform(nu: np.ndarray, window_s: float, cutoff_hz: float | None) -> np.ndarray:
    """W(nu) of the kernel (real: w is even), by the midpoint rule on a fine grid."""
    n = 8192
    t = (np.arange(n) + 0.5) / n * window_s - 0.5 * window_s
    w = _kernel(t, window_s, cutoff_hz)[0] * (window_s / n)
    out = np.empty(nu.shape)
    for i in range(0, nu.size, 512):
        out[i : i + 512] = np.cos(2.0 * np.pi * np.outer(nu[i : i + 512], t)) @ w
    return out


def _bank_response(kernels: np.ndarray, m: np.ndarray, d: int, fs: float, nu: np.ndarray) -> np.ndarray:
    """(D, K, len(nu)) complex: the exact response of the sampled kernels (after the CIC2)
    to a tone at nu, per input-sample phase rho: sum_m K[rho, k, m] e^{-j 2 pi nu t_m} A(nu).
    Exact (not the continuous W): deep in the stopband, where the image lies, the sampled
    kernels' aliases are comparable to W itself and the derivative relations of (K') fail."""
    out = np.empty((kernels.shape[0], kernels.shape[1], nu.size), dtype=np.complex128)
    a = _cic2(nu, d, fs)
    for rho in range(kernels.shape[0]):
        t = (m * d + rho) / fs
        e = np.exp(-2j * np.pi * np.outer(t, nu))
        out[rho] = (kernels[rho] @ e) * a
    return np.ascontiguousarray(out)


def _cic2(nu: np.ndarray, d: int, fs: float) -> np.ndarray:
    num = np.sin(np.pi * nu * d / fs)
    den = d * np.sin(np.pi * nu / fs)
    r: np.ndarray = np.divide(num, den, out=np.ones_like(nu), where=np.abs(den) > 1e-300)
    r2: np.ndarray = r * r
    return r2


#: The largest table of demodulation weights (rows of ``lcm(P, D)``) a rate that is not a whole
#: number of hertz may have: 2e5 rows of six floats, 9.6 MB.
MAX_WEIGHT_ROWS = 200_000


def oscillator(fs: float, f0: int, d: int) -> tuple[int, int, float]:
    """``(a, M, f_osc)``: the demodulation oscillator ``e^{-j 2 pi (a n mod M) / M}``, exact at
    every n from a table of one period ``P = M / gcd(M, a)``, at ``f_osc = fs a / M``. At a whole-number rate ``a / P = f0 /
    fs`` exactly (``f_osc = f0``). At any other rate (a third-party generator's 9999.33 Hz)
    ``f0 / fs`` has no short period, so ``a / P`` is its best rational approximation with
    ``lcm(P, D) <= MAX_WEIGHT_ROWS`` (continued fractions): ``f_osc`` is then within
    ``fs / P^2`` of f0 (2e-5 Hz at 9999.33 Hz, a few mHz at most at 50 kHz). Every step of
    (D)-(R) is written for the oscillator's frequency, not f0, so the estimates are exact
    either way; only the synchrophasor angle, referred to the nominal cosine, is turned by
    ``2 pi (f_osc - f0) (t - t_anchor)`` afterwards (:meth:`Pmu._run_timed`)."""
    fs_int = round(fs)
    if abs(fs - fs_int) <= 1e-9 * fs and fs_int > 0:
        return f0, fs_int, float(f0)
    from fractions import Fraction

    ratio = Fraction(f0) / Fraction(fs)
    best = None
    for limit in (MAX_WEIGHT_ROWS // d, MAX_WEIGHT_ROWS // (2 * d), MAX_WEIGHT_ROWS // (4 * d)):
        frac = ratio.limit_denominator(max(1, limit))
        a, period = frac.numerator, frac.denominator
        rows = period * d // math.gcd(period, d)
        err = abs(fs * a / period - f0)
        if rows <= MAX_WEIGHT_ROWS and (best is None or err < best[2] - 1e-15):
            best = (a, period, err)
    assert best is not None
    a, period, _ = best
    return a, period, fs * a / period


@functools.lru_cache(maxsize=32)
def design(fs: float, f0: int, reporting_rate: int, performance_class: str) -> Design:
    if not (math.isfinite(fs) and fs > 0):
        raise ParameterError(f"sample_rate_hz: expected a finite rate > 0, got {fs}")
    if fs < MIN_SAMPLES_PER_CYCLE * f0:
        raise ParameterError(
            f"sample_rate_hz: expected >= {MIN_SAMPLES_PER_CYCLE * f0} Hz ({MIN_SAMPLES_PER_CYCLE} samples per "
            f"nominal cycle), got {fs}"
        )
    d = max(1, int(fs) // 1000)
    fd = fs / d
    if performance_class == "M":
        window_s = M_WINDOW_REPORTS / reporting_rate
        frac = M_CUTOFF_FRACTION[f0] if reporting_rate == f0 else M_CUTOFF_LOW_RATE
        cutoff: float | None = frac * reporting_rate / 2.0
    else:
        window_s = P_WINDOW_CYCLES / f0
        cutoff = None
    mult, modulus, f_osc = oscillator(fs, f0, d)
    period = modulus // math.gcd(modulus, mult)
    n = np.arange(period)
    ang = 2.0 * np.pi * ((mult * n) % modulus) / modulus
    osc = np.ascontiguousarray(np.stack([np.cos(ang), np.sin(ang)], axis=1))
    weights = demod_weights(osc, d)
    half = 0.5 * window_s * fs  # in input samples
    m_lo = math.ceil((-half - (d - 1)) / d)
    m_hi = math.floor(half / d)
    taps = m_hi - m_lo + 1
    w0 = _w_transform(np.zeros(1), window_s, cutoff)[0]
    scale = 1.0 / (fd * w0)
    kernels = np.empty((d, 3, taps))
    m = np.arange(m_lo, m_hi + 1)
    for rho in range(d):
        t = (m * d + rho) / fs
        kernels[rho] = _kernel(t, window_s, cutoff) * scale
    span = 0.5 * reporting_rate + 1.0
    nu_pass = np.arange(-span, span + TABLE_STEP_HZ / 2, TABLE_STEP_HZ)
    nu_img = -2.0 * f_osc + nu_pass
    bank = _bank_response(kernels, m, d, fs, nu_pass)
    t2 = np.stack([((m * d + rho) / fs) ** 2 for rho in range(d)])  # t_m^2 per phase
    g_chirp = np.ascontiguousarray(_bank_response(kernels[:, :1] * t2[:, None, :], m, d, fs, nu_pass)[:, 0])
    g_pass = np.ascontiguousarray(bank[:, 0])
    r1 = bank[:, 1] / bank[:, 0]
    a2_bias = np.ascontiguousarray(bank[:, 2] / bank[:, 0] - r1 * r1)
    g_img = _bank_response(kernels, m, d, fs, nu_img)
    noise_gram, probe_taper, probe_gram = _noise_design(kernels, m, d, fs, window_s)
    return Design(
        fs=fs,
        f0=f0,
        f_osc=f_osc,
        reporting_rate=reporting_rate,
        decimation=d,
        window_s=window_s,
        cutoff_hz=math.nan if cutoff is None else cutoff,
        osc=osc,
        weights=weights,
        kernels=np.ascontiguousarray(kernels),
        m_lo=m_lo,
        g_pass=g_pass,
        a2_bias=a2_bias,
        g_chirp=g_chirp,
        nu_pass0=float(nu_pass[0]),
        g_image=g_img,
        nu_image0=float(nu_img[0]),
        noise_gram=noise_gram,
        probe_taper=probe_taper,
        probe_gram=probe_gram,
    )


def _triangle_autocorrelation(d: int) -> tuple[float, float]:
    """(U) ``R0 = sum_i tri_i^2`` and ``R1 = sum_i tri_i tri_{i+D}`` of the triangle of (D):
    the noise covariance of consecutive c_j (lags beyond D are zero)."""
    i = np.arange(-(d - 1), d)
    tri = (d - np.abs(i)) / (d * d)
    r0 = float(np.sum(tri * tri))
    r1 = float(np.sum(tri[d:] * tri[:-d])) if d > 1 else 0.0
    return r0, r1


def _noise_design(
    kernels: np.ndarray, m: np.ndarray, d: int, fs: float, window_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(U) per input-sample phase rho: the gram ``Gamma_kl = sum_n h_k[n] h_l[n]`` of the three
    kernels' raw-domain responses h_k (taps convolved with the triangle), the probes' Nuttall taper
    on the kernels' tap times, and the probes' gram terms ``(R0 sum v_i^2, R1 sum v_i v_{i+1})``."""
    r0, r1 = _triangle_autocorrelation(d)
    n_rho, _, taps = kernels.shape
    gram = np.empty((n_rho, 3, 3))
    taper = np.empty((n_rho, taps))
    pgram = np.empty((n_rho, 2))
    for rho in range(n_rho):
        k = kernels[rho]
        lag1 = k[:, :-1] @ k[:, 1:].T
        gram[rho] = r0 * (k @ k.T) + r1 * (lag1 + lag1.T)
        t = (m * d + rho) / fs
        v = _kernel(t, window_s, None)[0]
        taper[rho] = v
        pgram[rho] = (r0 * float(v @ v), r1 * float(v[:-1] @ v[1:]))
    return np.ascontiguousarray(gram), np.ascontiguousarray(taper), np.ascontiguousarray(pgram)


#: 'auto': the detection window (ten cycles of 50 Hz, twelve of 60) and how long a signal
#: between 54 and 56 Hz is held before the nominal frequency is taken from its side of 55 Hz.
DETECTION_S = 0.2
AMBIGUOUS_S = 3.0
_DETECTION_GRID_HZ = np.arange(40.0, 70.0 + 1e-9, 0.25)


def _steady_level(x: np.ndarray) -> bool:
    """Whether the two halves of ``x`` carry AC power within a factor of 4 of each other: a
    window that a signal starts (or stops) in has a spectrum smeared by the edge, not one to
    judge the nominal frequency from."""
    h = x.size // 2
    a, b = float(np.var(x[:h])), float(np.var(x[h:]))
    return min(a, b) > 0.25 * max(a, b)


def spectral_peak_hz(x: np.ndarray, fs: float) -> float:
    """Where the Hann-windowed spectrum of ``x`` peaks between 40 and 70 Hz (0.25 Hz grid;
    a DC offset removed first; harmonics of 50 or 60 Hz lie above 80 Hz): the fundamental of
    mains. NaN when ``x`` has no AC content (a silent window says nothing)."""
    ac = x - np.mean(x)
    if not np.max(np.abs(ac)) > 1e-12 * np.max(np.abs(x)):  # a constant, up to the mean's rounding
        return math.nan
    wx = np.hanning(ac.size) * ac
    t = np.arange(ac.size) / fs
    power = np.empty(_DETECTION_GRID_HZ.size)
    for i in range(0, _DETECTION_GRID_HZ.size, 16):  # 16 frequencies at a time: bounded memory
        f = _DETECTION_GRID_HZ[i : i + 16]
        power[i : i + 16] = np.abs(np.exp(-2j * np.pi * np.outer(f, t)) @ wx)
    return float(_DETECTION_GRID_HZ[int(np.argmax(power))])


def gain(d: Design, nu: float | np.ndarray) -> np.ndarray:
    """The kernel bank's complex gain G(nu) (real), exact, for analysis and tests."""
    nu = np.atleast_1d(np.asarray(nu, dtype=np.float64))
    w0 = _w_transform(np.zeros(1), d.window_s, None if math.isnan(d.cutoff_hz) else d.cutoff_hz)[0]
    cut = None if math.isnan(d.cutoff_hz) else d.cutoff_hz
    g: np.ndarray = _w_transform(nu, d.window_s, cut) / w0 * _cic2(nu, d.decimation, d.fs)
    return g


# --------------------------------------------------------------------------------------
# kernel

# istate: 0 n (samples since the anchor), 1 j (next decimated index), 2 k_next (grid
# index of the next report), 3 k0 (first grid index at/after the anchor), 4 held (a
# report has been made), 5 defined (it has a finite estimate)
# fstate: 0 delta0 (samples from the anchor to grid point k0), 1 beta (2 pi f0 t_anchor
# mod 2 pi), 2-3 acc_cur (re, im), 4-5 acc_next, 6 dc_cur, 7 dc_next,
# 8 f, 9 A (peak), 10 theta (phase at the current sample), 11 B (offset), 12 rocof,
# 13 converged, 14 cos theta, 15 sin theta (rotor at the current sample)
N_ISTATE = 6
N_FSTATE = 16
#: (U) noise probes per report, and the time constant (s) of their average over reports
N_PROBES = 4
NOISE_TIME_CONSTANT_S = 1.0
#: report rows: the 8 values, then (U) the standard deviations of frequency, ROCOF, amplitude,
#: phase, offset and TVE
N_REPORT_COLUMNS = 14


@kernel
def _interp(table: np.ndarray, x0: float, step: float, x: float) -> Any:
    """Cubic (4-point Lagrange) interpolation of a table sampled at x0 + i step; clamped."""
    u = (x - x0) / step
    n = table.shape[0]
    i = math.floor(u)
    if i < 1:
        i = 1
    if i > n - 3:
        i = n - 3
    s = u - i
    if s < -1.0:
        s = -1.0
    if s > 2.0:
        s = 2.0
    ym, y0, y1, y2 = table[i - 1], table[i], table[i + 1], table[i + 2]
    return (
        -s * (s - 1.0) * (s - 2.0) / 6.0 * ym
        + (s + 1.0) * (s - 1.0) * (s - 2.0) / 2.0 * y0
        - (s + 1.0) * s * (s - 2.0) / 2.0 * y1
        + (s + 1.0) * s * (s - 1.0) / 6.0 * y2
    )


@kernel
def _report(
    ring: np.ndarray,
    dcring: np.ndarray,
    start: int,
    kern: np.ndarray,
    osc: np.ndarray,
    n_r: int,
    fconsts: np.ndarray,
    gp: np.ndarray,
    bias: np.ndarray,
    gc: np.ndarray,
    gi3: np.ndarray,
    gram: np.ndarray,
    taper: np.ndarray,
    pgram: np.ndarray,
    noise: np.ndarray,
    out: np.ndarray,
) -> None:
    """(K)-(E) from the M decimated samples ring[start:start+M] (oldest first): fills
    out = (nu, Re X, Im X, rocof, B, defined) at input sample n_r (anchor frame), then (U):
    updates the noise average ``noise`` (in place) and fills out[6:12] = the standard
    deviations of frequency, ROCOF, amplitude (peak), phase, offset and TVE (NaN when
    undefined)."""
    M = kern.shape[1]
    f0, nu_p0, nu_i0, step = fconsts[0], fconsts[2], fconsts[3], fconsts[4]
    # taps run m = m_lo .. m_lo + M - 1 over c_{q - m}: newest sample first
    p0r = p0i = p1r = p1i = p2r = p2i = b = 0.0
    last = start + M - 1
    for i in range(M):
        cr = ring[last - i, 0]
        ci = ring[last - i, 1]
        k0v = kern[0, i]
        k1v = kern[1, i]
        k2v = kern[2, i]
        p0r += k0v * cr
        p0i += k0v * ci
        p1r += k1v * cr
        p1i += k1v * ci
        p2r += k2v * cr
        p2i += k2v * ci
        b += k0v * dcring[last - i]
    p0 = complex(p0r, p0i)
    p1 = complex(p1r, p1i)
    p2 = complex(p2r, p2i)
    if not (abs(p0) > 0.0) or not math.isfinite(abs(p0)):
        out[5] = 0.0
        return
    # e^{-j 4 pi f0 n_r / fs} from the oscillator table
    P = osc.shape[0]
    ph = n_r % P
    e1 = complex(osc[ph, 0], -osc[ph, 1])
    e2 = e1 * e1
    q0, q1, q2 = p0, p1, p2
    nu = 0.0
    for _ in range(N_IMAGE_PASSES):  # (I) image cancellation passes [R]
        nu = (q1 / q0).imag / (2.0 * math.pi)
        x1 = q0 / _interp(gp, nu_p0, step, nu)
        nu_i = -2.0 * f0 - nu
        xi = x1.conjugate() * e2
        q0 = p0 - _interp(gi3[0], nu_i0, step, nu_i) * xi
        q1 = p1 - _interp(gi3[1], nu_i0, step, nu_i) * xi
        q2 = p2 - _interp(gi3[2], nu_i0, step, nu_i) * xi
        if not (abs(q0) > 0.0):
            out[5] = 0.0
            return
    r1 = q1 / q0
    nu = r1.imag / (2.0 * math.pi)  # (E)
    a2 = q2 / q0 - r1 * r1 - _interp(bias, nu_p0, step, nu)  # (B): d^2 log X / dt^2
    rocof = a2.imag / (2.0 * math.pi)
    x = q0 / (_interp(gp, nu_p0, step, nu) + 0.5 * a2 * _interp(gc, nu_p0, step, nu))  # (C)
    out[0] = nu
    out[1] = x.real
    out[2] = x.imag
    out[3] = rocof
    out[4] = b
    out[5] = 1.0 if (math.isfinite(nu) and math.isfinite(rocof) and math.isfinite(abs(x))) else 0.0
    for c in range(6, 12):
        out[c] = np.nan
    if out[5] == 0.0:
        return
    sig2 = _noise_update(ring, start, M, taper, pgram, f0 + nu, fconsts, noise)
    dn = _interp(gp, nu_p0, step, nu) + 0.5 * a2 * _interp(gc, nu_p0, step, nu)
    _report_std(q0, q1, q2, r1, dn, _interp(gc, nu_p0, step, nu), x, gram, sig2, out)


@kernel
def _noise_update(
    ring: np.ndarray,
    start: int,
    M: int,
    taper: np.ndarray,
    pgram: np.ndarray,
    f_hz: float,
    fconsts: np.ndarray,
    noise: np.ndarray,
) -> float:
    """(U) the noise variance sigma^2 of the raw samples: N_PROBES probes (the Nuttall taper
    modulated to raw frequencies (i + 1/2) f, halfway between the signal's harmonics, relative
    to the estimated f so that neither the tone nor its harmonics, the offset or the image
    fall in their main lobes) read the noise beside the tone in this window; their power over
    their gram, averaged over the probes and over reports (weights ``lambda^age``, the
    average in ``noise`` = (weighted sum, sum of weights)), is sigma^2. Returns it."""
    f_osc, lam, dstep = fconsts[0], fconsts[7], fconsts[8]
    last = start + M - 1
    acc = 0.0
    for k in range(N_PROBES):
        dk = (k + 0.5) * f_hz - f_osc  # the probe's frequency after demodulation
        w = 2.0 * math.pi * dk * dstep  # radians per decimated sample
        rot = complex(math.cos(w), math.sin(w))
        e = complex(1.0, 0.0)
        pr = complex(0.0, 0.0)
        for i in range(M):
            pr += taper[i] * e * complex(ring[last - i, 0], ring[last - i, 1])
            e *= rot
        g = pgram[0] + 2.0 * pgram[1] * math.cos(w)
        acc += (pr.real * pr.real + pr.imag * pr.imag) / (2.0 * g)
    noise[0] = lam * noise[0] + acc / N_PROBES
    noise[1] = lam * noise[1] + 1.0
    sig2: float = noise[0] / noise[1]
    return sig2


@kernel(inline="always")
def _qform(c0: complex, c1: complex, c2: complex, gram: np.ndarray) -> float:
    """c^H Gamma c for a real symmetric 3x3 Gamma: the variance of Re(c^T e) (and of Im) per
    unit sigma^2, for the kernels' noise e (E[e e^H] = 2 sigma^2 Gamma, E[e e^T] ~ 0)."""
    v: float = (
        gram[0, 0] * (c0.real * c0.real + c0.imag * c0.imag)
        + gram[1, 1] * (c1.real * c1.real + c1.imag * c1.imag)
        + gram[2, 2] * (c2.real * c2.real + c2.imag * c2.imag)
        + 2.0 * gram[0, 1] * (c0.conjugate() * c1).real
        + 2.0 * gram[0, 2] * (c0.conjugate() * c2).real
        + 2.0 * gram[1, 2] * (c1.conjugate() * c2).real
    )
    return v if v > 0.0 else 0.0


@kernel
def _report_std(
    q0: complex,
    q1: complex,
    q2: complex,
    r1: complex,
    dn: complex,
    gcv: complex,
    x: complex,
    gram: np.ndarray,
    sig2: float,
    out: np.ndarray,
) -> None:
    """(U) the estimates of (E) and (C) linearised in the kernels' noise (the image
    cancellation's and the tables' own dependence on nu left out: second order): out[6:12] =
    std of nu, ROCOF, amplitude (peak, sqrt 2 |X|), arg X, offset, and the RMS TVE
    ``sqrt(E |dX|^2) / |X|``."""
    inv = 1.0 / q0
    two_pi = 2.0 * math.pi
    # nu = Im(q1 / q0) / 2 pi
    out[6] = math.sqrt(sig2 * _qform(-r1 * inv, inv, 0j, gram)) / two_pi
    # a2 = q2/q0 - r1^2 - b: da2 = ca0 dq0 + ca1 dq1 + ca2 dq2; ROCOF = Im(a2) / 2 pi
    ca0 = (2.0 * r1 * r1 - q2 * inv) * inv
    ca1 = -2.0 * r1 * inv
    ca2 = inv
    out[7] = math.sqrt(sig2 * _qform(ca0, ca1, ca2, gram)) / two_pi
    # X = q0 / dn, dn = G + a2 G2 / 2
    s = -0.5 * gcv * q0 / (dn * dn)
    cx0 = 1.0 / dn + s * ca0
    cx1 = s * ca1
    cx2 = s * ca2
    mag = abs(x)
    u = x.conjugate() / mag
    out[8] = math.sqrt(2.0 * sig2 * _qform(u * cx0, u * cx1, u * cx2, gram))
    out[9] = math.sqrt(sig2 * _qform(u * cx0, u * cx1, u * cx2, gram)) / mag
    out[10] = math.sqrt(sig2 * gram[0, 0])  # b = sum_n h0[n] x_n: no sqrt 2, no demodulation
    out[11] = math.sqrt(2.0 * sig2 * _qform(cx0, cx1, cx2, gram)) / mag


@kernel
def pmu_kernel(
    x: np.ndarray,
    ring: np.ndarray,
    dcring: np.ndarray,
    istate: np.ndarray,
    fstate: np.ndarray,
    anchor: np.ndarray,
    noise: np.ndarray,
    kernels: np.ndarray,
    osc: np.ndarray,
    weights: np.ndarray,
    iconsts: np.ndarray,
    fconsts: np.ndarray,
    g_pass: np.ndarray,
    a2_bias: np.ndarray,
    g_chirp: np.ndarray,
    g_image: np.ndarray,
    noise_gram: np.ndarray,
    probe_taper: np.ndarray,
    probe_gram: np.ndarray,
    last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run (D)-(R) over block ``x``. Returns (out (N or 1, 6), reports (R, 14), sse,
    n_pred, new_ring, new_dcring, new_istate, new_fstate, new_anchor, new_noise) (``anchor``,
    the time anchor the class keeps, passes through unchanged; ``noise``, the (U) average).

    ``ring`` (2L, 2) holds the decimated c_j twice (so any window is contiguous), dcring
    (2L,) the decimated raw samples; ``iconsts`` = (D, M, m_lo, L); ``fconsts`` = (f0, fs,
    nu_pass0, nu_image0, table step, samples per report fs/Fs, min_amplitude). Output
    columns: frequency_hz, amplitude, phase_rad, offset, converged, rocof. Report rows:
    k, f, rocof, RMS magnitude, synchrophasor angle, amplitude (peak), phase_rad (sine,
    instantaneous), offset, then the std of frequency, ROCOF, amplitude, phase, offset and
    the RMS TVE (U). Pure: no input is modified."""
    D, M, m_lo, L = iconsts[0], iconsts[1], iconsts[2], iconsts[3]
    f0, fs, spr, min_amp = fconsts[0], fconsts[1], fconsts[5], fconsts[6]
    rg = ring.copy()
    dr = dcring.copy()
    ist = istate.copy()
    fst = fstate.copy()
    n, j, k_next, k0, held, defined = ist[0], ist[1], ist[2], ist[3], ist[4], ist[5]
    delta0, beta = fst[0], fst[1]
    acr, aci, anr, ani, dcc, dcn = fst[2], fst[3], fst[4], fst[5], fst[6], fst[7]
    f, A, B, rocof, conv = fst[8], fst[9], fst[11], fst[12], fst[13]
    cth, sth = fst[14], fst[15]
    n_in = x.shape[0]
    out = np.empty((1 if last_only else n_in, 6))
    cap = n_in // max(1, int(spr)) + 2
    reps = np.empty((cap, N_REPORT_COLUMNS))
    n_rep = 0
    est = np.zeros(12)
    nz = noise.copy()
    Q = weights.shape[0]
    ph = n % Q  # sample phase (weights) and decimation phase of sample n, then counted
    rho = n % D
    sse = 0.0
    n_pred = 0
    cstep = 1.0
    sstep = 0.0
    if held and defined:
        cstep = math.cos(2.0 * math.pi * f / fs)
        sstep = math.sin(2.0 * math.pi * f / fs)
    for i in range(n_in):
        xi = x[i]
        if held and defined:  # one-step prediction of the held model
            e = xi - (B + A * sth)
            sse += e * e
            n_pred += 1
        # (D) demodulate and accumulate the triangle
        acr += xi * weights[ph, 0]
        aci += xi * weights[ph, 1]
        anr += xi * weights[ph, 2]
        ani += xi * weights[ph, 3]
        dcc += xi * weights[ph, 4]
        dcn += xi * weights[ph, 5]
        if rho == D - 1:  # c_j complete
            slot = j % L
            rg[slot, 0] = acr
            rg[slot, 1] = aci
            rg[slot + L, 0] = acr
            rg[slot + L, 1] = aci
            dr[slot] = dcc
            dr[slot + L] = dcc
            acr, aci, dcc = anr, ani, dcn
            anr = ani = dcn = 0.0
            # reports whose newest tap is c_j (or that can never be made)
            while True:
                u = delta0 + (k_next - k0) * spr
                n_r = math.floor(u + 0.5)
                q = n_r // D
                newest = q - m_lo
                oldest = newest - M + 1
                if newest > j:
                    break
                if oldest < 1 or newest < j:  # window reaches before the anchor: skip
                    k_next += 1
                    continue
                ph_r = n_r - q * D
                _report(
                    rg,
                    dr,
                    oldest % L,
                    kernels[ph_r],
                    osc,
                    n_r,
                    fconsts,
                    g_pass[ph_r],
                    a2_bias[ph_r],
                    g_chirp[ph_r],
                    g_image[ph_r],
                    noise_gram[ph_r],
                    probe_taper[ph_r],
                    probe_gram[ph_r],
                    nz,
                    est,
                )
                held = 1
                tau = (u - n_r) / fs
                if est[5] != 0.0:
                    nu = est[0]
                    xr = complex(est[1], est[2]) * complex(
                        math.cos(2 * math.pi * nu * tau), math.sin(2 * math.pi * nu * tau)
                    )
                    mag = abs(xr)
                    rocof = est[3]
                    f = f0 + nu + rocof * tau
                    B = est[4]
                    defined = 1
                    conv = 1.0 if mag > min_amp else 0.0
                    arg = math.atan2(xr.imag, xr.real)
                    # phase of the nominal oscillator at u: 2 pi f0 u / fs (mod 2 pi)
                    nom = 2.0 * math.pi * ((f0 * u / fs) - math.floor(f0 * u / fs))
                    theta_r = arg + nom + 0.5 * math.pi  # sine convention
                    A = math.sqrt(2.0) * mag
                    if n_rep < cap:
                        reps[n_rep, 0] = k_next
                        reps[n_rep, 1] = f
                        reps[n_rep, 2] = rocof
                        reps[n_rep, 3] = mag
                        reps[n_rep, 4] = wrap_pi(arg - beta)
                        reps[n_rep, 5] = A
                        reps[n_rep, 6] = wrap_pi(theta_r)
                        reps[n_rep, 7] = B
                        for c in range(6):  # (U): frequency, ROCOF, amplitude, phase, offset, TVE
                            reps[n_rep, 8 + c] = est[6 + c]
                        n_rep += 1
                    # rotor at the current sample n (predicts sample n + 1 after a step)
                    th = theta_r + 2.0 * math.pi * f * (n - u) / fs
                    cth = math.cos(th)
                    sth = math.sin(th)
                    cstep = math.cos(2.0 * math.pi * f / fs)
                    sstep = math.sin(2.0 * math.pi * f / fs)
                else:
                    defined = 0
                    f = A = B = rocof = conv = 0.0
                    cth, sth = 1.0, 0.0
                    if n_rep < cap:
                        reps[n_rep, 0] = k_next
                        for c in range(1, N_REPORT_COLUMNS):
                            reps[n_rep, c] = np.nan
                        n_rep += 1
                k_next += 1
            j += 1
        if not (last_only and i != n_in - 1):
            row = 0 if last_only else i
            if held and defined:
                out[row, 0] = f
                out[row, 1] = A
                out[row, 2] = math.atan2(sth, cth) if (not last_only or i == n_in - 1) else 0.0
                out[row, 3] = B
                out[row, 4] = conv
                out[row, 5] = rocof
            else:
                for c in range(4):
                    out[row, c] = np.nan
                out[row, 4] = 0.0
                out[row, 5] = np.nan
        # advance the rotor to sample n + 1
        if held and defined:
            c2 = cth * cstep - sth * sstep
            sth = sth * cstep + cth * sstep
            cth = c2
        n += 1
        ph = cyclic_next(ph, Q)
        rho = cyclic_next(rho, D)
    ist2 = np.array([n, j, k_next, k0, held, defined], dtype=np.int64)
    fst2 = np.array([delta0, beta, acr, aci, anr, ani, dcc, dcn, f, A, 0.0, B, rocof, conv, cth, sth])
    return out, reps[:n_rep].copy(), sse, n_pred, rg, dr, ist2, fst2, anchor.copy(), nz


N_TRANSITION = 9


def _fresh_transition() -> np.ndarray:
    """(T)'s state at the start: no last report."""
    return np.zeros(N_TRANSITION)


@kernel
def transition_kernel(
    mag: np.ndarray, freq: np.ndarray, rocof: np.ndarray, trans: np.ndarray, fs_rep: float, n_hold: int, min_amp: float
) -> tuple[np.ndarray, np.ndarray]:
    """(T) over reports in order: their converged and the new state (``trans`` is not
    modified; layout in :meth:`Pmu._converged`). Slot 7 is the last report's converged."""
    st = trans.copy()
    n = mag.shape[0]
    conv = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        m, f, r = mag[i], freq[i], rocof[i]
        if not (math.isfinite(m) and math.isfinite(f) and math.isfinite(r)):
            for c in range(N_TRANSITION):
                st[c] = 0.0  # an undefined report: start over
            continue
        if st[4] == 0.0:  # the first report: nothing to check it against
            st[3] = n_hold - 1.0
        else:
            dm = abs(m / st[0] - 1.0) if st[0] > 0.0 else math.inf
            df = abs(f - st[1] - st[2] / fs_rep)
            tm = max(TRANSITION_MAG_FLOOR, TRANSITION_K * st[5])
            tf = max(TRANSITION_FREQ_FLOOR_HZ, TRANSITION_K * st[6])
            st[8] += 1.0
            w = max(TRANSITION_ALPHA, 1.0 / st[8])  # the plain mean of the first reports, then a running one
            st[5] += w * (min(dm, tm) - st[5])
            st[6] += w * (min(df, tf) - st[6])
            st[3] = 0.0 if (dm > tm or df > tf) else min(st[3] + 1.0, float(n_hold))
        st[0], st[1], st[2], st[4] = m, f, r, 1.0
        conv[i] = st[3] >= n_hold and m > min_amp
        st[7] = 1.0 if conv[i] else 0.0
    return conv, st


@register
class Pmu(Estimator[PmuParams], kernel=pmu_kernel, name="pmu"):
    """C37.118.1 synchrophasor (RMS magnitude, phase vs nominal cosine), frequency and ROCOF on the reporting grid: demodulation + derivative filter bank + image cancellation (M or P class)"""

    reports_on_grid = True
    paper = None
    example_sample_rate_hz = 10_000.0
    example_params: ClassVar[dict[str, Any]] = {"nominal_frequency_hz": 50, "reporting_rate_hz": 50}

    def _check_params(self) -> None:
        p = self.params
        self.auto = p.nominal_frequency_hz == "auto"
        for f0 in (50, 60) if self.auto else (int(p.nominal_frequency_hz),):
            self._configure(f0)  # raises for a rate or sample rate that does not fit
        # 'auto': the 50 Hz design (the longer window) until the signal says which
        self._nominal = 0 if self.auto else int(p.nominal_frequency_hz)
        self._pending = np.zeros(0)
        self._pending_t0 = np.array([0, 0], dtype=np.int64)  # t0_ns of pending[0], known (0/1)
        self._transition = _fresh_transition()  # (T), see _converged
        self._configure(self._nominal or 50)

    def _configure(self, f0: int) -> None:
        p = self.params
        rate = f0 if p.reporting_rate_hz is None else int(p.reporting_rate_hz)
        allowed = (M_CLASS_RATES if p.performance_class == "M" else P_CLASS_RATES)[f0]
        if rate not in allowed:
            raise ParameterError(
                f"reporting_rate_hz: expected one of {list(allowed)} for class {p.performance_class} at {f0} Hz, "
                f"got {rate}"
            )
        self.reporting_rate = rate
        self.design = design(self.sample_rate_hz, f0, rate, p.performance_class)
        self._n_hold = math.ceil(self.design.window_s * rate - 1e-9)  # (T): reports in one kernel length

    @property
    def memory_samples(self) -> int:
        """A report depends on the samples within half its kernel (``window_s / 2``) of the
        report time, plus one decimation step of the triangle (D) before it."""
        d = self.design
        return math.ceil(0.5 * d.window_s * self.sample_rate_hz) + d.decimation

    @property
    def lookahead_samples(self) -> int:
        """Samples after a report's time that the report depends on (its kernel's far half
        and the triangle: ``design.latency_s``); the pipeline judges its validity up to there."""
        return math.ceil(self.design.latency_s * self.sample_rate_hz - 1e-9)

    def _setup(self) -> None:
        d = self.design
        self._ring_len = d.n_taps + 2
        self._iconsts = np.array([d.decimation, d.n_taps, d.m_lo, self._ring_len], dtype=np.int64)
        self._fconsts = np.array(
            [
                d.f_osc,
                d.fs,
                d.nu_pass0,
                d.nu_image0,
                TABLE_STEP_HZ,
                d.fs / d.reporting_rate,
                self.params.min_amplitude,
                math.exp(-1.0 / (NOISE_TIME_CONSTANT_S * d.reporting_rate)),  # (U) the reports' weight lambda
                d.decimation / d.fs,  # (U) a decimated sample's duration (s)
            ]
        )
        self._constants = (
            d.kernels, d.osc, d.weights, self._iconsts, self._fconsts, d.g_pass, d.a2_bias, d.g_chirp, d.g_image,
            d.noise_gram, d.probe_taper, d.probe_gram,
        )  # fmt: skip

    # ---- time anchor ----------------------------------------------------------------------
    def _anchor_state(self, anchor_ns: int) -> dict[str, np.ndarray]:
        fs_rep = self.reporting_rate
        f0 = self.design.f0
        k0 = -((-anchor_ns * fs_rep) // 1_000_000_000)  # ceil(anchor * Fs / 1e9)
        delta0_ns = (k0 * 1_000_000_000 - anchor_ns * fs_rep) / fs_rep  # exact rational -> float
        delta0 = delta0_ns * 1e-9 * self.sample_rate_hz
        beta = 2.0 * math.pi * (((f0 * anchor_ns) % 1_000_000_000) / 1e9)
        istate = np.array([0, 0, k0, k0, 0, 0], dtype=np.int64)
        fstate = np.zeros(N_FSTATE)
        fstate[0] = delta0
        fstate[1] = beta
        fstate[14] = 1.0
        return {
            "ring": np.zeros((2 * self._ring_len, 2)),
            "dc_ring": np.zeros(2 * self._ring_len),
            "counters": istate,
            "values": fstate,
            "anchor_ns": np.array([anchor_ns, 0], dtype=np.int64),  # anchor, anchored by a t0 (0/1)
            "noise": np.zeros(2),
        }

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``ring`` (2L, 2): the decimated c_j (re, im), each written twice so that a window
        is contiguous; ``dc_ring`` (2L,): the decimated raw samples; ``counters`` (6,) int64:
        samples since the anchor, next decimated index, next grid index, first grid index
        after the anchor, report held, report defined; ``values`` (16,): see ``N_FSTATE``;
        ``anchor_ns`` (2,) int64: the anchor (ns since the epoch) and whether a block's
        time set it (1) or it is the default t = 0 (0); ``noise`` (2,): (U) the reports' noise
        average, its weighted sum and the sum of its weights."""
        return self._anchor_state(0)

    def _expected_t0_ns(self, st: dict[str, np.ndarray]) -> int:
        """Where the next block starts if the stream is contiguous (ns since the epoch)."""
        return int(st["anchor_ns"][0]) + round(int(st["counters"][0]) * 1e9 / self.sample_rate_hz)

    def _state_for_block(self, st: dict[str, np.ndarray], t0_ns: int | None) -> dict[str, np.ndarray]:
        """The state to run the block from: ``st``, or a fresh one anchored at ``t0_ns`` on
        the first timed block and after a gap in time."""
        if t0_ns is None:
            return st
        t0_ns = int(t0_ns)
        n = int(st["counters"][0])
        anchored = int(st["anchor_ns"][1]) != 0
        if n == 0 and not anchored:
            s = self._anchor_state(t0_ns)
            s["anchor_ns"][1] = 1
            return s
        half_sample_ns = 0.5e9 / self.sample_rate_hz
        if abs(t0_ns - self._expected_t0_ns(st)) > half_sample_ns:  # a gap in time: restart on the grid
            s = self._anchor_state(t0_ns)
            s["anchor_ns"][1] = 1
            return s
        return st

    # ---- the kernel ----------------------------------------------------------------------
    def _run_timed(
        self, samples: np.ndarray, state: dict[str, np.ndarray], last_only: bool, t0_ns: int | None
    ) -> tuple[Track, dict[str, np.ndarray]]:
        trans = self._transition
        if self._nominal == 0:
            track, new_state = self._run_undecided(samples, state, last_only, t0_ns)
            trans = _fresh_transition()  # the estimator starts once the nominal frequency is found
        else:
            st = self._state_for_block(state, t0_ns)
            if st is not state:  # anchored afresh (the first timed block, a gap in time): (T) starts over
                trans = _fresh_transition()
            track, new_state = self._run_decided(samples, st, last_only)
        track, self._transition = self._converged(track, trans, last_only)
        return track, new_state

    def _converged(self, track: Track, trans: np.ndarray, last_only: bool) -> tuple[Track, np.ndarray]:
        """(T) over the block's reports, in order: their ``converged``, and the transition
        state after them (``trans`` is not modified). ``trans`` (9,): the last report's RMS
        magnitude, frequency and ROCOF, reports since the last transition, whether there is
        a last report (0/1), the running scales of the magnitude's and the frequency's
        departures, the last report's converged (0/1), departures checked (the scales' weights)."""
        reports = track.reports
        st = trans
        if reports is not None and reports.n_reports:
            tr = reports.track
            freq = tr.frequency_hz[:, 0]
            rocof = tr.rocof_hz_per_s[:, 0] if tr.rocof_hz_per_s is not None else np.zeros(freq.shape)
            tr.converged, st = transition_kernel(
                np.ascontiguousarray(tr.extras["synchrophasor_magnitude"]),
                np.ascontiguousarray(freq),
                np.ascontiguousarray(rocof),
                trans,
                float(self.reporting_rate),
                self._n_hold,
                self.params.min_amplitude,
            )
        return track, st

    def _run_decided(
        self, samples: np.ndarray, state: dict[str, np.ndarray], last_only: bool
    ) -> tuple[Track, dict[str, np.ndarray]]:
        track, new_state = self._run(samples, state, last_only)
        d = self.design
        if d.f_osc != d.f0 and track.reports is not None and track.reports.n_reports:
            self._refer_to_nominal(track.reports, int(new_state["anchor_ns"][0]))
        return track, new_state

    # ---- nominal frequency from the signal ('auto') ----------------------------------------
    @property
    def detection_samples(self) -> int:
        """Samples the nominal frequency is found from ('auto'): 0.2 s, ten cycles of 50 Hz."""
        return max(1, round(DETECTION_S * self.sample_rate_hz))

    def _run_undecided(
        self, samples: np.ndarray, state: dict[str, np.ndarray], last_only: bool, t0_ns: int | None
    ) -> tuple[Track, dict[str, np.ndarray]]:
        """'auto' before the nominal frequency is known: the samples are held back and judged
        in consecutive detection windows (aligned on the first held sample, so the decision
        does not depend on how the stream is cut into blocks). Leading silent windows are
        dropped; a window the signal starts in is not judged (the next one is). A spectral peak below 54 Hz says 50, above 56 Hz 60; between, both are
        within the M-class range of the signal (f0 +- 5 Hz) and the next windows decide
        which way it goes (a 1 Hz/s ramp from 55 Hz), for up to ``AMBIGUOUS_S`` of signal
        (then 50 up to 55 Hz, else 60: a signal steady at 55 Hz is
        at the edge of both ranges and is taken as 50 + 5). Once decided, the estimator is the one of that
        nominal frequency, anchored at the first held sample, run over the held samples and
        the block: its reports are those it would have made configured from the start, only
        later."""
        fs = self.sample_rate_hz
        pending, pt0 = self._pending, self._pending_t0
        if pending.size and t0_ns is not None and pt0[1]:
            expected = int(pt0[0]) + round(pending.size * 1e9 / fs)
            if abs(int(t0_ns) - expected) > 0.5e9 / fs:  # a gap in time: what was held is stale
                pending = pending[:0]
        if pending.size == 0:
            pt0 = np.array([0 if t0_ns is None else int(t0_ns), 0 if t0_ns is None else 1], dtype=np.int64)
        data = np.concatenate([pending, samples])
        n_win = self.detection_samples
        start, f0 = 0, 0
        pos = (pending.size // n_win) * n_win  # windows before this were judged (ambiguous)
        while data.size - pos >= n_win and f0 == 0:
            win = data[pos : pos + n_win]
            peak = spectral_peak_hz(win, fs)
            if math.isnan(peak):  # silent
                if pos == start:
                    start = pos + n_win
            elif _steady_level(win):  # not a window the signal starts or stops in
                f0 = 50 if peak < 54.0 else 60 if peak > 56.0 else 0
                if f0 == 0 and (pos + n_win - start) >= AMBIGUOUS_S * fs:
                    f0 = 50 if peak <= 55.0 else 60  # 55 Hz exactly is both f0 +- 5: 50
            pos += n_win
        t_start = int(pt0[0]) + round(start * 1e9 / fs)
        if f0 == 0:
            self._pending = data[start:].copy()
            self._pending_t0 = np.array([t_start, pt0[1]], dtype=np.int64)
            return self._undefined(samples, last_only), state
        self._decide(f0)
        fresh = self._state_for_block(self._initial_state(), t_start if pt0[1] else None)
        rest = data[start:]
        track, new_state = self._run_decided(rest, fresh, last_only)
        n_block = samples.shape[0]
        if not last_only and rest.size > n_block:  # the held samples' rows are not this block's
            reports = track.reports
            track = track.rows(slice(rest.size - n_block, None))
            track.reports = reports
        elif not last_only and rest.size < n_block:  # part of the block was a dropped silent window
            track = concat_tracks([self._undefined(samples[: n_block - rest.size], False), track])
        self._pending = np.zeros(0)
        self._pending_t0 = np.array([0, 0], dtype=np.int64)
        return track, new_state

    def _undefined(self, samples: np.ndarray, last_only: bool) -> Track:
        out = np.full((1 if last_only else samples.shape[0], 6), np.nan)
        out[:, 4] = 0.0
        return self._track((out, np.empty((0, N_REPORT_COLUMNS)), 0.0, 0), samples)

    def _decide(self, f0: int) -> None:
        self._nominal = f0
        self._configure(f0)
        self._setup()

    def reset(self) -> None:
        self._transition = _fresh_transition()
        if self.auto:
            self._nominal = 0
            self._pending = np.zeros(0)
            self._pending_t0 = np.array([0, 0], dtype=np.int64)
            self._configure(50)
            self._setup()
        super().reset()

    def get_state(self) -> dict[str, Any]:
        snap = super().get_state()
        snap["transition"] = encode_array(self._transition)
        if self.auto:
            snap["auto"] = {
                "nominal_frequency_hz": self._nominal,
                "pending": encode_array(self._pending),
                "pending_t0_ns": encode_array(self._pending_t0),
            }
        return snap

    def set_state(self, snapshot: Mapping[str, Any]) -> None:
        """As :meth:`Estimator.set_state`; a snapshot from a build before the noise average
        (U) existed is accepted, that average starting afresh."""
        state = snapshot.get("state")
        if isinstance(state, Mapping) and "ring" in state and "noise" not in state:
            snapshot = {**snapshot, "state": {**state, "noise": encode_array(np.zeros(2))}}
        trans = _fresh_transition()  # snapshots of earlier builds have none: (T) starts over
        if "transition" in snapshot:
            trans = decode_array(snapshot["transition"])
            if trans.shape != (N_TRANSITION,) or trans.dtype != np.float64:
                raise ParameterError(
                    f"state transition: expected float64 ({N_TRANSITION},), got {trans.dtype}{trans.shape}"
                )
        if not self.auto:
            super().set_state(snapshot)
            self._transition = trans
            return
        auto = snapshot.get("auto")
        if not isinstance(auto, Mapping) or auto.get("nominal_frequency_hz") not in (0, 50, 60):
            raise ParameterError(
                f"state auto: expected the nominal frequency found (0, 50 or 60) and the held samples, got {auto!r}"
            )
        pending, pt0 = decode_array(auto["pending"]), decode_array(auto["pending_t0_ns"])
        if pending.ndim != 1 or pending.dtype != np.float64 or pt0.shape != (2,) or pt0.dtype != np.int64:
            raise ParameterError("state auto: expected float64 (n,) held samples and an int64 (2,) start time")
        before = self._nominal
        self._decide(int(auto["nominal_frequency_hz"]) or 50)
        self._nominal = int(auto["nominal_frequency_hz"])
        try:
            super().set_state(snapshot)
        except ParameterError:
            self._decide(before or 50)
            self._nominal = before
            raise
        self._pending, self._pending_t0 = pending, pt0
        self._transition = trans

    def _refer_to_nominal(self, reports: GridReports, anchor_ns: int) -> None:
        """The synchrophasor angle of reports made with an oscillator off f0 (a rate that is
        not a whole number of hertz, :func:`oscillator`), referred to the nominal cosine: the
        kernel refers it to the oscillator's, which has turned ``2 pi (f_osc - f0) (t_k -
        t_anchor)`` ahead of it by the report time ``t_k = k / Fs``."""
        d = self.design
        fs_rep = self.reporting_rate
        # t_k - t_anchor in ns, exact in integers, then seconds
        base = anchor_ns * fs_rep  # beyond int64: Python integers
        dt_s = np.array([(int(k) * 1_000_000_000 - base) / (fs_rep * 1e9) for k in reports.index.tolist()])
        angle = reports.track.extras["synchrophasor_angle_rad"]
        turned = angle + 2.0 * math.pi * (d.f_osc - d.f0) * dt_s
        reports.track.extras["synchrophasor_angle_rad"] = np.angle(np.exp(1j * turned))

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out, reps, sse, n_pred = outputs
        residual = math.sqrt(sse / n_pred) if n_pred else math.nan
        return track_from_columns(
            out,
            sse,
            n_pred,
            rocof_hz_per_s=out[:, 5:6],
            reports=GridReports(
                index=reps[:, 0].astype(np.int64),
                reporting_rate_hz=self.reporting_rate,
                track=Track(
                    frequency_hz=reps[:, 1:2],
                    amplitude=reps[:, 5:6],
                    phase_rad=reps[:, 6:7],
                    offset=reps[:, 7],
                    converged=reps[:, 3] > self._fconsts[6],
                    residual_rms=residual,
                    extras={
                        "synchrophasor_magnitude": reps[:, 3],
                        "synchrophasor_angle_rad": reps[:, 4],
                        "std_rocof_hz_per_s": reps[:, 9],
                        "std_tve": reps[:, 13],
                    },
                    rocof_hz_per_s=reps[:, 2:3],
                    std=TrackStd(
                        frequency_hz=reps[:, 8:9],
                        amplitude=reps[:, 10:11],
                        phase_rad=reps[:, 11:12],
                        offset=reps[:, 12],
                    ),
                ),
            ),
        )

    @classmethod
    def params_for(cls, sample_rate_hz: float, hints: dict[str, Any]) -> dict[str, Any]:
        f0s = hints.get("nominal_frequency_hz") or (50.0,)
        f0 = round(float(f0s[0]))
        if f0 not in (50, 60) or hints.get("n_components", 1) != 1 or hints.get("n_inputs", 1) != 1:
            raise ParameterError("pmu: one tone at a 50 or 60 Hz nominal frequency only")
        rate = hints.get("reporting_rate_hz") or f0
        rate = round(float(rate))
        if rate not in M_CLASS_RATES[f0]:
            rate = f0
        return {"nominal_frequency_hz": f0, "reporting_rate_hz": rate}
