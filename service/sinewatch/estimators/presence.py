"""Signal presence: is there a signal to estimate, and for how long has there been one?

Not an estimator: the pipeline runs it beside every channel's estimator to fill
``diagnostics.valid`` (an estimate is a measurement only while the signal it describes is
present, and only once the estimator's own memory holds nothing but that signal).

The level is the one-cycle RMS of the AC part refreshed every half cycle, as IEC 61000-4-30
(Sec. 5.4, voltage dips and interruptions, its U_rms(1/2)) measures it: at the end of each
half cycle of H = max(1, round(fs / (2 f_nominal))) samples, over the last two half cycles
(M = 2 H samples),

(L)  ``L^2 = max(0, S2 / M - (S1 / M)^2)``, ``S1 = sum x``, ``S2 = sum x^2`` over the window,

so a DC offset is not a signal. The reference is the recent level, a peak hold that decays
with time constant ``tau`` while the signal is present and is frozen while it is absent:

(R)  ``R = max(L, R' exp(-H / (tau fs)))`` while present, ``R = R'`` while absent (R' the
     previous half cycle's reference).

(A)  The signal is absent from a half-cycle boundary to the next when ``L < ratio R`` there
     (default ratio 0.1: IEEE Std 1159-2019 Table 2 calls a fall below 0.1 pu an
     interruption: strictly below, so 0.1 pu itself is a sag) or ``L = 0``; before the first
     full cycle it is absent too.

(H)  (validity rules version 2) The fall is judged against ``max(R, R_-1, R_-2)``, R as it
     was one and two half cycles back: while a one-cycle window straddles the onset of an
     interruption its level is still above 0.1 R, so the signal counts as present and R
     decays by ``exp(-H / (tau fs))`` at each of those two readings (2 % at 50 Hz); a fall
     to 0.099 pu then reads 0.101 of the decayed R and was missed. Against the reference from
     before the onset it is 0.099 and flagged, and R is frozen at that reference while the
     signal stays absent.

(E)  (validity rules version 3) An absence ends only when the level is back to ``(ratio +
     hysteresis) R`` (``DEFAULT_HYSTERESIS`` 0.02: IEC 61000-4-30 ends a dip or interruption
     at its threshold plus a hysteresis, typically 2 % of the declared voltage). A one-cycle
     window of the estimator's lowest expected frequency (40 Hz) over a 50 Hz signal is not a
     whole number of its cycles, so its level ripples by a few per cent with the phase: a
     fall to 0.099 pu read present again every 25 ms and, once the ripple let it through, for
     its last 50 ms.

(F)  (validity rules version 4) An onset is also read within a third of a cycle, by comparing
     the signal with the sinusoid of an earlier reading: at the nominal frequency a sine and
     its copy a quarter cycle (Q = max(1, round(fs / (4 f_nominal))) samples) earlier are in
     quadrature, so ``P_n = (x_n - mu)^2 + (x_{n-Q} - mu)^2`` is its squared magnitude A^2 =
     2 L^2 at every phase (mu a one-cycle mean, the DC part). The signal is absent from sample
     n on when the mean of P over the last m = max(1, min(16, round(Q / 4))) samples falls
     below ``2 k^2 L^2`` (``FAST_RATIO`` k = 0.35, L the larger of the last two levels): the
     magnitude fell to below 0.35 of what it was. mu is the mean of the reading before the
     last, and L the larger of the last two levels, because a reading whose window straddles
     the onset has neither the signal's mean nor its level. Away from the nominal frequency
     the pair is not in quadrature (40 to 65 Hz in a 50 Hz detector: P between 0.55 and 1.45
     of 2 L^2), and a harmonic ripples it (a 50 % third: P at least 0.2 of it), all above
     0.35^2 = 0.12; an interruption to 0.099 pu leaves at most 0.026 R^2 (noise included: the
     level test calls it absent only when noise and what is left are below 0.1 R together).
     The test reads an onset once all of its 2 m samples are in the interruption: ``Q + m -
     1`` samples after it (6.1 ms at 50 Hz, 5.1 ms at 60 Hz at 10 kHz), the hold-back
     (:attr:`SignalPresence.onset_latency_samples`). It is off, and the hold-back is the level
     test's (4 H), while it cannot be trusted: x_n and x_{n-Q} correlate by more than
     ``FAST_MAX_CORR`` (0.5) over a cycle (the signal far from the detector's frequency), a DC
     part above ``FAST_DC`` (0.25) of R (mu is one cycle's mean, off by up to 0.15 L for 45 to
     55 Hz in a 50 Hz window), or before one cycle of signal since a start or a reset. The
     level test still ends an absence (E), so a fast "absent" lasts until the next half-cycle
     reading at least. What it also reads as an onset: a fall by more than a factor of about
     three within a quarter cycle that the level test calls a deep sag (0.1 to 0.35 pu), a
     phase jump of about 60 degrees or more, and in a 40 Hz detector on a 50 Hz signal the
     onset of a sag to 0.5 pu; the estimates across them are then not valid for one memory.

(G)  (validity rules version 5) An edge: at a reading, a level below ``EDGE_RATIO`` (0.8) of
     the level two readings back (the cycle just before this reading's, not overlapping it),
     or above 1 / 0.8 of it, starts the run over (the signal stays present). A sag to 0.5 pu
     and its end are edges; an observer's state still holds the old level across them
     (``kkl`` 12 Hz, ``kkl-biased`` 22 Hz, ``sogi-fll`` 1.2 Hz, ``ges-kalman`` 0.32 Hz off while
     valid under version 4), so no estimate is valid until the estimator's memory holds none of
     it. A step to 0.6 or 1.5 of the level, or beyond, is read within 3 H at any phase; one
     between 0.6 and 0.8 only at some phases (no reading compares a whole cycle of each level
     then). C37.118.1's +-10 % magnitude step, amplitude modulation, noise down to 0 dB SNR
     and harmonics are not edges (``tests/test_validity.py``).

Freezing R while absent keeps a lost signal absent however long it stays lost (noise at 30 dB
below the signal never becomes "the signal"); letting it decay while present lets a sustained
change of operating level become the new reference within a few ``tau``. A sag to 0.3 pu is
a signal (valid) for the level test; its transitions are what ``converged`` is for.

Each sample's output is the run length: the number of consecutive samples, up to and
including this one, at which the signal was present by the last decision (capped at 2^62). The pipeline calls an
estimate valid when the run length at its sample is at least the estimator's memory
(:attr:`sinewatch.estimators.base.Estimator.memory_samples`): present now, and present
throughout the span of input the estimate depends on. At a channel's start the run length
starts at 0, so the first estimates (before one memory of signal) are not valid either.

Onset latency: the level of a one-cycle window falls below 0.1 of R only once about 99 % of
the window is the interruption, and it is read every half cycle, so the level test says so
within one and a half nominal cycles (3 H samples) of the onset; the quadrature test (F)
within ``Q + m - 1``. An estimate made in that time would read as valid though its window
holds the interruption: the pipeline holds every estimate back by the detector's latency
and judges it then (``hold_estimates``, on by default; docs/validity.md says what it costs;
:attr:`SignalPresence.onset_latency_samples`).

The level's sums are of two half cycles only, started afresh each half cycle (no running
sum, so no accumulated rounding); the quadrature test's running sum of m values of P is
summed afresh at every half-cycle reading. The state is a few numbers and a ring of the
last Q + m samples; the outputs depend only on the samples, not on how they are cut into
blocks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sinewatch.estimators.base import decode_array, encode_array, kernel, kernel_samples, ring_write
from sinewatch.schemas.errors import ParameterError

PRESENCE_STATE_VERSION = 4  # 3: no level two readings back (G); 2: no quadrature test (its ring and sums); 1: no R one and two half cycles back
DEFAULT_RATIO = 0.1  # IEEE 1159: below 0.1 pu is an interruption
DEFAULT_TAU_S = 1.0  # decay of the reference level while the signal is present
DEFAULT_HYSTERESIS = 0.02  # (E): an absence ends at 0.12 of the reference (validity rules version 3)
FAST_RATIO = 0.35  # (F): absent when the quadrature magnitude falls below 0.35 of the last level's
FAST_DC = 0.25  # (F) is off while the one-cycle mean is above 0.25 of the reference
FAST_MAX_CORR = 0.5  # (F) is off while x_n and x_{n-Q} correlate more (far from quadrature)
FAST_MAX_MEAN = 16  # (F): at most 16 values of P averaged (noise), fewer below 20 kHz at 50 Hz
EDGE_RATIO = (
    0.8  # (G): a level below 0.8, or above 1 / 0.8, of the cycle before it is an edge (validity rules version 5)
)
RUN_CAP = 1 << 62

# slots of "sums": the previous half cycle's S1, S2, the current one's S1, S2, then R, the
# last level squared, R as it was one and two half cycles back; for (F): the one-cycle mean
# in use (the reading before the last's), the running sum of P over the last m samples, the
# last reading's mean, the level before the last, the previous and the current half cycle's
# sum of x_n x_{n-Q}, the lag-Q correlation in use and the last reading's
_P1, _P2, _C1, _C2, _R, _R1, _R2, _MU, _PSUM, _MU1, _L1, _Q1, _Q2, _CQ, _CQ1, _L2 = (
    0,
    1,
    2,
    3,
    4,
    6,
    7,
    8,
    9,
    10,
    11,
    12,
    13,
    14,
    15,
    16,
)
_N_SUMS = 17  # slot 16: the level two readings back (G), the cycle before the last one read
# slots of "counters": samples in the current half cycle, half cycles seen (up to 2), run
# length, present (0/1: the last decision), samples in the ring (up to its length), the
# ring's next slot, armed (1: the running sum holds the last m values of P)
_COUNT, _HALVES, _RUN, _PRESENT, _FILL, _POS, _ARMED = 0, 1, 2, 3, 4, 5, 6
_N_COUNTERS = 7
# slots of the kernel's constants (one float array: the single and the bank kernel take the same)
_K_HALF, _K_DECAY, _K_RATIO, _K_HOLD, _K_HYST, _K_QUARTER, _K_MEAN, _K_FAST, _K_EDGE = range(9)


@kernel
def _p_sum(ring: np.ndarray, pos: int, quarter: int, m: int, mu: float) -> float:
    """Sum of P over the m samples before ring slot ``pos`` (the next to write), afresh."""
    size = ring.shape[0]
    total = 0.0
    for k in range(1, m + 1):
        a = ring[(pos - k) % size] - mu
        b = ring[(pos - k - quarter) % size] - mu
        total += a * a + b * b
    return total


@kernel
def _fast_usable(mu: float, cq: float, r: float) -> bool:
    """(F) applies: a DC part at most FAST_DC of R and the pair close enough to quadrature
    (lag-Q correlation at most FAST_MAX_CORR: the signal near the detector's frequency)."""
    return abs(mu) <= FAST_DC * r and abs(cq) <= FAST_MAX_CORR


@kernel
def presence_kernel(
    x: np.ndarray, sums: np.ndarray, counters: np.ndarray, ring: np.ndarray, consts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run (L), (R), (A), and (F) when ``consts`` says so, over ``x``; return ``(run, level,
    new_sums, new_counters, new_ring)``: per sample the run length of presence and the last
    level read (0 before the first). ``consts``: :meth:`SignalPresence.params`. Pure: the
    inputs are not modified."""
    half = int(consts[_K_HALF])
    decay, ratio, hysteresis = consts[_K_DECAY], consts[_K_RATIO], consts[_K_HYST]
    hold = consts[_K_HOLD] != 0.0
    quarter, m, fast = int(consts[_K_QUARTER]), int(consts[_K_MEAN]), consts[_K_FAST] != 0.0
    edge = consts[_K_EDGE]  # (G): 0 off
    l2 = sums[_L2]
    p1, p2, c1, c2, r = sums[_P1], sums[_P2], sums[_C1], sums[_C2], sums[_R]
    r1, r2, mu, psum, mu1, l1 = sums[_R1], sums[_R2], sums[_MU], sums[_PSUM], sums[_MU1], sums[_L1]
    q1, q2, cq, cq1 = sums[_Q1], sums[_Q2], sums[_CQ], sums[_CQ1]
    count, halves, run, present = counters[_COUNT], counters[_HALVES], counters[_RUN], counters[_PRESENT]
    fill, pos, armed = counters[_FILL], counters[_POS], counters[_ARMED]
    ring = ring.copy()
    size = ring.shape[0]
    level = math.sqrt(sums[5])  # the last level read (its square, kept for the outputs)
    n = x.shape[0]
    run_out = np.empty(n, dtype=np.int64)
    level_out = np.empty(n)
    m_total = 2.0 * half
    thresh = m * 2.0 * FAST_RATIO * FAST_RATIO * max(level, l1) ** 2  # (F), from the last two readings
    # the ring's indices wrap by a compare, not a modulo (an integer division a sample each,
    # the larger part of the detector's time); pos is in [0, size) from here on, as a state
    # this kernel wrote always has it (the modulo once keeps a forged state's reads in the ring)
    pos = pos % size
    for j in range(n):
        xj = np.float64(x[j])  # float32 samples are summed in float64, as if converted first
        c1 += xj
        c2 += xj * xj
        count += 1
        if fast:  # (F): the ring of the last Q + m samples, the running sum of P, the lag-Q sums
            iq = pos - quarter  # quarter < size, so one wrap at most
            xq = ring[iq + size if iq < 0 else iq]
            q2 += xj * xq
            if armed:
                a = xj - mu
                b = xq - mu
                im = pos - m  # m < size
                c = ring[im + size if im < 0 else im] - mu
                d = ring[pos] - mu  # the sample Q + m back, leaving the ring
                psum += a * a + b * b - c * c - d * d
            pos, fill = ring_write(ring, xj, pos, fill)  # base.py's window push, without its hop
        if count == half:  # a half-cycle boundary: read the last cycle
            if halves < 2:
                halves += 1
            if halves == 2:
                mean = (p1 + c1) / m_total
                ms = (p2 + c2) / m_total - mean * mean
                l2, l1 = l1, level
                level = math.sqrt(ms) if ms > 0.0 else 0.0
                rd = r * decay
                ref = level if level > rd else rd
                judge = ref
                if hold:  # (H): the reference of two half cycles back, before an onset's readings
                    judge = max(ref, r1, r2)
                need = ratio if present else ratio + hysteresis  # (E): an absence ends higher up
                present = 1 if (level > 0.0 and level >= need * judge) else 0  # strictly below: absent
                if edge > 0.0 and l2 > 0.0 and (level < edge * l2 or edge * level > l2):
                    run = 0  # (G): the level stepped since the cycle before: the run starts over
                r2, r1 = r1, r
                if present:
                    r = ref
                elif hold:  # absent: frozen at the level from before the onset's readings
                    r = judge
                if fast:
                    # (F) takes the sinusoid of the reading before this one: a reading whose
                    # window straddles an onset has a mean and a correlation that are neither
                    mu, cq = mu1, cq1
                    mu1 = mean
                    cq1 = ((q1 + q2) / m_total - mean * mean) / ms if ms > 0.0 else 1.0
                    armed = 1 if fill == size else 0
                    psum = _p_sum(ring, pos, quarter, m, mu) if armed else 0.0
                    thresh = m * 2.0 * FAST_RATIO * FAST_RATIO * max(level, l1) ** 2
            p1, p2, c1, c2 = c1, c2, 0.0, 0.0
            q1, q2 = q2, 0.0
            count = 0
        if fast and armed and present and psum < thresh and _fast_usable(mu, cq, r):
            present = 0  # (F): the magnitude fell within a quarter cycle
        if present:
            if run < RUN_CAP:
                run += 1
        else:
            run = 0
        run_out[j] = run
        level_out[j] = level
    new_sums = np.array([p1, p2, c1, c2, r, level * level, r1, r2, mu, psum, mu1, l1, q1, q2, cq, cq1, l2])
    new_counters = np.array([count, halves, run, present, fill, pos, armed], dtype=np.int64)
    return run_out, level_out, new_sums, new_counters, ring


@kernel
def presence_bank_kernel(
    x: np.ndarray, columns: np.ndarray, sums: np.ndarray, counters: np.ndarray, rings: np.ndarray, consts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`presence_kernel` on columns ``columns`` of ``x`` (n, C), detector i's state in
    row i of ``sums``, ``counters`` and ``rings``: returns the runs (D, n), the new state
    rows and each detector's onset latency after the frame (what
    :attr:`SignalPresence.onset_latency_samples` reads from its new state: the same
    comparisons, :func:`_fast_usable`). Each detector's are exactly presence_kernel's on its
    column alone: it is that kernel, called per column (one call from Python for a frame's
    channels instead of one each)."""
    d = columns.shape[0]
    runs = np.empty((d, x.shape[0]), dtype=np.int64)
    new_sums = np.empty_like(sums)
    new_counters = np.empty_like(counters)
    new_rings = np.empty_like(rings)
    latency = np.empty(d, dtype=np.int64)
    fast = consts[_K_FAST] != 0.0
    level_test = (4 if fast else 3) * int(consts[_K_HALF])  # the level test's latency, 3 H or 4 H
    quadrature_test = int(consts[_K_QUARTER]) + int(consts[_K_MEAN]) - 1  # (F)'s, Q + m - 1
    for i in range(d):
        run, _level, s, c, g = presence_kernel(x[:, columns[i]], sums[i], counters[i], rings[i], consts)
        runs[i] = run
        new_sums[i] = s
        new_counters[i] = c
        new_rings[i] = g
        latency[i] = level_test
        if fast and c[_ARMED] != 0 and _fast_usable(s[_MU], s[_CQ], s[_R]) and _fast_usable(s[_MU1], s[_CQ1], s[_R]):
            latency[i] = quadrature_test
    return runs, new_sums, new_counters, new_rings, latency


def update_presence_bank(detectors: list[SignalPresence], x: np.ndarray, columns: list[int]) -> np.ndarray | None:
    """Advance ``detectors[i]`` by column ``columns[i]`` of the float64 frame ``x`` (n, C):
    the runs (len(detectors), n), each row what ``detectors[i].update(x[:, columns[i]])``
    returns, and each detector's state as that call leaves it. None (nothing done) when the
    detectors do not share their parameters or ``x`` is not float64: the caller then runs
    them one by one."""
    readings = read_presence_bank(detectors, x, columns)
    return None if readings is None else readings.runs


@dataclass(frozen=True, slots=True)
class PresenceBankReadings:
    """What a bank of detectors read over a frame: each one's runs, and after the frame its
    ``run_samples`` and ``onset_latency_samples``, read from the bank's new state arrays at
    once (the same values as the properties, without their Python a detector)."""

    runs: np.ndarray  # (D, n)
    run_samples: list[int]
    onset_latency_samples: list[int]


def read_presence_bank(
    detectors: list[SignalPresence], x: np.ndarray, columns: list[int]
) -> PresenceBankReadings | None:
    """:func:`update_presence_bank`, with the detectors' readings after the frame."""
    first = detectors[0]
    if x.dtype != np.float64 or x.ndim != 2:
        return None
    stacked = first.bank_rows
    if stacked is not None and stacked.holds(detectors):  # the last frame's bank, untouched since
        # (its detectors' parameters were found alike when it was gathered, and never change)
        sums, counters, rings = stacked.arrays
    else:
        params = first.params
        if any(d.params != params for d in detectors):
            return None
        # np.array of the rows, not np.stack: the same (D, k) array, without np.stack's checks
        # in Python (1.3 against 5.3 us an array of 8 rows, timeit)
        sums = np.array([d.sums for d in detectors])
        counters = np.array([d.counters for d in detectors])
        rings = np.array([d.ring for d in detectors])
    runs, new_sums, new_counters, new_rings, latency = presence_bank_kernel(
        kernel_samples(x), np.asarray(columns, dtype=np.int64), sums, counters, rings, first.consts
    )
    rows = _BankRows(tuple(detectors), (new_sums, new_counters, new_rings))
    for d, s, c, g in zip(detectors, *rows.rows, strict=True):
        d.sums, d.counters, d.ring = s, c, g
    first.bank_rows = rows
    return PresenceBankReadings(runs, new_counters[:, _RUN].tolist(), latency.tolist())


class _BankRows:
    """A bank's new state arrays (sums, counters, rings: a row a detector) and the row views
    each detector was given: the next frame of the same bank passes the arrays as they are,
    without gathering them again, while every detector still holds exactly those rows (a
    detector updated, reset or restored on its own holds new arrays, and the bank is then
    gathered afresh)."""

    __slots__ = ("arrays", "members", "rows")

    def __init__(self, members: tuple[SignalPresence, ...], arrays: tuple[np.ndarray, np.ndarray, np.ndarray]):
        self.members = members
        self.arrays = arrays
        self.rows = tuple(list(a) for a in arrays)  # each row a view, made in one C call an array

    def holds(self, detectors: list[SignalPresence]) -> bool:
        members = self.members
        if len(members) != len(detectors):
            return False
        sums, counters, rings = self.rows
        return all(
            a is d and d.sums is s and d.counters is c and d.ring is g
            for a, d, s, c, g in zip(members, detectors, sums, counters, rings, strict=True)
        )


class SignalPresence:
    """The presence detector of one channel: owns the state, runs :func:`presence_kernel`."""

    def __init__(
        self,
        sample_rate_hz: float,
        nominal_frequency_hz: float = 50.0,
        *,
        ratio: float = DEFAULT_RATIO,
        tau_s: float = DEFAULT_TAU_S,
        hold: bool = True,
        hysteresis: float = 0.0,
        fast: bool = False,
        edge: float = 0.0,
    ) -> None:
        if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise ParameterError(f"sample_rate_hz: expected a finite value > 0, got {sample_rate_hz}")
        if not (math.isfinite(nominal_frequency_hz) and nominal_frequency_hz > 0):
            raise ParameterError(f"nominal_frequency_hz: expected a finite value > 0, got {nominal_frequency_hz}")
        if not (0 < ratio < 1):
            raise ParameterError(f"ratio: expected 0 < ratio < 1, got {ratio}")
        self.sample_rate_hz = float(sample_rate_hz)
        self.nominal_frequency_hz = float(nominal_frequency_hz)
        self.half_cycle_samples = max(1, round(sample_rate_hz / (2.0 * nominal_frequency_hz)))
        self.quarter_cycle_samples = max(1, round(sample_rate_hz / (4.0 * nominal_frequency_hz)))  # (F)'s Q
        self.mean_samples = max(1, min(FAST_MAX_MEAN, round(self.quarter_cycle_samples / 4)))  # (F)'s m
        self.ratio = float(ratio)
        self.decay = math.exp(-self.half_cycle_samples / (tau_s * sample_rate_hz))
        self.hold = 1 if hold else 0  # (H); off: the rule of earlier builds (their recordings)
        if not (0.0 <= hysteresis < 1.0 - ratio):
            raise ParameterError(f"hysteresis: expected 0 <= hysteresis < {1.0 - ratio}, got {hysteresis}")
        self.hysteresis = float(hysteresis)  # (E); 0: the rule of earlier builds
        self.fast = 1 if fast else 0  # (F); off: the rules of earlier builds (validity rules version 3 and before)
        if not (edge == 0.0 or 0.0 < edge < 1.0):
            raise ParameterError(f"edge: expected 0 (off) or 0 < edge < 1, got {edge}")
        self.edge = float(edge)  # (G); 0: the rules of earlier builds (validity rules version 4 and before)
        self.consts = np.array(self.params, dtype=np.float64)
        self.bank_rows: _BankRows | None = None  # the bank this detector led last (read_presence_bank)
        self.reset()

    def reset(self) -> None:
        """``sums`` (17,), ``counters`` (7,) int64: the slots listed at the top of this module;
        ``ring`` (Q + m,): the last samples, for (F)."""
        self.sums = np.zeros(_N_SUMS)
        self.counters = np.zeros(_N_COUNTERS, dtype=np.int64)
        self.ring = np.zeros(self.quarter_cycle_samples + self.mean_samples)

    def update(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-sample (run length of presence, level) over ``samples`` (1-D; converted to
        float64 unless they are the kernels' kind already (``kernel_samples``): the kernel
        sums in float64, so float32 samples give the same outputs either way)."""
        x = kernel_samples(np.asarray(samples))
        run, level, self.sums, self.counters, self.ring = presence_kernel(
            x, self.sums, self.counters, self.ring, self.consts
        )
        return run, level

    @property
    def params(self) -> tuple[int, float, float, int, float, int, int, int, float]:
        """The kernel's constants: (half, decay, ratio, hold, hysteresis, quarter, mean, fast, edge)."""
        return (
            self.half_cycle_samples,
            self.decay,
            self.ratio,
            self.hold,
            self.hysteresis,
            self.quarter_cycle_samples,
            self.mean_samples,
            self.fast,
            self.edge,
        )

    @property
    def onset_latency_samples(self) -> int:
        """Samples from the first sample of an interruption to the sample at which the
        detector says so, at most, as things stand now. The level test: the one-cycle window
        (2 H) must be all but filled with it (a fall to 0.099 of R reads below 0.1 R only once
        more than 99.98 % of the window is the interruption), and the next reading is up to
        H later: 3 H. The quadrature test (F), when on and armed: all of its 2 m values in
        the interruption, ``Q + m - 1``. The pipeline holds estimates back by this much."""
        # the hold reads this for every estimate: the test's own Python (``py_func``) on Python
        # floats, the same doubles and comparisons as the compiled one, without two numba
        # dispatches: 0.7 us instead of 1.6-2.5 (timeit, under load)
        usable = _fast_usable.py_func  # type: ignore[attr-defined]  # (numba's, not in its stubs)
        s = self.sums.tolist() if self.fast and self.counters[_ARMED] else None
        if s is not None and usable(s[_MU], s[_CQ], s[_R]) and usable(s[_MU1], s[_CQ1], s[_R]):
            return self.quarter_cycle_samples + self.mean_samples - 1
        # the level test, read in a window that is not a whole number of the signal's cycles
        # (a 40 Hz detector on 50 Hz, a 50 Hz one on 60 Hz), reads a fall to 0.099 up to about
        # 4 H after it (its level ripples with the phase): 4 H from rules version 4 on
        return (4 if self.fast else 3) * self.half_cycle_samples

    @property
    def run_samples(self) -> int:
        """The run length after the last sample seen."""
        return int(self.counters[_RUN])

    def get_state(self) -> dict[str, Any]:
        return {
            "format_version": PRESENCE_STATE_VERSION,
            "half_cycle_samples": self.half_cycle_samples,
            "sums": encode_array(self.sums),
            "counters": encode_array(self.counters),
            "ring": encode_array(self.ring),
        }

    def set_state(self, snapshot: dict[str, Any]) -> None:
        version = snapshot.get("format_version")
        if version not in (1, 2, 3, PRESENCE_STATE_VERSION):
            raise ParameterError(f"presence format_version: expected {PRESENCE_STATE_VERSION}, got {version!r}")
        if snapshot.get("half_cycle_samples") != self.half_cycle_samples:
            raise ParameterError(
                f"presence half_cycle_samples: expected {self.half_cycle_samples}, "
                f"got {snapshot.get('half_cycle_samples')!r}"
            )
        sums, counters = decode_array(snapshot["sums"]), decode_array(snapshot["counters"])
        ring = decode_array(snapshot["ring"]) if "ring" in snapshot else np.zeros_like(self.ring)
        if version == 1 and sums.shape == (6,):  # earlier builds: R back then is R
            sums = np.concatenate([sums, sums[_R : _R + 1], sums[_R : _R + 1]])
        if version in (1, 2) and sums.shape == (8,) and counters.shape == (4,):  # (F) not armed yet
            sums = np.concatenate([sums, np.zeros(_N_SUMS - 8)])
            counters = np.concatenate([counters, np.zeros(_N_COUNTERS - 4, dtype=np.int64)])
        if version == 3 and sums.shape == (_N_SUMS - 1,):  # no level two readings back: the last one's
            sums = np.concatenate([sums, sums[_L1 : _L1 + 1]])
        if sums.shape != (_N_SUMS,) or counters.shape != (_N_COUNTERS,) or ring.shape != self.ring.shape:
            raise ParameterError(
                f"presence state: expected shapes ({_N_SUMS},), ({_N_COUNTERS},) and {self.ring.shape}, "
                f"got {sums.shape}, {counters.shape} and {ring.shape}"
            )
        self.sums, self.counters, self.ring = sums, counters, ring


__all__ = [
    "DEFAULT_HYSTERESIS",
    "DEFAULT_RATIO",
    "DEFAULT_TAU_S",
    "EDGE_RATIO",
    "FAST_DC",
    "FAST_RATIO",
    "PresenceBankReadings",
    "SignalPresence",
    "presence_bank_kernel",
    "presence_kernel",
    "read_presence_bank",
    "update_presence_bank",
]
