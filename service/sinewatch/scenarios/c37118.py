"""IEEE C37.118.1 M-class compliance signals and limits (test generators, not registered
scenarios: ``sinewatch.apps.bench.compliance`` runs and scores them).

Each :class:`TestSignal` is a noise-free signal ``x(t)`` (t in seconds from the test's
start, which is a whole second since the epoch, so the nominal cosine has phase 0 there)
with its exact truth: the synchrophasor ``X(t)`` (RMS, angle referred to the nominal
cosine ``cos(2 pi f0 t)``, C37.118.1-2011 clause 4.2), frequency ``f(t)`` and ROCOF
(clause 4.3), and the times that are scored.

Tests and limits: IEEE Std C37.118.1-2011 clause 5.5 (Tables 3-10) as amended by IEEE Std
C37.118.1a-2014 (its abstract: requirements in Tables 4 to 10 modified, and Table 11, formerly
Table 12); M class only. ``limits`` below is the one
table. Where this module is unsure of a limit recalled from the standard, ``LIMIT_NOTES``
says so; check the standard before quoting compliance (this is a model of the test suite,
not a certified one). The ranges follow the standard's test conditions:

* steady state, frequency: ``f0 +- 2 Hz`` (Fs < 10), ``+- Fs/5`` (10 <= Fs < 25), ``+- 5 Hz``
  (Fs >= 25) [Table 3]; magnitude 10 % to 120 % [Table 3]; TVE 1 %, FE 0.005 Hz, RFE
  0.1 Hz/s [Tables 3, 4 as amended].
* harmonics: 10 % of each harmonic 2..50 at f0 [Table 3]; TVE 1 %; FE 0.025 Hz (Fs > 20),
  0.005 Hz (Fs <= 20) [Table 4]; RFE suspended by the 2014 amendment (reported, not
  judged).
* out-of-band interference: signal at f0 and ``f0 +- 0.1 Fs/2``; 10 % interferer from 10 Hz
  to ``f0 - Fs/2`` and from ``f0 + Fs/2`` to ``2 f0`` [Table 3, footnote on the passband];
  TVE 1.3 %, FE 0.01 Hz [Table 4 as amended]; RFE suspended.
* measurement bandwidth: 10 % amplitude modulation and 0.1 rad phase modulation at
  ``fm <= Frt = min(Fs/5, 5 Hz)`` [Table 5]; TVE 3 %; FE ``0.06 Frt`` Hz and RFE
  ``0.18 pi Frt^2`` Hz/s (0.3 Hz and 14 Hz/s at Frt = 5 Hz, the 2014 values;
  IEC/IEEE 60255-118-1:2018 scales them with Frt, which is stricter below 5 Hz: used here),
  rounded to two significant figures as the tables print them (:func:`printed`): 14 Hz/s,
  not 0.18 pi 25 = 14.14; 9 Hz/s at 20 frames/s (Frt = 4); 0.14 Hz at 12 frames/s (Frt = 2.4).
* frequency ramp +-1 Hz/s over the steady-state range [Table 6]; TVE 1 %, FE 0.01 Hz, RFE
  0.2 Hz/s [Table 7 as amended]; reports within ``7 / Fs`` of a ramp's start or end are
  excluded (clause 5.5.7).
* steps of +-10 % magnitude and +-10 degrees phase [Table 10]: TVE response time
  ``7 / Fs``, FE and RFE response times ``14 / Fs`` (amended), delay time ``1 / (4 Fs)``,
  overshoot/undershoot 10 % of the step [Table 11 as amended]; measured by equivalent
  time sampling (the step placed at ``n_offsets`` fractions of the reporting interval,
  clause 5.5.8); the thresholds are the steady-state limits (TVE 1 %, FE 0.005 Hz, RFE
  0.1 Hz/s).
* reporting latency ``5 / Fs`` [clause 5.5.10, Table 12].
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

SAMPLE_RATE_HZ = 10_000.0
M_RATES = {50: (10, 25, 50), 60: (10, 12, 15, 20, 30, 60)}
SQRT_HALF = math.sqrt(0.5)

LIMIT_NOTES = (
    "Recalled from C37.118.1-2011 and C37.118.1a-2014, not copied from the text. Least sure: "
    "the harmonic FE split at Fs = 20 (0.025 / 0.005 Hz), the modulation FE/RFE scaling with "
    "Frt (60255-118-1:2018; the 2014 table gives 0.3 Hz and 14 Hz/s), and that RFE is "
    "suspended (not judged) for harmonics and out-of-band interference."
)


def frequency_range_hz(fs_report: int) -> float:
    """Half-width of the M-class steady-state and ramp frequency range (Table 3)."""
    if fs_report < 10:
        return 2.0
    if fs_report < 25:
        return fs_report / 5.0
    return 5.0


def modulation_max_hz(fs_report: int) -> float:
    """Frt = min(Fs / 5, 5 Hz), the M-class measurement-bandwidth limit (Table 5)."""
    return min(fs_report / 5.0, 5.0)


def printed(value: float) -> float:
    """``value`` to two significant figures, as the standard's tables print a limit that a
    formula gives (14 Hz/s where ``0.18 pi Frt^2`` is 14.137 at Frt = 5 Hz): the test judges
    against the printed figure, not the formula's unrounded value."""
    if value == 0.0 or not math.isfinite(value):
        return value
    digits = 1 - math.floor(math.log10(abs(value)))
    return round(value, digits)


def limits(family: str, f0: int, fs_report: int) -> dict[str, float]:
    """The M-class limits of one test family (keys: tve_pct, fe_hz, rfe_hz_per_s,
    response_s, fe_response_s, rfe_response_s, delay_s, overshoot_pct, latency_s)."""
    latency = {"latency_s": 5.0 / fs_report}
    if family in ("steady-frequency", "steady-magnitude"):
        return {"tve_pct": 1.0, "fe_hz": 0.005, "rfe_hz_per_s": 0.1, **latency}
    if family == "harmonic":
        return {"tve_pct": 1.0, "fe_hz": 0.025 if fs_report > 20 else 0.005, **latency}
    if family == "out-of-band":
        return {"tve_pct": 1.3, "fe_hz": 0.01, **latency}
    if family in ("am", "pm"):
        frt = modulation_max_hz(fs_report)
        return {
            "tve_pct": 3.0,
            "fe_hz": printed(0.06 * frt),
            "rfe_hz_per_s": printed(0.18 * math.pi * frt * frt),
            **latency,
        }
    if family == "ramp":
        return {"tve_pct": 1.0, "fe_hz": 0.01, "rfe_hz_per_s": 0.2, **latency}
    if family in ("step-magnitude", "step-phase"):
        return {
            "response_s": 7.0 / fs_report,
            "fe_response_s": 14.0 / fs_report,
            "rfe_response_s": 14.0 / fs_report,
            "delay_s": 1.0 / (4.0 * fs_report),
            "overshoot_pct": 10.0,
            **latency,
        }
    raise ValueError(f"family: expected a C37.118.1 test family, got {family!r}")


# thresholds that define response times (the steady-state limits)
STEP_THRESHOLDS = {"tve_pct": 1.0, "fe_hz": 0.005, "rfe_hz_per_s": 0.1}


@dataclass(frozen=True)
class TestSignal:
    """One test condition: x(t) and its truth, with the times that are scored."""

    family: str
    label: str
    f0: int
    fs_report: int
    duration_s: float
    signal: Callable[[np.ndarray], np.ndarray]
    truth: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]  # X, f, rocof
    score_from_s: float  # reports before this are settling
    excluded: tuple[tuple[float, float], ...] = ()  # (start, end) intervals not scored
    step_time_s: float | None = None
    step_kind: str | None = None  # "magnitude" or "phase"
    step_size: float = 0.0  # relative magnitude or radians
    sample_rate_hz: float = SAMPLE_RATE_HZ
    tags: tuple[str, ...] = field(default_factory=tuple)

    def scored(self, t: np.ndarray) -> np.ndarray:
        keep = (t >= self.score_from_s) & (t <= self.duration_s)
        for a, b in self.excluded:
            keep &= ~((t > a) & (t < b))
        return keep


def _steady(f0: int, fs_report: int, f: float, mag: float, settle: float, dur: float, family: str) -> TestSignal:
    phi0 = 0.3

    def signal(t: np.ndarray) -> np.ndarray:
        return mag * np.cos(2.0 * np.pi * f * t + phi0)

    def truth(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = mag * SQRT_HALF * np.exp(1j * (2.0 * np.pi * (f - f0) * t + phi0))
        return x, np.full(t.shape, f), np.zeros(t.shape)

    label = f"f = {f:g} Hz" if family == "steady-frequency" else f"magnitude {100 * mag:g} %"
    return TestSignal(family, label, f0, fs_report, dur, signal, truth, settle)


def _with_interferer(
    f0: int, fs_report: int, f_in: float, f_i: float, amp: float, settle: float, dur: float, family: str
) -> TestSignal:
    phi0, phi_i = 0.3, 1.1

    def signal(t: np.ndarray) -> np.ndarray:
        return np.cos(2.0 * np.pi * f_in * t + phi0) + amp * np.cos(2.0 * np.pi * f_i * t + phi_i)

    def truth(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = SQRT_HALF * np.exp(1j * (2.0 * np.pi * (f_in - f0) * t + phi0))
        return x, np.full(t.shape, f_in), np.zeros(t.shape)

    label = f"h{round(f_i / f0)}" if family == "harmonic" else f"f = {f_in:g} Hz, interferer {f_i:g} Hz"
    return TestSignal(family, label, f0, fs_report, dur, signal, truth, settle)


def _modulation(f0: int, fs_report: int, fm: float, kind: str, settle: float) -> TestSignal:
    kx, ka = (0.1, 0.0) if kind == "am" else (0.0, 0.1)
    dur = settle + max(1.0, 1.0 / fm)
    wm = 2.0 * np.pi * fm

    def signal(t: np.ndarray) -> np.ndarray:
        return (1.0 + kx * np.cos(wm * t)) * np.cos(2.0 * np.pi * f0 * t + ka * np.cos(wm * t - np.pi))

    def truth(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = SQRT_HALF * (1.0 + kx * np.cos(wm * t)) * np.exp(1j * ka * np.cos(wm * t - np.pi))
        f = f0 - ka * fm * np.sin(wm * t - np.pi)
        rocof = -ka * wm * fm * np.cos(wm * t - np.pi)
        return x, f, rocof

    return TestSignal(kind, f"fm = {fm:g} Hz", f0, fs_report, dur, signal, truth, settle)


def _ramp(f0: int, fs_report: int, rate: float, settle: float) -> TestSignal:
    half = frequency_range_hz(fs_report)
    f_start = f0 - half if rate > 0 else f0 + half
    t1 = settle + 0.5
    t2 = t1 + 2.0 * half / abs(rate)
    dur = t2 + 0.5
    phi0 = 0.3

    def dphase(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(phase relative to the nominal cosine, frequency, rocof)."""
        tc = np.clip(t, t1, t2)
        nu0 = f_start - f0
        ph = 2.0 * np.pi * (nu0 * tc + 0.5 * rate * (tc - t1) ** 2)
        nu_end = nu0 + rate * (t2 - t1)
        ph = ph + 2.0 * np.pi * (nu0 * np.minimum(t - t1, 0.0) + nu_end * np.maximum(t - t2, 0.0))
        f = f0 + nu0 + rate * (tc - t1)
        rocof = np.where((t >= t1) & (t <= t2), rate, 0.0)
        return ph + phi0, f, rocof

    def signal(t: np.ndarray) -> np.ndarray:
        ph, _, _ = dphase(t)
        y: np.ndarray = np.cos(2.0 * np.pi * f0 * t + ph)
        return y

    def truth(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ph, f, rocof = dphase(t)
        return SQRT_HALF * np.exp(1j * ph), f, rocof

    excl = 7.0 / fs_report
    excluded = ((t1 - excl, t1 + excl), (t2 - excl, t2 + excl))
    label = f"{rate:+g} Hz/s, {f_start:g} -> {f_start + rate * (t2 - t1):g} Hz"
    return TestSignal("ramp", label, f0, fs_report, dur, signal, truth, settle, excluded=excluded)


def _step(f0: int, fs_report: int, kind: str, sign: float, offset_frac: float, settle: float) -> TestSignal:
    ts = settle + 0.5 + offset_frac / fs_report
    dur = ts + 1.0
    kx = 0.1 * sign if kind == "magnitude" else 0.0
    ka = math.radians(10.0) * sign if kind == "phase" else 0.0
    phi0 = 0.3

    def signal(t: np.ndarray) -> np.ndarray:
        u = (t >= ts).astype(np.float64)
        return (1.0 + kx * u) * np.cos(2.0 * np.pi * f0 * t + phi0 + ka * u)

    def truth(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u = (t >= ts).astype(np.float64)
        x = SQRT_HALF * (1.0 + kx * u) * np.exp(1j * (phi0 + ka * u))
        return x, np.full(t.shape, float(f0)), np.zeros(t.shape)

    return TestSignal(
        f"step-{kind}",
        f"{'+' if sign > 0 else '-'}{'10 %' if kind == 'magnitude' else '10 deg'}",
        f0,
        fs_report,
        dur,
        signal,
        truth,
        settle,
        step_time_s=ts,
        step_kind=kind,
        step_size=kx if kind == "magnitude" else ka,
    )


FAMILIES = (
    "steady-frequency",
    "steady-magnitude",
    "harmonic",
    "out-of-band",
    "am",
    "pm",
    "ramp",
    "step-magnitude",
    "step-phase",
)


def generate(
    family: str, f0: int, fs_report: int, *, full: bool, settle_s: float, n_offsets: int = 10
) -> Iterator[TestSignal]:
    """The test conditions of one family. ``full`` sweeps what the standard sweeps (1 Hz /
    0.1 Hz / every harmonic); otherwise a representative subset, always including the
    extremes (range edges, passband edges, the highest harmonic and modulation)."""
    dur = settle_s + 1.0
    if family == "steady-frequency":
        half = frequency_range_hz(fs_report)
        grid = np.linspace(-half, half, 21 if full else 5)
        for df in grid:
            yield _steady(f0, fs_report, f0 + float(df), 1.0, settle_s, dur, family)
    elif family == "steady-magnitude":
        for mag in np.arange(1, 13) / 10.0 if full else (0.1, 1.0, 1.2):
            yield _steady(f0, fs_report, float(f0), float(mag), settle_s, dur, family)
    elif family == "harmonic":
        for h in range(2, 51) if full else (2, 3, 5, 13, 50):
            yield _with_interferer(f0, fs_report, float(f0), float(h * f0), 0.1, settle_s, dur, family)
    elif family == "out-of-band":
        offsets = (-0.05 * fs_report, 0.0, 0.05 * fs_report)
        lo_edge, hi_edge = f0 - fs_report / 2.0, f0 + fs_report / 2.0
        if full:
            fis = [*np.arange(10.0, lo_edge + 0.5, 1.0), *np.arange(hi_edge, 2.0 * f0 + 0.5, 1.0)]
        else:
            fis = [10.0, lo_edge, hi_edge, 2.0 * f0]
        for off in offsets if full else (-0.05 * fs_report, 0.05 * fs_report):
            for fi in fis:
                yield _with_interferer(f0, fs_report, f0 + off, float(fi), 0.1, settle_s, dur, family)
    elif family in ("am", "pm"):
        frt = modulation_max_hz(fs_report)
        fms = np.round(np.arange(0.1, frt + 1e-9, 0.1 if full else frt / 2.0), 6) if full else (frt / 5.0, frt)
        for fm in fms:
            yield _modulation(f0, fs_report, float(fm), family, settle_s)
    elif family == "ramp":
        for rate in (1.0, -1.0):
            yield _ramp(f0, fs_report, rate, settle_s)
    elif family in ("step-magnitude", "step-phase"):
        kind = family.split("-")[1]
        for sign in (1.0, -1.0):
            for i in range(n_offsets):
                yield _step(f0, fs_report, kind, sign, i / n_offsets, settle_s)
    else:
        raise ValueError(f"family: expected one of {FAMILIES}, got {family!r}")
