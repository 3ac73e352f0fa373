"""``pmu``: synchrophasor, frequency and ROCOF on the reporting grid (IEEE C37.118.1).

The estimator reports, at the times ``k / Fs`` since the epoch (``Fs`` the reporting rate,
``k`` an integer), the synchrophasor ``X = (Xm / sqrt 2) e^{j phi}`` of the signal
``x(t) = Xm cos(2 pi f0 t + phi(t))`` (magnitude RMS, phase referred to the
nominal-frequency cosine at the report time, C37.118.1-2011 clause 4.2 eq. (1)-(3)),
its frequency ``f = f0 + (1 / 2 pi) dphi/dt`` and ROCOF ``df/dt`` (clause 4.3 eq. (4)-(5)).

Design: quadrature demodulation and a filter bank of a smooth lowpass kernel and its
first two time derivatives, evaluated at the report time, with iterative cancellation of
the negative-frequency image. The maths, with the papers and the C37.118.1 clauses and
equations it follows, is in ``_pmu_design`` (the design of the demodulation and the kernel
bank: (D), (K), (K'), (I), (E), (B), (C), (R), (U)) and ``_pmu_kernels`` (the compiled
kernels, and the transition test (T) behind the reports' ``converged``); this module is
the estimator class, its parameters and its state (the time anchor, 'auto').

Time: reports are on the grid ``k / Fs`` since the epoch. The block's absolute start time
(``update(samples, t0_ns=...)``) anchors the sample count; without it the stream is
taken to start at t = 0. A block whose start time disagrees with the count by more than
half a sample (a gap in time) re-anchors the estimator: it restarts (its reports resume
after one kernel length). Every report is computed once the kernel's last tap has
arrived: the latency is ``T / 2 + 2 D / fs``.

Per-sample outputs (the Track rows) hold the latest report, the phase advanced at its
frequency (``y = offset + A sin(phase)``, A = sqrt 2 |X|); ``offset`` is the kernel's DC
output on the raw samples. ``residual_rms`` is the one-step prediction error of that
held model. A row's ``converged`` is the kernel's magnitude test, whatever ``last_only``
(a row is the same row either way); the reports' own ``converged`` is (T). The reports themselves (``Track.reports``, a GridReports) carry the same
fields at the report times, the ROCOF in ``rocof_hz_per_s`` and the synchrophasor in
``extras`` (``synchrophasor_magnitude``, RMS, and ``synchrophasor_angle_rad``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from sinewatch.estimators import register
from sinewatch.estimators._pmu_bank import grid_track, pmu_bank_kernel, run_pmu_bank
from sinewatch.estimators._pmu_design import (
    AMBIGUOUS_S,
    DETECTION_S,
    M_CLASS_RATES,
    P_CLASS_RATES,
    TABLE_STEP_HZ,
    Design,
    design,
    gain,
    oscillator,
    spectral_peak_hz,
    steady_level,
)
from sinewatch.estimators._pmu_kernels import (
    N_FSTATE,
    N_REPORT_COLUMNS,
    N_TRANSITION,
    NOISE_TIME_CONSTANT_S,
    fresh_transition,
    pmu_kernel,
    transition_kernel,
)
from sinewatch.estimators.bank import register_bank
from sinewatch.estimators.base import (
    Estimator,
    EstimatorParams,
    GridReports,
    Track,
    concat_tracks,
    decode_array,
    encode_array,
)
from sinewatch.schemas.errors import ParameterError

# the public face of the estimator: what other modules and tests import from ``pmu``
__all__ = [
    "AMBIGUOUS_S",
    "DETECTION_S",
    "Design",
    "Pmu",
    "PmuParams",
    "design",
    "gain",
    "oscillator",
    "pmu_kernel",
    "spectral_peak_hz",
    "transition_kernel",
]


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


@register
class Pmu(Estimator[PmuParams], kernel=pmu_kernel, name="pmu"):
    """C37.118.1 synchrophasor (RMS magnitude, phase vs nominal cosine), frequency and ROCOF on the reporting grid: demodulation + derivative filter bank + image cancellation (M or P class)"""

    reports_on_grid = True
    # Printed by ``sinewatch bench kernels --bank N`` when the bank stays below twice the FFT.
    bank_note: ClassVar[str] = (
        "the bank runs 8 channels whose schedules agree (a frame's) as vector lanes: the per-sample "
        "prediction, demodulation and rotor vectorised, about 1.7x faster than 8 channels one at a "
        "time; but each lane's reports (5 a 1024-sample block at 50 reports/s: the 181-tap filter "
        "bank, the image passes, four noise probes, the standard deviations, with sin, cos, atan2 "
        "and complex divisions) stay scalar per lane, about two thirds of the kernel, and the "
        "Python that assembles each channel's Track and its grid reports (~25 numpy views a "
        "channel) is about as much again (CPU time of update_bank against its kernel alone, load "
        "~19). Twice the FFT would take the reports' sums across the lanes (their complex "
        "rotations written as the same real operations, so the bits stay) and a Track for the "
        "whole frame. Read in the bank's AVX2 assembly (2-core AMD EPYC VM): the whole sample loop "
        "holds 63 packed double operations on ymm (the 8 lanes' prediction, (D)'s six sums and the "
        "rotor: ~8 operations a channel-sample) against 113 scalar ones, 6 scalar divisions and 40 "
        "calls in its report branch, so the vector part is a few ns of update_bank's 42-53 ns a "
        "channel-sample (ten processes, load 18-29)"
    )
    paper = None
    example_sample_rate_hz = 10_000.0
    REFILL_MEMORIES: ClassVar[int] = 1  # its memory is its window (validity rules version 5)
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
        self._transition = fresh_transition()  # (T), see _converged
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
            trans = fresh_transition()  # the estimator starts once the nominal frequency is found
        else:
            st = self._state_for_block(state, t0_ns)
            if st is not state:  # anchored afresh (the first timed block, a gap in time): (T) starts over
                trans = fresh_transition()
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
            elif steady_level(win):  # not a window the signal starts or stops in
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
        self._transition = fresh_transition()
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
        trans = fresh_transition()  # snapshots of earlier builds have none: (T) starts over
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
        # the reports' converged: the magnitude test until (T) replaces it (_converged)
        return grid_track(self.reporting_rate, out, reps, sse, n_pred, reps[:, 3] > self._fconsts[6])

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


register_bank(Pmu, pmu_bank_kernel, n_outputs=6, run=run_pmu_bank)
