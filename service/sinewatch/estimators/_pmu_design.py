"""The ``pmu`` estimator's maths at design time: the demodulation, the kernel bank and
the tables its kernels read, derived once per (fs, f0, Fs, class); and the nominal frequency
found from the signal ('auto'). The compiled per-sample kernels are in ``_pmu_kernels``, the
thin estimator class and its parameters in ``pmu``.

What is estimated (the synchrophasor of C37.118.1-2011 clause 4.2 eq. (1)-(3), frequency and
ROCOF of clause 4.3 eq. (4)-(5)) is stated at the top of ``pmu``. How: quadrature demodulation
at f0, a bank of one smooth lowpass kernel and its first two time derivatives read at the
report time, and iterative cancellation of the negative-frequency image. References:

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
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

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


def _bank_response(
    kernels: np.ndarray, m: np.ndarray, d: int, fs: float, nu: np.ndarray, *more: np.ndarray
) -> list[np.ndarray]:
    """(D, K, len(nu)) complex: the exact response of the sampled kernels (after the CIC2)
    to a tone at nu, per input-sample phase rho: sum_m K[rho, k, m] e^{-j 2 pi nu t_m} A(nu).
    Exact (not the continuous W): deep in the stopband, where the image lies, the sampled
    kernels' aliases are comparable to W itself and the derivative relations of (K') fail.
    One array for ``kernels`` and one for each of ``more`` (other kernels on the same taps):
    the complex exponentials, most of the design's time (seconds at 50 kHz), are computed once
    for all of them."""
    banks = (kernels, *more)
    outs = [np.empty((k.shape[0], k.shape[1], nu.size), dtype=np.complex128) for k in banks]
    a = _cic2(nu, d, fs)
    for rho in range(kernels.shape[0]):
        t = (m * d + rho) / fs
        e = np.exp(-2j * np.pi * np.outer(t, nu))
        for k, out in zip(banks, outs, strict=True):
            out[rho] = (k[rho] @ e) * a
    return [np.ascontiguousarray(out) for out in outs]


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
    t2 = np.stack([((m * d + rho) / fs) ** 2 for rho in range(d)])  # t_m^2 per phase
    bank, chirp = _bank_response(kernels, m, d, fs, nu_pass, kernels[:, :1] * t2[:, None, :])
    g_chirp = np.ascontiguousarray(chirp[:, 0])
    g_pass = np.ascontiguousarray(bank[:, 0])
    r1 = bank[:, 1] / bank[:, 0]
    a2_bias = np.ascontiguousarray(bank[:, 2] / bank[:, 0] - r1 * r1)
    [g_img] = _bank_response(kernels, m, d, fs, nu_img)
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


def steady_level(x: np.ndarray) -> bool:
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
