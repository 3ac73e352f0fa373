"""IEC 61000-4-30 class A time aggregation of 10/12-cycle values: 150/180-cycle (about
3 s), 10-min and 2-h aggregates, the 10-s frequency value, with the resynchronisation on
the 10-min tick.

Reference: [4-30] IEC 61000-4-30:2015, "Testing and measurement techniques - Power quality
measurement methods", clauses 4.5 (measurement aggregation over time intervals, class A)
and 5.1 (power frequency). The standard's text is not reproduced here; what the rules
below rely on, besides the clause titles: the class A synchronisation figure of 4.5 as
instrument manuals quote it (a new 150/180-cycle interval starts at the 10-min tick "while
measurement of the existing 150/180 cycle time interval continues until it is complete",
the two overlapping: "overlap 2"), the 2-h interval "aggregated from twelve 10-min
intervals", and the class A frequency reading of 5.1 (every 10 s: the number of integral
cycles counted during the 10-s time clock interval divided by the cumulative duration of
those integer cycles; cycles that overlap the 10-s clock are discarded). Check the
standard before quoting compliance.

The rules implemented, for a stream of contiguous 10/12-cycle windows of one source
(:class:`WindowValues`, e.g. from :class:`sinewatch.power_quality.harmonics.HarmonicAnalyser`):

(A1) Aggregation of a quantity [4-30 4.5.1]: the square root of the arithmetic mean of
     the squared input values, ``sqrt(sum v_i^2 / n)`` (method ``"rms"``: magnitudes,
     harmonics, THD, unbalance). Frequency (method ``"cycles"``) follows the definition of
     [4-30 5.1]: the number of whole cycles counted divided by their cumulative duration;
     each window spans exactly ``N_i`` cycles of ``f_i``, so ``f = sum N_i / sum (N_i / f_i)``.
     A NaN value (undefined, e.g. THD of a dead channel) is left out of its quantity.
(A2) 150/180-cycle interval [4-30 4.5.2]: 15 contiguous 10/12-cycle values (150 cycles at
     50 Hz, 180 at 60 Hz, about 3 s), not aligned to the clock; its time stamp is the
     end of its last window.
(A3) 10-min interval [4-30 4.5.3]: aggregated from the 10/12-cycle values (not from the
     150/180-cycle ones), over the interval between two 10-min ticks of absolute time
     (``k * 600 s`` since the epoch); time stamp: the tick that ends it. A window belongs to
     the interval its *start* falls in, so the window in progress at a tick ("overlap 1")
     is the last one of the interval the tick ends.
(A4) Resynchronisation [4-30 4.5.2-4.5.3]: the window stream restarts at the tick (the
     analyser does this: its next window starts on the tick, overlapping overlap 1), and
     so does the 150/180-cycle count: a new 150/180-cycle interval starts with the first
     window of the new 10-min interval, while the one in progress at the tick goes on
     taking windows (the new stream's, which it shares with the new interval) until it
     has its 15 ("overlap 2"); its values then include windows of both 10-min intervals.
(A5) A discontinuity (a window that does not start where the previous one ended, other
     than at a tick) closes the 150/180-cycle intervals in progress (``complete = False``)
     and marks the 10-min interval incomplete; so does a 10-min interval whose windows do
     not cover it from tick to tick (the stream started or stopped inside it).
(A6) 2-h interval [4-30 4.5.4]: the RMS (A1) of the twelve 10-min values between two
     2-h ticks of absolute time (``k * 7200 s``), each 10-min value counting once;
     frequency by cycles over the cumulative duration of the 10-min intervals' cycles.
     Time stamp: the 2-h tick that ends it; published when its last 10-min interval
     closes; complete when all twelve 10-min values are.
(A7) 10-s frequency [4-30 5.1]: the fundamental's whole cycles lying within each 10-s
     interval of absolute time (``k * 10 s``): each window spans ``N_i`` cycles of
     ``1 / f_i`` from its start; a cycle that crosses a 10-s tick is discarded; at the
     10-min tick, the cycles of overlap 1 past the tick give way to the new stream's
     (counted once). ``f = count / sum of their durations``; published once a window
     starts past the interval; complete when the cycles cover it (the first starts,
     and the last ends, within one cycle of its ends) and no discontinuity broke it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from sinewatch.estimators.base import decode_array, encode_array
from sinewatch.schemas.errors import ParameterError
from sinewatch.schemas.power_quality import PqAggregate, finite_or_none

Method = Literal["rms", "cycles"]
NS_PER_S = 1_000_000_000
CONTIGUITY_NS = 1_000  # windows closer than this are contiguous (rounding of ns times)
TEN_S_NS = 10 * NS_PER_S  # (A7)
TWO_H_S = 7200.0  # (A6)
TEN_MIN_PER_TWO_H = 12
DEFAULT_METHODS: dict[str, Method] = {"frequency_hz": "cycles"}


@dataclass(frozen=True)
class WindowValues:
    """The 10/12-cycle values of one source over one window."""

    start_ns: int
    end_ns: int
    n_cycles: int
    values: Mapping[str, float]
    arrays: Mapping[str, np.ndarray] = field(default_factory=dict)


@dataclass
class _Accumulator:
    methods: Mapping[str, Method]
    start_ns: int | None = None
    end_ns: int | None = None
    n_windows: int = 0
    broken: bool = False  # a discontinuity inside (A5)
    sums: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    cycles: dict[str, float] = field(default_factory=dict)
    array_sums: dict[str, np.ndarray] = field(default_factory=dict)
    array_counts: dict[str, np.ndarray] = field(default_factory=dict)

    def add(self, w: WindowValues) -> None:
        if self.start_ns is None:
            self.start_ns = w.start_ns
        self.end_ns = w.end_ns
        self.n_windows += 1
        for name, v in w.values.items():
            v = float(v)
            self.sums.setdefault(name, 0.0)
            self.counts.setdefault(name, 0)
            self.cycles.setdefault(name, 0.0)
            if not math.isfinite(v):
                continue
            if self.methods.get(name, "rms") == "cycles":
                self.sums[name] += w.n_cycles / v  # (A1) duration of N_i cycles
                self.cycles[name] += w.n_cycles
            else:
                self.sums[name] += v * v  # (A1)
            self.counts[name] += 1
        for name, a in w.arrays.items():
            self._add_squares(name, np.asarray(a, dtype=np.float64))

    def add_interval(self, acc: _Accumulator) -> None:
        """(A6): one closed interval's aggregate as one value (RMS quantities); cycles and
        durations carried over whole (frequency)."""
        if self.start_ns is None:
            self.start_ns = acc.start_ns
        self.end_ns = acc.end_ns
        self.n_windows += 1
        for name, v in acc.values().items():
            self.sums.setdefault(name, 0.0)
            self.counts.setdefault(name, 0)
            self.cycles.setdefault(name, 0.0)
            if v is None:
                continue
            if self.methods.get(name, "rms") == "cycles":
                self.sums[name] += acc.sums[name]
                self.cycles[name] += acc.cycles[name]
            else:
                self.sums[name] += v * v
            self.counts[name] += 1
        for name, vals in acc.arrays().items():
            self._add_squares(name, np.array([math.nan if v is None else v for v in vals], dtype=np.float64))

    def _add_squares(self, name: str, a: np.ndarray) -> None:
        """(A1) per element of an array quantity: its square summed where it is finite, and counted."""
        ok = np.isfinite(a)
        if name not in self.array_sums:
            self.array_sums[name] = np.zeros(a.shape)
            self.array_counts[name] = np.zeros(a.shape, dtype=np.int64)
        self.array_sums[name] += np.where(ok, a * a, 0.0)
        self.array_counts[name] += ok

    def state(self) -> dict[str, Any]:
        return {
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "n_windows": self.n_windows,
            "broken": self.broken,
            "sums": self.sums,
            "counts": self.counts,
            "cycles": self.cycles,
            "array_sums": {k: encode_array(v) for k, v in self.array_sums.items()},
            "array_counts": {k: encode_array(v) for k, v in self.array_counts.items()},
        }

    def set_state(self, d: Mapping[str, Any]) -> None:
        self.start_ns, self.end_ns, self.n_windows, self.broken = (
            d["start_ns"],
            d["end_ns"],
            d["n_windows"],
            d["broken"],
        )
        self.sums = {k: float(v) for k, v in d["sums"].items()}
        self.counts = {k: int(v) for k, v in d["counts"].items()}
        self.cycles = {k: float(v) for k, v in d["cycles"].items()}
        self.array_sums = {k: decode_array(v) for k, v in d["array_sums"].items()}
        self.array_counts = {k: decode_array(v) for k, v in d["array_counts"].items()}

    def values(self) -> dict[str, float | None]:
        out: dict[str, float | None] = {}
        for name, s in self.sums.items():
            n = self.counts[name]
            if n == 0:
                out[name] = None
            elif self.methods.get(name, "rms") == "cycles":
                out[name] = finite_or_none(self.cycles[name] / s)  # (A1) cycles / duration
            else:
                out[name] = finite_or_none(math.sqrt(s / n))  # (A1)
        return out

    def arrays(self) -> dict[str, list[float | None]]:
        out = {}
        for name, s in self.array_sums.items():
            n = self.array_counts[name]
            with np.errstate(invalid="ignore", divide="ignore"):
                r = np.sqrt(s / n)
            out[name] = [finite_or_none(v) if c else None for v, c in zip(r.tolist(), n.tolist(), strict=True)]
        return out


@dataclass
class _TenSecond:
    """(A7) the whole cycles of one 10-s interval: count, cumulative duration (ns), the
    first cycle's start and the last one's end relative to the interval start (ns)."""

    count: int = 0
    duration_ns: float = 0.0
    first_ns: float = math.inf
    last_ns: float = -math.inf
    n_windows: int = 0
    broken: bool = False


def _ten_s_row(k: int, t: _TenSecond) -> list[Any]:
    """A 10-s interval's state as JSON (first/last are +-inf before any cycle: JSON has none)."""
    first, last = (t.first_ns, t.last_ns) if t.count else (None, None)
    return [k, t.count, t.duration_ns, first, last, t.n_windows, t.broken]


def window_cycles(start_ns: int, n_cycles: int, frequency_hz: float) -> list[tuple[int, float, float]]:
    """(A7): the whole cycles of a window within the 10-s intervals, as (interval index,
    start relative to the interval's start in ns, duration in ns); cycles that cross a
    10-s tick are left out. Relative times keep float64 exact to well below 1 ns."""
    period = NS_PER_S / frequency_hz
    k = start_ns // TEN_S_NS
    rel0 = float(start_ns - k * TEN_S_NS)
    out = []
    for j in range(n_cycles):
        cs = rel0 + j * period
        kk = k + int(cs // TEN_S_NS)
        cs -= (kk - k) * TEN_S_NS
        if cs + period <= TEN_S_NS:
            out.append((kk, cs, period))
    return out


class Aggregator:
    """Aggregates the 10/12-cycle values of one source; ``add`` returns the aggregates each
    window completes, oldest first: 10-s frequency values (A7) as their intervals pass,
    150/180-cycle ones (A2, A4), and at a tick the 10-min one (A3) and, at a 2-h tick,
    the 2-h one (A6).

    ``windows_per_interval`` is 15 (A2); ``tick_s`` the 10-min clock (A3), 600 s;
    ``long_ticks_per_two_h`` the 10-min intervals of a 2-h one (A6), 12; ``methods`` maps
    quantity names to ``"rms"`` or ``"cycles"`` (default: ``frequency_hz`` by cycles,
    everything else RMS).
    """

    def __init__(
        self,
        source: str,
        windows_per_interval: int = 15,
        tick_s: float = 600.0,
        methods: Mapping[str, Method] | None = None,
        long_ticks_per_two_h: int = TEN_MIN_PER_TWO_H,
    ) -> None:
        if windows_per_interval < 1:
            raise ParameterError(f"windows_per_interval: expected >= 1, got {windows_per_interval}")
        if not (math.isfinite(tick_s) and tick_s > 0):
            raise ParameterError(f"tick_s: expected a finite value > 0, got {tick_s}")
        if long_ticks_per_two_h < 1:
            raise ParameterError(f"long_ticks_per_two_h: expected >= 1, got {long_ticks_per_two_h}")
        self.source = source
        self.windows_per_interval = int(windows_per_interval)
        self.tick_ns = round(tick_s * NS_PER_S)
        self.two_h_ticks = int(long_ticks_per_two_h)  # (A6) 10-min intervals per 2-h one
        self.methods: dict[str, Method] = dict(DEFAULT_METHODS)
        self.methods.update(methods or {})
        self._short = _Accumulator(self.methods)
        self._finishing: _Accumulator | None = None  # (A4) the interval of overlap 2
        self._long = _Accumulator(self.methods)
        self._long_index: int | None = None
        self._last_end: int | None = None
        self._two_h = _Accumulator(self.methods)  # (A6)
        self._two_h_index: int | None = None
        self._two_h_complete = 0  # complete 10-min values in it
        self._ten_s: dict[int, _TenSecond] = {}  # (A7) open 10-s intervals by index
        self._last_cycles: list[tuple[int, float, float]] = []  # the last window's, for overlap 1

    def add(self, w: WindowValues) -> list[PqAggregate]:
        if w.end_ns <= w.start_ns:
            raise ParameterError(f"window: expected end_ns > start_ns, got {w.start_ns}..{w.end_ns}")
        out: list[PqAggregate] = []
        index = w.start_ns // self.tick_ns  # (A3) by the window's start
        contiguous = self._last_end is None or abs(w.start_ns - self._last_end) <= CONTIGUITY_NS
        overlap = self._last_end is not None and w.start_ns < self._last_end - CONTIGUITY_NS
        at_tick = self._long_index is not None and index != self._long_index
        out.extend(self._ten_seconds(w, contiguous, at_tick and overlap))
        if at_tick:
            out.extend(self._close_finishing())  # a second tick before it finished: as it is
            if contiguous or overlap:
                self._finishing = self._short if self._short.n_windows else None  # (A4) overlap 2
            else:
                out.extend(self._short_aggregate(self._short))  # (A5) the stream stopped before the tick
            self._short = _Accumulator(self.methods)
            out.extend(self._close_long())
        elif not contiguous:
            out.extend(self._close_short())  # (A5)
            out.extend(self._close_finishing())
            self._long.broken = True
        if self._long_index is None:
            self._long_index = index
        self._short.add(w)
        self._long.add(w)
        if self._finishing is not None:
            self._finishing.add(w)
            if self._finishing.n_windows == self.windows_per_interval:
                out.extend(self._close_finishing())
        self._last_end = w.end_ns
        if self._short.n_windows == self.windows_per_interval:  # (A2)
            out.extend(self._close_short())
        return out

    def flush(self) -> list[PqAggregate]:
        """Close what is open (end of stream): the 10-s, 150/180-cycle, 10-min and 2-h
        intervals in progress, ``complete = False`` unless they happen to be whole."""
        out = [self._ten_s_aggregate(k, self._ten_s.pop(k)) for k in sorted(self._ten_s)]
        out += self._close_finishing()
        out += self._close_short()
        if self._long_index is not None:
            out.extend(self._close_long())
        if self._two_h_index is not None:
            out.append(self._close_two_h())
        return out

    # ---- (A7) 10-s frequency -----------------------------------------------------------------
    def _ten_seconds(self, w: WindowValues, contiguous: bool, overlap_1: bool) -> list[PqAggregate]:
        if "frequency_hz" not in w.values:
            return []
        f = float(w.values["frequency_hz"])
        first = w.start_ns // TEN_S_NS
        if overlap_1:  # the last window's cycles from the new stream's start on give way
            for k in {k for k, _, _ in self._last_cycles}:
                item = self._ten_s.get(k)
                mine = [(cs, d) for kk, cs, d in self._last_cycles if kk == k]
                gone = [(cs, d) for cs, d in mine if k * TEN_S_NS + cs >= w.start_ns - CONTIGUITY_NS]
                if item is None or not gone:
                    continue
                item.count -= len(gone)
                item.duration_ns -= math.fsum(d for _, d in gone)
                item.n_windows -= len(gone) == len(mine)
        elif not contiguous:  # a hole: in the intervals open before it and the one after
            for item in self._ten_s.values():
                item.broken = True
            self._ten_s.setdefault(first, _TenSecond()).broken = True
        out = [self._ten_s_aggregate(k, self._ten_s.pop(k)) for k in sorted(self._ten_s) if k < first]
        cycles = window_cycles(w.start_ns, w.n_cycles, f) if math.isfinite(f) and f > 0 else []
        for k in {k for k, _, _ in cycles}:
            self._ten_s.setdefault(k, _TenSecond()).n_windows += 1
        for k, cs, d in cycles:
            item = self._ten_s[k]
            item.count += 1
            item.duration_ns += d
            item.first_ns = min(item.first_ns, cs)
            item.last_ns = max(item.last_ns, cs + d)
        self._last_cycles = cycles
        return out

    def _ten_s_aggregate(self, k: int, item: _TenSecond) -> PqAggregate:
        f = item.count * NS_PER_S / item.duration_ns if item.count else math.nan
        period = item.duration_ns / item.count if item.count else math.inf
        whole = not item.broken and item.first_ns <= period and item.last_ns >= TEN_S_NS - period
        return PqAggregate(
            source=self.source,
            interval="10-s",
            timestamp_ns=(k + 1) * TEN_S_NS,
            start_ns=k * TEN_S_NS,
            n_windows=item.n_windows,
            complete=whole,
            values={"frequency_hz": finite_or_none(f)},
        )

    # ---- (A2) (A4) 150/180-cycle -------------------------------------------------------------
    def _close_short(self) -> list[PqAggregate]:
        acc = self._short
        self._short = _Accumulator(self.methods)
        return self._short_aggregate(acc)

    def _close_finishing(self) -> list[PqAggregate]:
        acc, self._finishing = self._finishing, None
        return [] if acc is None else self._short_aggregate(acc)

    def _short_aggregate(self, acc: _Accumulator) -> list[PqAggregate]:
        if acc.n_windows == 0:
            return []
        assert acc.start_ns is not None and acc.end_ns is not None
        return [
            PqAggregate(
                source=self.source,
                interval="150/180-cycle",
                timestamp_ns=acc.end_ns,
                start_ns=acc.start_ns,
                n_windows=acc.n_windows,
                complete=acc.n_windows == self.windows_per_interval and not acc.broken,
                values=acc.values(),
                arrays=acc.arrays(),
            )
        ]

    # ---- (A3) 10-min, (A6) 2-h ---------------------------------------------------------------
    def _close_long(self) -> list[PqAggregate]:
        acc = self._long
        assert self._long_index is not None and acc.start_ns is not None and acc.end_ns is not None
        t_start = self._long_index * self.tick_ns
        t_end = t_start + self.tick_ns
        whole = (
            not acc.broken
            and abs(acc.start_ns - t_start) <= CONTIGUITY_NS  # (A5) from the tick ...
            and acc.end_ns >= t_end - CONTIGUITY_NS  # ... to the next
        )
        self._long = _Accumulator(self.methods)
        self._long_index = None
        out = [
            PqAggregate(
                source=self.source,
                interval="10-min",
                timestamp_ns=t_end,
                start_ns=t_start,
                n_windows=acc.n_windows,
                complete=whole,
                values=acc.values(),
                arrays=acc.arrays(),
            )
        ]
        two_h_ns = self.two_h_ticks * self.tick_ns
        index = t_start // two_h_ns
        if self._two_h_index is not None and index != self._two_h_index:
            out.append(self._close_two_h())  # the stream skipped the end of the last one
        self._two_h_index = index
        acc.start_ns, acc.end_ns = t_start, t_end
        self._two_h.add_interval(acc)
        self._two_h_complete += whole
        if t_end % two_h_ns == 0:
            out.append(self._close_two_h())
        return out

    def _close_two_h(self) -> PqAggregate:
        acc = self._two_h
        assert self._two_h_index is not None
        two_h_ns = self.two_h_ticks * self.tick_ns
        t_start = self._two_h_index * two_h_ns
        whole = self._two_h_complete == self.two_h_ticks
        self._two_h = _Accumulator(self.methods)
        self._two_h_index = None
        self._two_h_complete = 0
        return PqAggregate(
            source=self.source,
            interval="2-h",
            timestamp_ns=t_start + two_h_ns,
            start_ns=t_start,
            n_windows=acc.n_windows,
            complete=whole,
            values=acc.values(),
            arrays=acc.arrays(),
        )

    # ---- state -------------------------------------------------------------------------------
    def get_state(self) -> dict[str, Any]:
        """Everything :meth:`set_state` needs to go on exactly where this left off (JSON)."""
        return {
            "short": self._short.state(),
            "finishing": None if self._finishing is None else self._finishing.state(),
            "long": self._long.state(),
            "long_index": self._long_index,
            "last_end": self._last_end,
            "two_h": self._two_h.state(),
            "two_h_index": self._two_h_index,
            "two_h_complete": self._two_h_complete,
            "ten_s": [_ten_s_row(k, t) for k, t in sorted(self._ten_s.items())],
            "last_cycles": [list(c) for c in self._last_cycles],
        }

    def set_state(self, d: Mapping[str, Any]) -> None:
        """Restore :meth:`get_state`; a state of an earlier build (no 2-h, 10-s or overlap-2
        entries) restores its 150/180-cycle and 10-min intervals, the others start afresh."""
        self._short.set_state(d["short"])
        self._long.set_state(d["long"])
        self._long_index = d["long_index"]
        self._last_end = d["last_end"]
        self._finishing = None
        if d.get("finishing") is not None:
            self._finishing = _Accumulator(self.methods)
            self._finishing.set_state(d["finishing"])
        self._two_h = _Accumulator(self.methods)
        if d.get("two_h") is not None:
            self._two_h.set_state(d["two_h"])
        self._two_h_index = d.get("two_h_index")
        self._two_h_complete = int(d.get("two_h_complete", 0))
        self._ten_s = {
            int(k): _TenSecond(
                int(n),
                float(dur),
                math.inf if a is None else float(a),
                -math.inf if b is None else float(b),
                int(nw),
                br,
            )
            for k, n, dur, a, b, nw, br in d.get("ten_s", [])
        }
        self._last_cycles = [(int(k), float(cs), float(p)) for k, cs, p in d.get("last_cycles", [])]
