"""Harmonic analyser after IEC 61000-4-7: synchronised 10/12-cycle windows, harmonics up to
the 50th, harmonic groups and subgroups, interharmonic groups and centred subgroups, THD,
THDG and THDS.

References (the clause numbers are those of the consolidated edition as recalled here;
check the standard before quoting compliance: this is a model of the method, not a
certified instrument):

* [4-7] IEC 61000-4-7:2002+AMD1:2008, "Electromagnetic compatibility (EMC) - Part 4-7:
  Testing and measurement techniques - General guide on harmonics and interharmonics
  measurements and instrumentation, for power supply systems and equipment connected
  thereto". Clause 3.2 (harmonics: component, group, subgroup, THD, THDG, THDS), clause
  3.3 (interharmonics: component, group, centred subgroup), clause 4 (the 10/12-cycle
  rectangular window synchronised to the supply, maximum synchronisation error
  +-0.03 %), clause 5.5.1 (the grouping of the DFT output).
* [4-30] IEC 61000-4-30:2015, "Testing and measurement techniques - Power quality
  measurement methods", clause 4.4/4.5 (the 10/12-cycle basic interval and its
  resynchronisation at every 10-min tick of the absolute clock, "overlap 1").
* [K] J. F. Kaiser, "Nonrecursive digital filter design using the I0-sinh window
  function", Proc. IEEE ISCAS 1974, pp. 20-23 (the window of the interpolation kernel);
  [SM] J. O. Smith and P. Gossett, "A flexible sampling-rate conversion method", Proc.
  IEEE ICASSP 1984, pp. 19.4.1-19.4.4 (band-limited interpolation with a windowed sinc).
* [RV] D. C. Rife and G. A. Vincent, "Use of the discrete Fourier transform in the
  measurement of frequencies and levels of tones", Bell System Technical Journal 49(2),
  197-228, 1970 (the class I cosine-sum windows, maximum sidelobe decay); [AS] D. Agrez,
  "Weighted multipoint interpolated DFT to improve amplitude estimation of multifrequency
  signal", IEEE Trans. Instrum. Meas. 51(2), 287-292, 2002 (the three-point interpolation
  for those windows).

The method, per window (one report per window):

(W)  The window is ``T_N = N / f_1`` seconds with ``N = 10`` at 50 Hz and ``N = 12`` at
     60 Hz [4-7 cl. 4]: exactly N cycles of the *measured* fundamental ``f_1``. At a
     sample rate ``f_s`` that is ``L = N f_s / f_1`` samples, in general not an integer.
     The window is therefore **resampled**: the ``M = N ceil(f_s / f_nom)`` points
     ``t_m = t_start + m T_N / M`` (m = 0..M-1) are interpolated from the samples, so that
     the DFT of the M points has its bin ``k`` exactly at ``k f_1 / N``: harmonic ``h`` is
     bin ``k = h N`` with no leakage and no picket-fence error, and the window length
     error is the error of ``f_1`` (below 1e-8 relative, against the +-0.03 % allowed).
(I)  Band-limited interpolation [SM]: ``y(t_m) = sum_{j=-R+1}^{R} x_{i+j} sinc(mu - j)
     w((mu - j) / R)`` with ``i = floor(p_m)``, ``mu = p_m - i``, ``p_m`` the position of
     ``t_m`` in samples, ``sinc(u) = sin(pi u)/(pi u)``, ``R = 16`` and the Kaiser window
     ``w(v) = I0(beta sqrt(1 - v^2)) / I0(beta)`` [K] with ``beta = 10``; the 2R taps are
     tabulated for ``mu = p / P``, P = 2048 (a polyphase table, [SM]), and interpolated
     linearly between two rows (error below 1e-7 of full scale).
     The kernel passes up to 0.4 f_s (the 51st harmonic of 69 Hz at 10 kHz is 0.35 f_s)
     and the images of that band lie above 0.6 f_s; measured error (tests): below 2e-6
     of the fundamental on the 50th harmonic.
(F)  The fundamental is measured on the whole window, by fixed-point iteration from the
     previous window's value: resample at ``f_a`` (W, I); weight the M points with the
     Rife-Vincent class I window of H = 4 terms [RV], ``w_m = sin^6(pi m / M)``
     (cosine-sum coefficients 5/16, 15/32, 3/16, 1/32; sidelobes fall as ``d^-7`` with
     the distance ``d`` in bins); take its DFT at the bins of the fundamental and its two
     neighbours, ``W_{N+d} = sum_m w_m y_m exp(-j 2 pi (N + d) m / M)``, d = -1, 0, 1; the
     fundamental lies ``delta`` bins above bin N, with the three-point interpolation of
     [AS] for that window, ``delta = H (|W_{N+1}| - |W_{N-1}|) / (|W_{N-1}| + 2 |W_N| +
     |W_{N+1}|)`` (exact for a lone tone to 2e-8 relative, measured), so
     ``f_1 = f_a (1 + delta / N)``. Repeat from ``f_1`` until ``|f_1 - f_a| <= 1e-9 f_a``
     (2-3 passes; at most 8; the estimate is clamped to 0.85-1.15 f_nom, the range of
     [4-30] class A). The report's window is the last resampling; its ``frequency_hz``
     is the ``f_a`` it spans.
     Why over the whole window and windowed: at the fixed point every harmonic and the DC
     sit on whole bins, where the cosine-sum window puts nothing into bins N-1..N+1
     (its transform is zero at whole bins beyond 3), so they do not bias the estimate
     whatever their level; an interharmonic ``d`` bins from the fundamental adds at most
     about ``|sinc d| prod_{i=1}^{3} i^2 / (d^2 - i^2)`` of its amplitude to those bins:
     1.3e-4 at d = 5.5 (an interharmonic at 1.55 f_1), 9e-7 at d = 10.5 (2.05 f_1)
     (measured, 5 % interharmonics off the bins from 103.7 to 2471.9 Hz: the frequency
     within 2.7e-6 Hz; tests). Within 4 bins of the fundamental (below about 1.4 f_1),
     an interharmonic is inside the window's main lobe and does bias it: 5 % at 77.7 Hz
     beside 60.2 Hz moves it by 42 mHz, at 77.7 Hz beside 50 Hz by 0.2 mHz. The
     one-cycle phasors this replaces took in an interharmonic at 2.5 f_1 through the
     one-cycle DFT's sidelobes (up to 1.5 mHz with 1.5 % of it, depending on its phase),
     enough to smear 0.04 % of the fundamental into interharmonic group 1.
(D)  DFT: ``X_k = (1/M) sum_m y_m exp(-j 2 pi k m / M)`` (numpy ``rfft``); the RMS value of
     spectral component k [4-7 cl. 3.2/3.3]: ``C_k = sqrt(2) |X_k|`` for k >= 1,
     ``C_0 = |X_0|`` (the DC value). Phase, sine convention like the rest of sinewatch
     (``c_k sin(2 pi k t / T_N + phi_k)``): ``phi_k = arg X_k + pi / 2`` at the window
     start; a harmonic (k = h N) has the same phase at the window end, N cycles later.
(H)  Harmonic component of order h [4-7 3.2]: ``C_h = C_{hN}`` (``harmonic_rms[h]``).
(G)  Harmonic group [4-7 3.2, 5.5.1]: ``G_g,h^2 = C_{hN-N/2}^2 / 2 + sum_{i=-N/2+1}^{N/2-1}
     C_{hN+i}^2 + C_{hN+N/2}^2 / 2`` (N/2 = 5 at 50 Hz, 6 at 60 Hz).
(S)  Harmonic subgroup [4-7 3.2, 5.5.1]: ``G_sg,h^2 = sum_{i=-1}^{1} C_{hN+i}^2``.
(IG) Interharmonic group of order n (between harmonics n and n+1) [4-7 3.3]:
     ``C_ig,n^2 = sum_{i=1}^{N-1} C_{nN+i}^2``.
(IS) Interharmonic centred subgroup [4-7 3.3, 5.5.1]: ``C_isg,n^2 = sum_{i=2}^{N-2}
     C_{nN+i}^2`` (the bins next to the harmonics are left to the harmonic subgroups).
(T)  ``THD = sqrt(sum_{h=2}^{H} (C_h / C_1)^2)``, ``THDG`` the same with ``G_g,h``,
     ``THDS`` the same with ``G_sg,h`` [4-7 3.2]; ``H = 40``, the order [4-7] sets for
     these ratios (``THD_MAX_ORDER``; lower when ``max_harmonic`` is lower), whatever the
     highest order reported: a 1 % 45th harmonic is in ``harmonic_rms`` but not in THD.
     All are ratios (multiply by 100 for percent); null when the fundamental is zero.

Order 0 of the harmonic arrays is the DC value ``C_0`` (groups and subgroups included:
IEC defines none there). ``rms`` is the true RMS over the window, ``sqrt(mean y_m^2)``.

Windows follow one another without gap [4-7 cl. 4, 4-30 4.4]: the next starts where the
last ended, except at a 10-min tick of the absolute clock (``resync_interval_s``): the
window that contains the tick runs to its end ("overlap 1" [4-30 4.5]) and the next one
starts at the tick, so the 10-min aggregates (:mod:`sinewatch.power_quality.aggregation`)
start on the tick. The first window of a stream starts ``R`` samples in (the interpolator
needs ``R`` samples either side), and a report comes out once ``R`` samples past the
window end have arrived. A block whose first-sample time is not where the last block
ended (more than half a sample off) starts a new stream: the partial window is dropped
and the next report says ``gap``.

Multi-channel input (``n_channels > 1``, one column per channel, e.g. the three phases)
is analysed on one window grid synchronised to ``reference_channel``, so the phases of
different channels compare (symmetrical components, :mod:`.sequence`).

Cost: about three resamplings (``2 R`` multiply-adds per point, plus 6 for the three
windowed bins of (F)) and one ``rfft`` of M points per channel and window; ``python -m sinewatch.power_quality.speed`` measures it
against a plain ``numpy.fft.rfft`` of the same windows.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from sinewatch.estimators.base import checked_sample_rate, decode_array, state_snapshot
from sinewatch.schemas.errors import InputError, InputTypeError, ParameterError

STATE_FORMAT_VERSION = 1
HALF_TAPS = 16  # R in (I)
KAISER_BETA = 10.0  # beta in (I)
TABLE_PHASES = 2048  # P, rows of the polyphase kernel table of (I)
FREQUENCY_RANGE = (0.85, 1.15)  # x f_nom, the clamp of (F)
FREQUENCY_TOLERANCE = 1e-9  # relative, the stop test of (F)
MAX_ITERATIONS = 8
THD_MAX_ORDER = 40  # H of (T)
SYNC_TERMS = 4  # H of the Rife-Vincent class I window of (F)
NS_PER_S = 1_000_000_000


class HarmonicParams(BaseModel):
    """Parameters of :class:`HarmonicAnalyser`: frozen, unknown keys rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    nominal_frequency_hz: float = Field(
        50.0, description="Nominal supply frequency: 50 Hz (10-cycle windows) or 60 Hz (12-cycle windows)"
    )
    max_harmonic: int = Field(
        50, ge=2, le=50, description="Highest harmonic order reported (THD, THDG, THDS stop at min(40, this))"
    )
    n_channels: int = Field(1, ge=1, le=16, description="Columns analysed on one common window grid")
    reference_channel: int = Field(0, ge=0, description="Column whose fundamental synchronises the windows")
    resync_interval_s: float | None = Field(
        600.0,
        gt=0,
        allow_inf_nan=False,
        description="Restart the window grid at every multiple of this many seconds of absolute time "
        "(IEC 61000-4-30: 600, the 10-min tick); null: never",
    )

    @model_validator(mode="after")
    def _reference_in_range(self) -> HarmonicParams:
        if self.nominal_frequency_hz not in (50.0, 60.0):
            raise ValueError(f"nominal_frequency_hz: expected 50 or 60, got {self.nominal_frequency_hz}")
        if self.reference_channel >= self.n_channels:
            raise ValueError(
                f"reference_channel: expected < n_channels = {self.n_channels}, got {self.reference_channel}"
            )
        return self


@dataclass(frozen=True)
class HarmonicWindow:
    """One analysed window (all channels). Arrays have one row per channel; harmonic arrays
    have ``max_harmonic + 1`` columns indexed by order (0 = DC), interharmonic arrays
    ``max_harmonic + 1`` columns indexed by the order below them. Values are RMS."""

    start_ns: int
    end_ns: int  # the report's timestamp
    n_cycles: int
    frequency_hz: float  # the fundamental the window spans N cycles of
    converged: bool  # (F) met its tolerance within MAX_ITERATIONS passes
    resync: bool  # this window starts on a resync tick
    gap: bool  # the stream restarted (time discontinuity) before this window
    rms: np.ndarray  # (C,)
    harmonic_rms: np.ndarray  # (C, H+1)
    harmonic_phase_rad: np.ndarray  # (C, H+1)
    harmonic_group_rms: np.ndarray  # (C, H+1)
    harmonic_subgroup_rms: np.ndarray  # (C, H+1)
    interharmonic_group_rms: np.ndarray  # (C, H+1)
    interharmonic_centred_subgroup_rms: np.ndarray  # (C, H+1)
    thd: np.ndarray  # (C,)
    thdg: np.ndarray  # (C,)
    thds: np.ndarray  # (C,)

    @property
    def fundamental_phasor(self) -> np.ndarray:
        """Complex RMS phasor of the fundamental per channel, sine convention, at the
        window end: ``C_1 exp(j phi_1)``."""
        return self.harmonic_rms[:, 1] * np.exp(1j * self.harmonic_phase_rad[:, 1])


@dataclass(frozen=True)
class KernelConstants:
    sample_rate_hz: float
    nominal_frequency_hz: float
    n_cycles: int  # N
    n_points: int  # M
    max_harmonic: int  # H
    n_channels: int
    reference_channel: int
    resync_interval_ns: int  # 0: never
    capacity: int  # samples the state's buffer holds
    table: np.ndarray  # the polyphase kernel of (I), (P+1, 2R)
    sync_re: np.ndarray  # (3, M) the windowed DFT rows of (F), real part
    sync_im: np.ndarray  # imaginary part


def kernel_table(beta: float = KAISER_BETA, phases: int = TABLE_PHASES, half_taps: int = HALF_TAPS) -> np.ndarray:
    """(I) as a polyphase table: row p holds the 2R taps ``sinc(u) w(u / R)``,
    ``u = p / P - j`` for ``j = -R+1..R``, ``w`` the Kaiser window; between rows the
    resampler interpolates linearly in the fraction."""
    mu = np.arange(phases + 1, dtype=np.float64)[:, None] / phases
    j = np.arange(-half_taps + 1, half_taps + 1, dtype=np.float64)[None, :]
    u = mu - j
    v = np.clip(1.0 - (u / half_taps) ** 2, 0.0, None)
    return np.asarray(np.sinc(u) * np.i0(beta * np.sqrt(v)) / np.i0(beta))


def highest_harmonic_order(sample_rate_hz: float, nominal_frequency_hz: float) -> int:
    """The highest order H whose top bin, (H + 1) f_nom +15 %, the interpolator (I) passes
    (up to 0.4 fs): the bound :func:`make_constants` checks."""
    h = math.floor(0.4 * sample_rate_hz / (FREQUENCY_RANGE[1] * nominal_frequency_hz)) - 1
    while h > 0 and (h + 1) * FREQUENCY_RANGE[1] * nominal_frequency_hz > 0.4 * sample_rate_hz:
        h -= 1  # the floor of a rounded quotient can be one too high
    return h


def make_constants(sample_rate_hz: float, params: HarmonicParams) -> KernelConstants:
    fs = float(sample_rate_hz)
    f_nom = float(params.nominal_frequency_hz)
    n_cyc = 10 if f_nom == 50.0 else 12  # (W)
    h = params.max_harmonic
    q = math.ceil(fs / f_nom)
    m = n_cyc * q  # (W); N is even, so M is
    # (I) passes up to 0.4 fs: the highest bin used, (H+1) N - 1, at the top of the range
    f_top = (h + 1) * FREQUENCY_RANGE[1] * f_nom
    if f_top > 0.4 * fs:
        raise ParameterError(
            f"sample_rate_hz: expected >= {f_top / 0.4:g} Hz for harmonics up to {h} of "
            f"{f_nom:g} Hz +15 % (the interpolator passes up to 0.4 fs), got {fs:g}"
        )
    l_max = n_cyc * fs / (FREQUENCY_RANGE[0] * f_nom)
    capacity = math.ceil(l_max) + 2 * HALF_TAPS + 8
    resync = 0 if params.resync_interval_s is None else round(params.resync_interval_s * NS_PER_S)
    return KernelConstants(
        fs, f_nom, n_cyc, m, h, params.n_channels, params.reference_channel, resync, capacity,
        kernel_table(), *sync_basis(n_cyc, m),
    )  # fmt: skip


def initial_state(c: KernelConstants) -> dict[str, np.ndarray]:
    """A fresh state: nothing buffered, the fundamental at its nominal value."""
    return {
        "buffer": np.zeros((c.capacity, c.n_channels)),
        "fill": np.zeros(1, dtype=np.int64),  # samples held in buffer
        "base_index": np.zeros(1, dtype=np.int64),  # stream index of buffer[0]
        "stream_t0_ns": np.zeros(1, dtype=np.int64),  # time of stream sample 0
        "started": np.zeros(1, dtype=np.bool_),  # a stream is running
        "gap": np.zeros(1, dtype=np.bool_),  # the next report follows a restart
        "resync": np.zeros(1, dtype=np.bool_),  # the next window starts on a tick
        "start_index": np.zeros(1, dtype=np.int64),  # next window start: stream index ...
        "start_frac": np.zeros(1),  # ... plus this fraction of a sample
        "f_hat": np.full(1, c.nominal_frequency_hz),  # last measured fundamental, Hz
    }


@njit(cache=True, nogil=True)
def resample_window(
    x: np.ndarray,
    fill: int,
    start_index: int,
    start_frac: float,
    step: float,
    m: int,
    table: np.ndarray,
    out: np.ndarray,
) -> bool:  # pragma: no cover - compiled
    """(I): ``out[i] = y(start_index + start_frac + i * step)`` for i < m, from ``x[:fill]``
    (rows = samples, columns = channels), with the polyphase kernel ``table`` (P+1, 2R).
    The integer and fractional parts of the start are kept apart so that the result does
    not depend on where the buffer begins. Returns False when a tap falls outside
    ``0..fill-1``."""
    n_taps = table.shape[1]
    r = n_taps // 2
    n_phase = table.shape[0] - 1
    n_ch = x.shape[1]
    for i in range(m):
        pos = start_frac + i * step
        fl = math.floor(pos)
        i0 = start_index + int(fl)
        if i0 - r + 1 < 0 or i0 + r >= fill:
            return False
        ph = (pos - fl) * n_phase
        p = int(ph)
        if p >= n_phase:
            p = n_phase - 1
        a = ph - p
        first = i0 - r + 1
        for c in range(n_ch):
            acc = 0.0
            for t in range(n_taps):
                w = table[p, t] + a * (table[p + 1, t] - table[p, t])  # (I) between phases
                acc += w * x[first + t, c]
            out[i, c] = acc
    return True


@njit(cache=True, nogil=True)
def fundamental_bin_offset(y: np.ndarray, basis_re: np.ndarray, basis_im: np.ndarray) -> float:  # pragma: no cover
    """(F): ``delta``, the fundamental's offset in bins from bin N of the resampled window
    ``y`` (M points), from the windowed DFT at bins N-1, N, N+1 (``basis`` rows: the
    window times ``exp(-j 2 pi (N + d) m / M)``); NaN when those bins are all zero."""
    m0 = m1 = m2 = 0.0
    for d in range(3):
        re = 0.0
        im = 0.0
        for k in range(y.shape[0]):
            re += y[k] * basis_re[d, k]
            im += y[k] * basis_im[d, k]
        mag = math.sqrt(re * re + im * im)
        if d == 0:
            m0 = mag
        elif d == 1:
            m1 = mag
        else:
            m2 = mag
    den = m0 + 2.0 * m1 + m2
    if den == 0.0:
        return math.nan
    return SYNC_TERMS * (m2 - m0) / den


def sync_basis(n_cycles: int, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(F): rows d = -1, 0, 1 of ``w_m exp(-j 2 pi (N + d) m / M)``, ``w`` the
    Rife-Vincent class I window of SYNC_TERMS terms (``sin^6(pi m / M)``)."""
    m = np.arange(n_points, dtype=np.float64)
    w = np.sin(np.pi * m / n_points) ** (2 * (SYNC_TERMS - 1))
    arg = 2.0 * np.pi * (n_cycles + np.arange(-1, 2, dtype=np.float64))[:, None] * m[None, :] / n_points
    return np.ascontiguousarray(w * np.cos(arg)), np.ascontiguousarray(-w * np.sin(arg))


def _time_ns(state_t0: int, index: float, fs: float) -> float:
    return state_t0 + index * NS_PER_S / fs


def _analyse(y: np.ndarray, c: KernelConstants) -> dict[str, np.ndarray]:
    """(D)-(T) on the resampled window ``y`` (M, C)."""
    n, h = c.n_cycles, c.max_harmonic
    x = np.fft.rfft(y, axis=0).T / c.n_points  # (D) (C, M/2+1)
    ck = np.abs(x) * math.sqrt(2.0)  # (D) RMS of each spectral component
    ck[:, 0] = np.abs(x[:, 0])
    c2 = ck * ck
    orders = np.arange(h + 1)
    k = orders * n
    harm = ck[:, k]  # (H)
    phase = np.angle(x[:, k]) + 0.5 * np.pi  # (D) sine convention
    phase = np.pi - np.mod(np.pi - phase, 2.0 * np.pi)  # wrap to (-pi, pi]
    half = n // 2
    # (G): a window of bins k-N/2..k+N/2 with half weights at the ends; (S): k-1..k+1
    g_w = np.ones(n + 1)
    g_w[0] = g_w[-1] = 0.5
    g_idx = k[1:, None] + np.arange(-half, half + 1)[None, :]
    group = np.empty_like(harm)
    group[:, 0] = harm[:, 0]
    group[:, 1:] = np.sqrt(np.sum(c2[:, g_idx] * g_w, axis=2))
    s_idx = k[1:, None] + np.arange(-1, 2)[None, :]
    sub = np.empty_like(harm)
    sub[:, 0] = harm[:, 0]
    sub[:, 1:] = np.sqrt(np.sum(c2[:, s_idx], axis=2))
    ig = np.sqrt(np.sum(c2[:, k[:, None] + np.arange(1, n)[None, :]], axis=2))  # (IG)
    isg = np.sqrt(np.sum(c2[:, k[:, None] + np.arange(2, n - 1)[None, :]], axis=2))  # (IS)

    top = min(h, THD_MAX_ORDER)

    def ratio(a: np.ndarray) -> np.ndarray:  # (T)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.sqrt(np.sum(a[:, 2 : top + 1] ** 2, axis=1)) / a[:, 1]
        return np.where(a[:, 1] > 0.0, r, np.nan)

    return {
        "rms": np.sqrt(np.mean(y * y, axis=0)),
        "harmonic_rms": harm,
        "harmonic_phase_rad": phase,
        "harmonic_group_rms": group,
        "harmonic_subgroup_rms": sub,
        "interharmonic_group_rms": ig,
        "interharmonic_centred_subgroup_rms": isg,
        "thd": ratio(harm),
        "thdg": ratio(group),
        "thds": ratio(sub),
    }


def harmonic_kernel(
    block: np.ndarray, t0_ns: int, state: Mapping[str, np.ndarray], c: KernelConstants
) -> tuple[list[HarmonicWindow], dict[str, np.ndarray]]:
    """Run the analyser over ``block`` ((n, C) float64, first sample at ``t0_ns``) from
    ``state``; return the windows completed in it and the new state. ``state`` is not
    modified. Positions are stream sample indices, the window start kept as an integer
    index plus a fraction, so the windows do not depend on how the stream is cut into
    blocks (bit for bit)."""
    fs = c.sample_rate_hz
    buf = state["buffer"]
    fill = int(state["fill"][0])
    base = int(state["base_index"][0])
    st0 = int(state["stream_t0_ns"][0])
    started = bool(state["started"][0])
    gap = bool(state["gap"][0])
    resync = bool(state["resync"][0])
    s_int = int(state["start_index"][0])
    s_frac = float(state["start_frac"][0])
    f_hat = float(state["f_hat"][0])

    expected = _time_ns(st0, base + fill, fs)
    if not started or abs(t0_ns - expected) > 0.5 * NS_PER_S / fs:
        if started:
            gap = True
        started, st0, base, fill, s_int, s_frac, resync = True, int(t0_ns), 0, 0, HALF_TAPS, 0.0, False
    x = np.concatenate([buf[:fill], block]) if fill else block
    avail = x.shape[0]
    n, m = c.n_cycles, c.n_points
    y = np.empty((m, c.n_channels))
    # the iteration (F) resamples the reference column only; the other columns once after
    x_ref = x[:, c.reference_channel : c.reference_channel + 1]
    y_ref = y if c.n_channels == 1 else np.empty((m, 1))
    f_lo, f_hi = FREQUENCY_RANGE[0] * c.nominal_frequency_hz, FREQUENCY_RANGE[1] * c.nominal_frequency_hz
    windows: list[HarmonicWindow] = []
    while True:
        f_a = f_hat
        ok = True
        converged = False
        for _ in range(MAX_ITERATIONS):
            length = n * fs / f_a  # (W) L
            if not resample_window(x_ref, avail, s_int - base, s_frac, length / m, m, c.table, y_ref):
                ok = False
                break
            delta = fundamental_bin_offset(y_ref[:, 0], c.sync_re, c.sync_im)
            if not math.isfinite(delta):
                break  # no fundamental: keep f_a
            f_new = min(max(f_a * (1.0 + delta / n), f_lo), f_hi)  # (F)
            if abs(f_new - f_a) <= FREQUENCY_TOLERANCE * f_a:
                converged = True
                break
            f_a = f_new
        if not ok:
            break
        length = n * fs / f_a
        if c.n_channels > 1 or not converged:  # y_ref may hold an earlier f_a's window
            if not resample_window(x, avail, s_int - base, s_frac, length / m, m, c.table, y):
                break
        ts = _time_ns(st0, s_int + s_frac, fs)
        end = s_frac + length
        te = _time_ns(st0, s_int + end, fs)
        out = _analyse(y, c)
        windows.append(
            HarmonicWindow(
                start_ns=round(ts), end_ns=round(te), n_cycles=n, frequency_hz=f_a, converged=converged,
                resync=resync, gap=gap, **out,
            )
        )  # fmt: skip
        gap = False
        f_hat = f_a
        whole = math.floor(end)
        s_int, s_frac = s_int + int(whole), end - whole
        resync = False
        if c.resync_interval_ns:
            t_start = round(ts)
            tick = (t_start // c.resync_interval_ns + 1) * c.resync_interval_ns
            if tick < te:  # overlap 1: the next window starts on the tick [4-30 4.5]
                p = (tick - st0) * fs / NS_PER_S
                whole = math.floor(p)
                s_int, s_frac = int(whole), p - whole
                resync = True

    # keep what the next window needs: from R samples before its start
    keep_from = max(0, min(s_int - base - HALF_TAPS, avail))
    tail = x[keep_from:]
    if tail.shape[0] > c.capacity:  # cannot happen for the windows above; a guard
        raise InputError(f"buffer: expected at most {c.capacity} samples to keep, got {tail.shape[0]}")
    new_buf = np.zeros_like(buf)
    new_buf[: tail.shape[0]] = tail
    new_state = {
        "buffer": new_buf,
        "fill": np.array([tail.shape[0]], dtype=np.int64),
        "base_index": np.array([base + keep_from], dtype=np.int64),
        "stream_t0_ns": np.array([st0], dtype=np.int64),
        "started": np.array([started]),
        "gap": np.array([gap]),
        "resync": np.array([resync]),
        "start_index": np.array([s_int], dtype=np.int64),
        "start_frac": np.array([s_frac]),
        "f_hat": np.array([f_hat]),
    }
    return windows, new_state


class HarmonicAnalyser:
    """The IEC 61000-4-7 analyser of one channel or one group of channels on a common
    window grid (see the module docstring). ``update(samples, t0_ns)`` returns the windows
    completed by the block; ``reset``, ``get_state``/``set_state`` as for estimators."""

    name = "iec61000-4-7"

    def __init__(
        self,
        sample_rate_hz: float,
        params: HarmonicParams | Mapping[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        self.sample_rate_hz = checked_sample_rate(sample_rate_hz)
        if isinstance(params, HarmonicParams) and not kwargs:
            self.params = params
        else:
            merged = dict(params.model_dump() if isinstance(params, HarmonicParams) else (params or {}))
            merged.update(kwargs)
            try:
                self.params = HarmonicParams.model_validate(merged)
            except ValidationError as exc:
                raise ParameterError(f"{self.name}: invalid parameters: {exc.errors()[0]['msg']}") from exc
        self.constants = make_constants(self.sample_rate_hz, self.params)
        self._state = initial_state(self.constants)

    @property
    def n_cycles(self) -> int:
        return self.constants.n_cycles

    def update(self, samples: np.ndarray, t0_ns: int) -> list[HarmonicWindow]:
        """Feed a block (``(n,)`` for one channel, ``(n, n_channels)``) whose first sample is
        at ``t0_ns``; return the windows it completes. A rejected block raises and leaves the
        state untouched."""
        x = self._as_block(samples)
        windows, self._state = harmonic_kernel(x, int(t0_ns), self._state, self.constants)
        return windows

    def _as_block(self, samples: Any) -> np.ndarray:
        if not isinstance(samples, np.ndarray):
            raise InputTypeError(f"samples: expected a numpy array, got {type(samples).__name__}")
        if samples.dtype.kind not in "fiu":
            raise InputTypeError(f"samples: expected a real numeric dtype, got {samples.dtype}")
        c = self.params.n_channels
        x = samples.reshape(-1, 1) if samples.ndim == 1 else samples
        if x.ndim != 2 or x.shape[1] != c:
            raise InputError(f"samples: expected shape (N, {c}), got {samples.shape}", kind="shape_mismatch")
        if x.shape[0] == 0:
            raise InputError("samples: expected at least one sample, got 0", kind="empty_block")
        x = np.ascontiguousarray(x, dtype=np.float64)
        if not np.isfinite(x).all():
            raise InputError(
                f"samples: expected finite values, got {int(np.count_nonzero(~np.isfinite(x)))} NaN/Inf",
                kind="non_finite",
            )
        return x

    def reset(self) -> None:
        self._state = initial_state(self.constants)

    def get_state(self) -> dict[str, Any]:
        return state_snapshot(
            STATE_FORMAT_VERSION, "analyser", self.name, self.sample_rate_hz, self.params, self._state
        )

    def set_state(self, snapshot: Mapping[str, Any]) -> None:
        if snapshot.get("format_version") != STATE_FORMAT_VERSION or snapshot.get("analyser") != self.name:
            raise ParameterError(
                f"state: expected {self.name!r} format {STATE_FORMAT_VERSION}, got "
                f"{snapshot.get('analyser')!r} format {snapshot.get('format_version')!r}"
            )
        if float(snapshot.get("sample_rate_hz", -1)) != self.sample_rate_hz:
            raise ParameterError(
                f"state sample_rate_hz: expected {self.sample_rate_hz}, got {snapshot.get('sample_rate_hz')}"
            )
        if HarmonicParams.model_validate(snapshot.get("params", {})) != self.params:
            raise ParameterError("state params differ from this analyser's parameters")
        fresh = initial_state(self.constants)
        arrays = {k: decode_array(v) for k, v in snapshot["state"].items()}
        if set(arrays) != set(fresh) or any(
            arrays[k].shape != fresh[k].shape or arrays[k].dtype != fresh[k].dtype for k in fresh
        ):
            raise ParameterError(f"state arrays: expected {sorted(fresh)} with this analyser's shapes")
        self._state = arrays
