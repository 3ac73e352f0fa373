"""``nls``: windowed maximum-likelihood (nonlinear least squares) fit of K sinusoids.

The maximum-likelihood estimator of tones in white Gaussian noise is the least-squares fit
of the exact model; it attains the Cramer-Rao bound at moderate SNR. The fit of one window
(variable projection after Golub and Pereyra, Kaufman's Gauss-Newton step, the periodogram
start, the order by Djuric's MDL, the Fisher-information standard deviations) and its
equations, numbered (1)-(8), are in :mod:`sinewatch.estimators._nls_fit`; the streaming kernel
that slides that fit over the stream, for one channel or a frame's channels at once, in
:mod:`sinewatch.estimators._nls_bank`. This module is the parameter model and the class.

Between estimates (every ``hop_samples``) the estimate is held and the phase advances at
the held frequency, ``phi(m) = phi + w m`` m samples after the window's last sample, its
variance ``var(phi) + m^2 var(w) + 2 m cov(w, phi)``; with a trend the offset advances by
``D / c`` per sample likewise. ``converged``: every reported tone found and (3) converged,
and the fit residual RMS at most ``max_relative_residual`` times the largest amplitude.
The Track's residual is the one-step prediction error of the held estimate, as ``ipdft``.

State: the ring buffer of the last N samples, counters and the held estimate (with its
covariances), so the outputs do not depend on how the stream is cut into blocks.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from sinewatch.estimators import register
from sinewatch.estimators._nls_bank import nls_bank_kernel
from sinewatch.estimators._nls_fit import GLOBAL_FIELDS, MAX_TONES, TONE_FIELDS
from sinewatch.estimators.bank import register_bank
from sinewatch.estimators.base import (
    Estimator,
    EstimatorParams,
    Track,
    TrackStd,
    require_below_nyquist,
)
from sinewatch.schemas.errors import ParameterError

Arr = np.ndarray  # numba ignores annotations; these are for the type checker
MAX_WINDOW_SAMPLES = 1 << 20


class NlsParams(EstimatorParams):
    n_components: int | None = Field(
        1,
        ge=1,
        le=MAX_TONES,
        description="Number of tones K (fixed); null: chosen in 0..k_max by the order criterion",
    )
    k_max: int = Field(4, ge=1, le=MAX_TONES, description="Most tones considered when n_components is null")
    criterion: Literal["mdl", "aic"] = Field(
        "mdl", description="Order criterion when n_components is null: mdl (Djuric 1996) or aic"
    )
    min_frequency_hz: float = Field(
        45.0, gt=0, allow_inf_nan=False, description="Lowest expected frequency (Hz): lower edge of the search band"
    )
    max_frequency_hz: float | None = Field(
        None,
        gt=0,
        allow_inf_nan=False,
        description="Upper edge of the search band (Hz; default: Nyquist less two DFT bins of the window)",
    )
    window_cycles: float | None = Field(
        None,
        ge=1,
        allow_inf_nan=False,
        description="Window length in cycles of min_frequency_hz (default 4 if no other length is given)",
    )
    window_s: float | None = Field(None, gt=0, allow_inf_nan=False, description="Window length in seconds")
    window_samples: int | None = Field(None, ge=8, description="Window length in samples")
    hop_samples: int | None = Field(
        None, ge=1, description="Samples between estimates (default: a quarter of the window); <= window"
    )
    trend: bool = Field(False, description="Fit a linear trend of the offset over the window")
    warm_start: bool = Field(
        True,
        description="K fixed: start from the previous window's frequencies, the periodogram only when "
        "that fit fails or its residual RMS exceeds 1.5 x the previous one",
    )
    zero_pad: int = Field(4, ge=1, le=64, description="Zero-padding factor of the coarse periodogram (power of 2)")
    max_iterations: int = Field(40, ge=1, le=1000, description="Gauss-Newton iterations per fit, at most")
    max_relative_residual: float = Field(
        0.5,
        gt=0,
        allow_inf_nan=False,
        description="converged requires the fit residual RMS <= this x the largest amplitude",
    )

    @model_validator(mode="after")
    def _one_window_length(self) -> NlsParams:
        given = [k for k in ("window_cycles", "window_s", "window_samples") if getattr(self, k) is not None]
        if len(given) > 1:
            raise ValueError(f"window: expected one of window_cycles, window_s, window_samples, got {given}")
        if (self.zero_pad & (self.zero_pad - 1)) != 0:
            raise ValueError(f"zero_pad: expected a power of 2, got {self.zero_pad}")
        return self


def nls_kernel(
    x: np.ndarray, buf: np.ndarray, istate: np.ndarray, tones: np.ndarray, glob: np.ndarray, iconsts: np.ndarray,
    fconsts: np.ndarray, cos_tab: np.ndarray, sin_tab: np.ndarray, last_only: bool,
) -> tuple[np.ndarray, np.ndarray, float, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """One channel's block ``x`` (N,) through :func:`nls_bank_kernel` as a bank of one, its arrays
    viewed with a channel axis of length 1 (no copy): ``(out_k (6, rows, k_cols), out_g (5, rows),
    sse, n_pred, buffer, counters, tones, fit)``. Why one compiled kernel for both paths: numba
    compiles a kernel's callees again into each kernel that calls them, and a second kernel
    calling the window's fit compiled the whole fit again (the nls task's cold compile 41.1 s of
    CPU against main's 24.9, load 4-12; compile time is the CI's limit); and a channel's bits are
    then the bank's by construction, whatever the bank. A Python function: compiled, it would be
    a second copy of the kernel."""
    out_k, out_g, sse, n_pred, b, ist, t, g = nls_bank_kernel(
        x[:, None], buf[:, None], istate[:, None], tones[:, :, None], glob[:, None], iconsts, fconsts, cos_tab,
        sin_tab, last_only,
    )  # fmt: skip
    return out_k[0], out_g[0], float(sse[0]), int(n_pred[0]), b[:, 0], ist[:, 0], t[:, :, 0], g[:, 0]


def _nls_track(out_k: np.ndarray, out_g: np.ndarray, converged: np.ndarray, residual_rms: float) -> Track:
    """The Track of one channel's :func:`nls_bank_kernel` outputs (``out_k`` (6, rows, k_cols),
    ``out_g`` (5, rows)), its converged flags and residual RMS given."""
    return Track(
        frequency_hz=out_k[0],
        amplitude=out_k[1],
        phase_rad=out_k[2],
        offset=out_g[0],
        converged=converged,
        residual_rms=residual_rms,
        extras={"n_tones": out_g[3], "fit_residual_rms": out_g[4]},
        std=TrackStd(frequency_hz=out_k[3], amplitude=out_k[4], phase_rad=out_k[5], offset=out_g[1]),
    )


@register
class Nls(Estimator[NlsParams], kernel=nls_kernel, name="nls"):
    """Windowed maximum-likelihood (nonlinear least squares) fit of K tones + offset, with CRLB-based std"""

    paper = (
        'G. H. Golub, V. Pereyra, "The differentiation of pseudo-inverses and nonlinear least squares '
        'problems whose variables separate", 1973 (variable projection)'
    )
    REFILL_MEMORIES: ClassVar[int] = 1  # its memory is its window (validity rules version 5)
    # Printed by ``sinewatch bench kernels --bank N`` when the bank is below its target.
    bank_note: ClassVar[str] = (
        "the bank runs each sample's one-step prediction for 8 channels as one vector and writes the rings a "
        "row of 8 channels at a time; each channel's window fit (Gauss-Newton to convergence, a number of "
        "steps that differs between channels) stays scalar, about half of the kernel's time. Measured in "
        "`sinewatch bench kernels --block 1024 --bank 8 --estimators nls` (2-core AMD EPYC VM (AVX2), load "
        "3-25): bank 8 2.02-2.08x the streaming FFT, the kernel alone 2.9-3.2x, update_bank's Python (the "
        "channels' Tracks) 6.7-9.5 ns a channel-sample: a loaded run can put it just under 2x"
    )
    # One estimate per 1024-sample block from a 1024-sample window (the kernel benchmark).
    example_params: ClassVar[dict[str, Any]] = {
        "min_frequency_hz": 20.0,
        "window_samples": 1024,
        "hop_samples": 1024,
        "zero_pad": 1,
    }

    def _check_params(self) -> None:
        p = self.params
        fs = self.sample_rate_hz
        nyq = require_below_nyquist("min_frequency_hz", p.min_frequency_hz, fs)
        if p.window_samples is not None:
            n = p.window_samples
        elif p.window_s is not None:
            n = round(p.window_s * fs)
        else:
            cycles = 4.0 if p.window_cycles is None else p.window_cycles
            n = math.ceil(cycles * fs / p.min_frequency_hz - 1e-9)
        if n > MAX_WINDOW_SAMPLES:
            raise ParameterError(f"window: expected <= {MAX_WINDOW_SAMPLES} samples, got {n}")
        if n < 8:
            raise ParameterError(f"window: expected >= 8 samples, got {n}")
        hop = max(1, n // 4) if p.hop_samples is None else p.hop_samples
        if hop > n:
            raise ParameterError(f"hop_samples: expected <= window = {n} samples, got {hop}")
        k_cols = p.k_max if p.n_components is None else p.n_components
        unknowns = 2 + 3 * k_cols + (1 if p.trend else 0)
        if n < 2 * unknowns:
            raise ParameterError(f"window: expected >= {2 * unknowns} samples for {k_cols} tones, got {n}")
        nfft = p.zero_pad * (1 << max(3, math.ceil(math.log2(n))))
        bin_hz = fs / nfft
        f_hi = nyq - 2.0 * fs / n if p.max_frequency_hz is None else p.max_frequency_hz
        require_below_nyquist("max_frequency_hz", f_hi, fs)
        lo = max(1, math.ceil(p.min_frequency_hz / bin_hz))
        hi = min(nfft // 2 - 1, math.floor(f_hi / bin_hz))
        if lo > hi:
            raise ParameterError(
                f"search band: expected min_frequency_hz < max_frequency_hz, got {p.min_frequency_hz:g}..{f_hi:g} Hz"
            )
        self.window_samples, self.hop_samples, self.k_cols, self.nfft = n, hop, k_cols, nfft
        self._band = (lo, hi)

    @property
    def memory_samples(self) -> int:
        """The window: a fit describes the last ``window_samples`` samples."""
        return int(self.window_samples)

    def _setup(self) -> None:
        p = self.params
        j = np.arange(self.nfft // 2)
        self._cos = np.cos(2.0 * np.pi * j / self.nfft)
        self._sin = np.sin(2.0 * np.pi * j / self.nfft)
        self._iconsts = np.array(
            [
                0 if p.n_components is None else p.n_components,
                p.k_max,
                1 if p.criterion == "aic" else 0,
                2 if p.trend else 1,
                self._band[0],
                self._band[1],
                p.max_iterations,
                self.hop_samples,
                1 if p.warm_start else 0,
            ],
            dtype=np.int64,
        )
        self._fconsts = np.array([self.sample_rate_hz, p.max_relative_residual])
        self._constants = (self._iconsts, self._fconsts, self._cos, self._sin)

    @property
    def n_components(self) -> int:
        return int(self.k_cols)

    def _initial_state(self) -> dict[str, np.ndarray]:
        """``buffer`` (N,): the ring buffer of the window; ``counters`` (5,) int64: write
        position, fill, samples since the last hop (starts at hop: fit as soon as full),
        estimate held (0/1), samples since the held estimate; ``tones`` (K, 11): per tone
        w (rad/sample), A, phase at the window's last sample, var w, var A, var phase,
        cov(w, phase), sin and cos of the phase m samples on, cos w, sin w; ``fit`` (8,):
        offset at the last sample, its slope per sample, var offset, var slope,
        cov(offset, slope), fit residual RMS, converged (0/1), number of tones + 0.5
        (0: nothing held)."""
        return {
            "buffer": np.zeros(self.window_samples),
            "counters": np.array([0, 0, self.hop_samples, 0, 0], dtype=np.int64),
            "tones": np.zeros((self.k_cols, TONE_FIELDS)),
            "fit": np.zeros(GLOBAL_FIELDS),
        }

    def _track(self, outputs: tuple[Any, ...], block: np.ndarray) -> Track:
        out_k, out_g, sse, n_pred = outputs
        return _nls_track(out_k, out_g, out_g[2] != 0.0, math.sqrt(sse / n_pred) if n_pred else math.nan)

    def _bank_tracks(self, outputs: tuple[Any, ...], block: np.ndarray) -> list[Track]:
        """:meth:`_track` of every channel of a bank (:func:`nls_bank_kernel`'s outputs, the
        channel first): the converged flags compared and the residuals taken for the whole
        frame at once (the same operations on the same values: the same bits)."""
        out_k, out_g, sse, n_pred = outputs
        conv = out_g[:, 2] != 0.0
        rms = [math.sqrt(s / n) if n else math.nan for s, n in zip(sse.tolist(), n_pred.tolist(), strict=True)]
        return [_nls_track(out_k[c], out_g[c], conv[c], rms[c]) for c in range(out_k.shape[0])]

    @classmethod
    def params_for(cls, sample_rate_hz: float, hints: dict[str, Any]) -> dict[str, Any]:
        """Bench hook: K = the scenario's tones, the band from its frequency range, a window
        of 4 cycles of half its lowest nominal frequency (or the range floor), hop a quarter."""
        lo, hi = hints["frequency_range_hz"]
        k = int(hints["n_components"])
        if hints.get("n_inputs", 1) != 1:
            raise ParameterError("nls: expected one input column")
        nyq = 0.5 * sample_rate_hz
        f_min = max(0.5 * min(hints["nominal_frequency_hz"]), float(lo), 1e-6)
        n = math.ceil(4.0 * sample_rate_hz / f_min - 1e-9)
        return {
            "n_components": k,
            "min_frequency_hz": f_min,
            "max_frequency_hz": min(float(hi), 0.98 * nyq) if hi else None,
            "window_samples": n,
            "hop_samples": max(1, n // 4),
            "zero_pad": 4,
        }


register_bank(Nls, nls_bank_kernel, n_outputs=4, tracks=Nls._bank_tracks)
