"""IEC 61000-4-30 class A time aggregation of 10/12-cycle values: 150/180-cycle (about
3 s) and 10-min aggregates, with the resynchronisation on the 10-min tick.

Reference: [4-30] IEC 61000-4-30:2015, "Testing and measurement techniques - Power quality
measurement methods", clause 4.5 (measurement aggregation over time intervals, class A)
and 5.1 (frequency), as recalled here; check the standard before quoting compliance.

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
     so does the 150/180-cycle count: the 150/180-cycle interval in progress at the tick
     is closed with the values it has ("overlap 2", ``complete = False`` when fewer than
     15) and a new one starts with the first window of the new 10-min interval.
(A5) A discontinuity (a window that does not start where the previous one ended, other
     than at a tick) closes the 150/180-cycle interval in progress (``complete = False``)
     and marks the 10-min interval incomplete; so does a 10-min interval whose windows do
     not cover it from tick to tick (the stream started or stopped inside it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from sinewatch.schemas.errors import ParameterError
from sinewatch.schemas.power_quality import PqAggregate, finite_or_none

Method = Literal["rms", "cycles"]
NS_PER_S = 1_000_000_000
CONTIGUITY_NS = 1_000  # windows closer than this are contiguous (rounding of ns times)
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
            a = np.asarray(a, dtype=np.float64)
            ok = np.isfinite(a)
            if name not in self.array_sums:
                self.array_sums[name] = np.zeros(a.shape)
                self.array_counts[name] = np.zeros(a.shape, dtype=np.int64)
            self.array_sums[name] += np.where(ok, a * a, 0.0)
            self.array_counts[name] += ok

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


class Aggregator:
    """Aggregates the 10/12-cycle values of one source; ``add`` returns the aggregates each
    window completes (none, a 150/180-cycle one, and at a tick possibly a 10-min one too).

    ``windows_per_interval`` is 15 (A2); ``tick_s`` the 10-min clock (A3), 600 s;
    ``methods`` maps quantity names to ``"rms"`` or ``"cycles"`` (default: ``frequency_hz``
    by cycles, everything else RMS).
    """

    def __init__(
        self,
        source: str,
        windows_per_interval: int = 15,
        tick_s: float = 600.0,
        methods: Mapping[str, Method] | None = None,
    ) -> None:
        if windows_per_interval < 1:
            raise ParameterError(f"windows_per_interval: expected >= 1, got {windows_per_interval}")
        if not (math.isfinite(tick_s) and tick_s > 0):
            raise ParameterError(f"tick_s: expected a finite value > 0, got {tick_s}")
        self.source = source
        self.windows_per_interval = int(windows_per_interval)
        self.tick_ns = round(tick_s * NS_PER_S)
        self.methods: dict[str, Method] = dict(DEFAULT_METHODS)
        self.methods.update(methods or {})
        self._short = _Accumulator(self.methods)
        self._long = _Accumulator(self.methods)
        self._long_index: int | None = None
        self._last_end: int | None = None

    def add(self, w: WindowValues) -> list[PqAggregate]:
        if w.end_ns <= w.start_ns:
            raise ParameterError(f"window: expected end_ns > start_ns, got {w.start_ns}..{w.end_ns}")
        out: list[PqAggregate] = []
        index = w.start_ns // self.tick_ns  # (A3) by the window's start
        if self._long_index is not None and index != self._long_index:
            out.extend(self._close_short())  # (A4) overlap 2
            out.append(self._close_long())
        elif self._last_end is not None and abs(w.start_ns - self._last_end) > CONTIGUITY_NS:
            out.extend(self._close_short())  # (A5)
            self._long.broken = True
        if self._long_index is None:
            self._long_index = index
        self._short.add(w)
        self._long.add(w)
        self._last_end = w.end_ns
        if self._short.n_windows == self.windows_per_interval:  # (A2)
            out.extend(self._close_short())
        return out

    def flush(self) -> list[PqAggregate]:
        """Close what is open (end of stream): the 150/180-cycle and 10-min intervals in
        progress, both ``complete = False`` unless they happen to be whole."""
        out = self._close_short()
        if self._long_index is not None:
            out.append(self._close_long())
        return out

    def _close_short(self) -> list[PqAggregate]:
        acc = self._short
        self._short = _Accumulator(self.methods)
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
                complete=acc.n_windows == self.windows_per_interval,
                values=acc.values(),
                arrays=acc.arrays(),
            )
        ]

    def _close_long(self) -> PqAggregate:
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
        return PqAggregate(
            source=self.source,
            interval="10-min",
            timestamp_ns=t_end,
            start_ns=t_start,
            n_windows=acc.n_windows,
            complete=whole,
            values=acc.values(),
            arrays=acc.arrays(),
        )
