"""The power-quality stage of the pipeline: per-channel IEC 61000-4-7 harmonics with their
IEC 61000-4-30 aggregates, and three-phase groups, fed with each accepted block.

The pipeline (:mod:`sinewatch.core.pipeline`) calls :meth:`PqStage.on_block` after it has
published a block's Estimate; the stage returns the messages that block completes, as
``(kind, key, payload)`` with ``kind`` the message name of
:mod:`sinewatch.schemas.power_quality`. Configuration: ``[power_quality]`` of
:class:`~sinewatch.schemas.config.SinewatchConfig`; keys under ``keys.pq_prefix``:

* ``PREFIX/harmonics/<channel>``: one HarmonicsReport per 10/12-cycle window of a channel
  whose input key matches a ``power_quality.harmonics`` rule (first match wins);
* ``PREFIX/agg/<channel>``: the PqAggregates (10-s, 150/180-cycle, 10-min, 2-h) of those windows
  (``aggregate = true``, the default): true and fundamental RMS, frequency, THD/THDG/THDS,
  harmonic and interharmonic subgroups;
* ``PREFIX/agg/<group>``: with ``aggregate_nominal_frequency_hz`` set on a group, the
  PqAggregates of the group's own 10/12-cycle windows: u2, u0, sequence magnitudes,
  frequency;
* ``PREFIX/group/<group>``: one ThreePhaseReport per estimate timestamp of a
  ``power_quality.groups`` entry.

Harmonics: one :class:`HarmonicAnalyser` per channel, created at the channel's first block
(its sample rate), fed column 0 of each block (the measurement) with the block's
``t0_ns``; reset when the pipeline resets the channel's estimator (``on_gap = "reset"``);
otherwise a block that does not start where the last ended starts a new window stream
(the analyser's own rule: the next report says ``gap``). One :class:`Aggregator` per
channel takes each window's values (:func:`channel_window_values`).

Groups: each phase contributes the fundamental (component 0) of its channel's estimate at
the estimate's ``timestamp_ns`` (the last sample of the block) as the RMS phasor
``(A / sqrt 2) exp(j phase)`` (Estimate amplitudes are peak values; the sine convention of
both makes the phases comparable at one instant). The phases' estimates are aligned on
equal ``timestamp_ns``, so the phases must share their block timing (same rate, same
block boundaries, as a three-phase ADC gives). A report goes out, oldest timestamp first,
as soon as all three phases are in, or, with the phases that are, once some phase's
newest timestamp is more than ``max_skew_s`` past it: the others are then ``missing``
(null phasor, null sequence values). An estimate for a timestamp already reported is
dropped (counted in ``late``). The report's frequency is the mean of the present phases'.

Group aggregates (IEC 61000-4-30 asks for unbalance aggregated from 10/12-cycle values, not
from block-rate estimates): with ``aggregate_nominal_frequency_hz``, the three blocks of each
complete timestamp (same ``t0_ns``, rate and length) are stacked into one three-column block
for a three-channel :class:`HarmonicAnalyser` whose windows are synchronised to phase a;
each window's symmetrical components (:func:`group_window_values`) go to the group's
:class:`Aggregator`. A timestamp with a phase missing is not fed: the analyser sees the
time jump, restarts its window stream and the aggregator closes the interval in progress
as incomplete.

Everything depends only on the inputs' data (``t0_ns``, samples, arrival order), never on
the wall clock, so a replay reproduces the bytes; :meth:`snapshot`/:meth:`restore` carry
the whole state across a recording's rotation. Aggregates still open when the stream
stops are not flushed (a shutdown is not in the recording, so a replay could not
reproduce them).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sinewatch.estimators.base import Track, decode_array, encode_array
from sinewatch.power_quality.aggregation import Aggregator
from sinewatch.power_quality.harmonics import (
    FREQUENCY_RANGE,
    HarmonicAnalyser,
    HarmonicParams,
    highest_harmonic_order,
)
from sinewatch.power_quality.reports import (
    channel_window_values,
    group_window_values,
    harmonics_report,
    three_phase_report,
)
from sinewatch.schemas.codec import Block
from sinewatch.schemas.config import HarmonicsRule, SinewatchConfig, ThreePhaseGroup
from sinewatch.schemas.errors import ParameterError
from sinewatch.schemas.power_quality import PQ_FORMAT_VERSION, encode_pq

Output = tuple[str, str, bytes]  # (message name, key, payload)
KeyMatcher = Callable[[str, str], bool]  # (key expression, key) -> the expression includes the key
STATE_FORMAT_VERSION = 1
MAX_PENDING = 4096  # timestamps a group holds at most (a bound whatever the skew and block rate)


@dataclass
class _HarmonicsChannel:
    rule: HarmonicsRule
    analyser: HarmonicAnalyser
    aggregator: Aggregator | None


@dataclass(frozen=True)
class _PhaseValue:
    """One phase's contribution to a group timestamp: its estimate's fundamental, and (for
    the group's own window analysis) its block."""

    phasor: complex  # RMS, sine convention, at the timestamp
    frequency_hz: float
    t0_ns: int = 0
    sample_rate_hz: float = 0.0
    samples: np.ndarray | None = None  # column 0 of the block, float64


Slot = list[_PhaseValue | None]


@dataclass
class _Group:
    config: ThreePhaseGroup
    skew_ns: int
    pending: dict[int, Slot] = field(default_factory=dict)
    newest_ns: int | None = None
    last_emitted_ns: int | None = None
    late: int = 0
    analyser: HarmonicAnalyser | None = None  # 3 columns, when the group is aggregated
    aggregates_off: bool = False  # its rate carries no window analysis (said once)
    aggregator: Aggregator | None = None

    def add(self, phase: int, timestamp_ns: int, value: _PhaseValue) -> list[tuple[int, Slot]]:
        """Take one phase's value; return the timestamps now ready with their values, oldest
        first (complete ones, and incomplete ones that waited more than the skew bound)."""
        if self.last_emitted_ns is not None and timestamp_ns <= self.last_emitted_ns:
            self.late += 1
            return []
        slot = self.pending.setdefault(timestamp_ns, [None, None, None])
        slot[phase] = value
        newest = timestamp_ns if self.newest_ns is None else max(self.newest_ns, timestamp_ns)
        self.newest_ns = newest
        ready = []
        while self.pending:
            oldest = min(self.pending)
            complete = all(v is not None for v in self.pending[oldest])
            if not complete and newest - oldest <= self.skew_ns and len(self.pending) <= MAX_PENDING:
                break
            ready.append((oldest, self.pending.pop(oldest)))
            self.last_emitted_ns = oldest
        return ready


class PqStage:
    """Harmonics, aggregates and three-phase groups for one pipeline (see the module doc)."""

    def __init__(self, config: SinewatchConfig, key_matcher: KeyMatcher, version: int = PQ_FORMAT_VERSION) -> None:
        self.section = config.power_quality
        self.version = version  # 1 to reproduce recordings of earlier builds
        self.prefix = config.keys.pq_prefix.rstrip("/")
        self._matches = key_matcher
        self.harmonics: dict[str, _HarmonicsChannel | None] = {}  # by channel; None: no rule matched
        self.groups = {g.name: _Group(g, round(g.max_skew_s * 1e9)) for g in self.section.groups}
        self._phase_of = {ch: (g.name, i) for g in self.section.groups for i, ch in enumerate(g.phases)}
        if self.section.harmonics or any(g.aggregate_nominal_frequency_hz for g in self.section.groups):
            warm_up()

    @property
    def enabled(self) -> bool:
        return bool(self.section.harmonics or self.section.groups)

    # ---- the hook ----------------------------------------------------------------------------
    def on_block(
        self, key: str, channel: str, block: Block, track: Track, reset: bool
    ) -> tuple[list[Output], str | None]:
        """The messages one accepted block completes (its Estimate is ``track``'s last row),
        and a problem to report, if any: harmonics asked for on a channel whose sample rate
        cannot carry them (said once; that channel then goes without harmonics)."""
        out: list[Output] = []
        if channel in self._phase_of:
            try:
                out.extend(self._group_values(channel, block, track))
            except ParameterError as exc:
                name = self._phase_of[channel][0]
                self.groups[name].aggregates_off = True
                return out, f"aggregates off for group {name!r}: {exc}"
        try:
            hc = self._harmonics_for(key, channel, block.sample_rate_hz)
        except ParameterError as exc:
            self.harmonics[channel] = None
            return out, f"harmonics off for channel {channel!r}: {exc}"
        if hc is not None:
            out.extend(self._harmonic_windows(channel, hc, block, reset))
        return out, None

    # ---- harmonics ---------------------------------------------------------------------------
    def _harmonics_for(self, key: str, channel: str, sample_rate_hz: float) -> _HarmonicsChannel | None:
        if channel not in self.harmonics:
            rule = next((r for r in self.section.harmonics if self._matches(r.match, key)), None)
            self.harmonics[channel] = None if rule is None else self._new_harmonics(rule, channel, sample_rate_hz)
        return self.harmonics[channel]

    @staticmethod
    def _new_harmonics(rule: HarmonicsRule, channel: str, sample_rate_hz: float) -> _HarmonicsChannel:
        params = HarmonicParams(nominal_frequency_hz=float(rule.nominal_frequency_hz), max_harmonic=rule.max_harmonic)
        return _HarmonicsChannel(
            rule, HarmonicAnalyser(sample_rate_hz, params), Aggregator(channel) if rule.aggregate else None
        )

    def _harmonic_windows(self, channel: str, hc: _HarmonicsChannel, block: Block, reset: bool) -> list[Output]:
        if reset:
            hc.analyser.reset()
        x = block.samples if block.samples.ndim == 1 else block.samples[:, 0]
        out: list[Output] = []
        nominal = float(hc.rule.nominal_frequency_hz)
        for window in hc.analyser.update(x, block.t0_ns):
            report = harmonics_report(window, channel, 0, nominal)
            out.append(("HarmonicsReport", f"{self.prefix}/harmonics/{channel}", encode_pq(report, self.version)))
            if hc.aggregator is not None:
                for agg in hc.aggregator.add(channel_window_values(window)):
                    out.append(("PqAggregate", f"{self.prefix}/agg/{channel}", encode_pq(agg, self.version)))
        return out

    # ---- groups ------------------------------------------------------------------------------
    def _group_values(self, channel: str, block: Block, track: Track) -> list[Output]:
        name, phase = self._phase_of[channel]
        group = self.groups[name]
        timestamp_ns = block.t0_ns + round((block.n_samples - 1) * 1e9 / block.sample_rate_hz)  # the Estimate's
        amplitude = float(track.amplitude[-1, 0])
        phasor = complex(amplitude / math.sqrt(2.0) * np.exp(1j * float(track.phase_rad[-1, 0])))
        frequency = float(track.frequency_hz[-1, 0])
        if group.config.aggregate_nominal_frequency_hz is None:
            value = _PhaseValue(phasor, frequency)
        else:
            x = block.samples if block.samples.ndim == 1 else block.samples[:, 0]
            value = _PhaseValue(phasor, frequency, block.t0_ns, block.sample_rate_hz, np.array(x, dtype=np.float64))
        out: list[Output] = []
        for ts, slot in group.add(phase, timestamp_ns, value):
            out.append(self._group_report(group, ts, slot))
            out.extend(self._group_windows(group, slot))
        return out

    def _group_windows(self, group: _Group, slot: Slot) -> list[Output]:
        """Feed a complete slot's three blocks, as one (n, 3) block, to the group's window
        analysis; its aggregates (u2, u0, sequence magnitudes, frequency) come out. A slot
        with a phase missing is not fed: the analyser sees the time jump and restarts."""
        nominal = group.config.aggregate_nominal_frequency_hz
        values = [v for v in slot if v is not None and v.samples is not None]
        if nominal is None or group.aggregates_off or len(values) != 3:
            return []
        first = values[0]
        assert first.samples is not None
        if any(
            v.t0_ns != first.t0_ns or v.sample_rate_hz != first.sample_rate_hz or v.samples.shape != first.samples.shape
            for v in values
            if v.samples is not None
        ):
            return []  # same end, different blocks: not one grid
        if group.analyser is None:
            group.analyser = HarmonicAnalyser(first.sample_rate_hz, _group_params(nominal, first.sample_rate_hz))
            group.aggregator = Aggregator(group.config.name)
        x = np.column_stack([v.samples for v in values if v.samples is not None])
        out: list[Output] = []
        key = f"{self.prefix}/agg/{group.config.name}"
        assert group.aggregator is not None
        for window in group.analyser.update(x, first.t0_ns):
            for agg in group.aggregator.add(group_window_values(window)):
                out.append(("PqAggregate", key, encode_pq(agg, self.version)))
        return out

    def _group_report(self, group: _Group, timestamp_ns: int, slot: Slot) -> Output:
        phases = group.config.phases
        phasors = [complex(math.nan, math.nan) if v is None else v.phasor for v in slot]
        freqs = [v.frequency_hz for v in slot if v is not None and math.isfinite(v.frequency_hz)]
        frequency = math.fsum(freqs) / len(freqs) if freqs else math.nan
        missing = [ch for ch, v in zip(phases, slot, strict=True) if v is None]
        report = three_phase_report(group.config.name, phases, timestamp_ns, phasors, frequency, missing)
        return "ThreePhaseReport", f"{self.prefix}/group/{group.config.name}", encode_pq(report, self.version)

    # ---- state -------------------------------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        return {
            "format_version": STATE_FORMAT_VERSION,
            "harmonics": {
                ch: None
                if hc is None
                else {
                    "rule": hc.rule.model_dump(mode="json"),
                    "analyser": hc.analyser.get_state(),
                    "aggregator": None if hc.aggregator is None else _aggregator_state(hc.aggregator),
                }
                for ch, hc in self.harmonics.items()
            },
            "groups": {
                name: {
                    "pending": [[ts, [_value_state(v) for v in slot]] for ts, slot in g.pending.items()],
                    "newest_ns": g.newest_ns,
                    "last_emitted_ns": g.last_emitted_ns,
                    "late": g.late,
                    "analyser": None if g.analyser is None else g.analyser.get_state(),
                    "aggregator": None if g.aggregator is None else _aggregator_state(g.aggregator),
                }
                for name, g in self.groups.items()
            },
        }

    def restore(self, snapshot: dict[str, Any]) -> None:
        for ch, item in snapshot.get("harmonics", {}).items():
            if item is None:
                self.harmonics[ch] = None
                continue
            rule = HarmonicsRule.model_validate(item["rule"])
            state = item["analyser"]
            hc = self._new_harmonics(rule, ch, float(state["sample_rate_hz"]))
            hc.analyser.set_state(state)
            if hc.aggregator is not None and item["aggregator"] is not None:
                _set_aggregator_state(hc.aggregator, item["aggregator"])
            self.harmonics[ch] = hc
        for name, item in snapshot.get("groups", {}).items():
            g = self.groups.get(name)
            if g is None:
                continue
            g.pending = {int(ts): [_value_from_state(v) for v in slot] for ts, slot in item["pending"]}
            g.newest_ns = item["newest_ns"]
            g.last_emitted_ns = item["last_emitted_ns"]
            g.late = item["late"]
            nominal = g.config.aggregate_nominal_frequency_hz
            if item.get("analyser") is not None and nominal is not None:
                fs = float(item["analyser"]["sample_rate_hz"])
                g.analyser = HarmonicAnalyser(fs, _group_params(nominal, fs))
                g.analyser.set_state(item["analyser"])
                g.aggregator = Aggregator(name)
                _set_aggregator_state(g.aggregator, item["aggregator"])


def _group_params(nominal: int, sample_rate_hz: float) -> HarmonicParams:
    """The group's window analysis: its aggregates (u2, u0, sequence magnitudes, frequency)
    use only the fundamental, so a rate too slow for harmonics to the 50th analyses up to the
    highest order it carries (the same windows and values at any rate that carries the 50th)."""
    order = min(50, highest_harmonic_order(sample_rate_hz, float(nominal)))
    if order < 2:  # the analyser's least
        least = 3 * FREQUENCY_RANGE[1] * nominal / 0.4
        raise ParameterError(
            f"sample_rate_hz: expected >= {least:g} Hz for a {nominal} Hz window analysis, got {sample_rate_hz:g}"
        )
    return HarmonicParams(nominal_frequency_hz=float(nominal), n_channels=3, reference_channel=0, max_harmonic=order)


def _value_state(v: _PhaseValue | None) -> dict[str, Any] | None:
    if v is None:
        return None
    return {
        "phasor": [v.phasor.real, v.phasor.imag],
        "frequency_hz": v.frequency_hz,
        "t0_ns": v.t0_ns,
        "sample_rate_hz": v.sample_rate_hz,
        "samples": None if v.samples is None else encode_array(v.samples),
    }


def _value_from_state(d: dict[str, Any] | None) -> _PhaseValue | None:
    if d is None:
        return None
    return _PhaseValue(
        complex(d["phasor"][0], d["phasor"][1]),
        float(d["frequency_hz"]),
        int(d["t0_ns"]),
        float(d["sample_rate_hz"]),
        None if d["samples"] is None else decode_array(d["samples"]),
    )


_warm = False


def warm_up() -> None:
    """Load (or compile) the harmonic analyser's kernels now, once per process, so that a
    channel's first block does not wait for numba (about 0.3 s from its cache here)."""
    global _warm
    if not _warm:
        analyser = HarmonicAnalyser(10_000.0, HarmonicParams())
        analyser.update(np.sin(2 * np.pi * 50.0 * np.arange(2500) / 10_000.0), 0)
        _warm = True


def _aggregator_state(agg: Aggregator) -> dict[str, Any]:
    return agg.get_state()


def _set_aggregator_state(agg: Aggregator, d: dict[str, Any]) -> None:
    agg.set_state(d)


__all__ = ["Output", "PqStage", "warm_up"]
