"""What the pipeline keeps per channel (:class:`Channel`), where another daemon left one
(:class:`ResumePoint`), a frame's channel waiting for its bank (:class:`FrameMember`) and
the pipeline's counters."""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sinewatch.core.continuity import VALIDITY_RULES_VERSION
from sinewatch.estimators.base import Estimator
from sinewatch.estimators.presence import DEFAULT_HYSTERESIS, EDGE_RATIO, SignalPresence
from sinewatch.schemas.codec import Block


@dataclass
class Channel:
    """Everything the pipeline knows about one channel."""

    name: str
    key: str
    estimator: Estimator
    sample_rate_hz: float
    last_seq: int | None = None
    next_t0_ns: int | None = None  # where the next contiguous block would start
    blocks: int = 0
    samples: int = 0
    gaps: int = 0
    errors: int = 0
    last_latency_ns: int | None = None
    converged: bool = False
    presence: SignalPresence | None = None  # set in __post_init__
    json_names: tuple[str, str] | None = field(default=None, repr=False)  # name, estimator as JSON strings
    out_key: str | None = field(default=None, repr=False)  # where its estimates go (set at the first)
    # gap, restart, reset, time jump of blocks that completed no report (grid estimators):
    # said by the next report
    held_flags: tuple[int, bool, bool, bool] | None = field(default=None, repr=False)
    # estimates held back until the presence detector has seen its onset latency past them
    # (validity rules version 3): (payload, release at sample count, window start or -1, converged), see sinewatch.core.hold
    held: deque[tuple[bytes, int, int, bool]] = field(default_factory=deque, repr=False)
    last_log_ns: int = field(default=0, repr=False)  # log time of its last accepted block
    # when its last accepted block arrived (the intake's receive time; its log time when none
    # is given) and the input key it comes on (a frame's key for a frame's channel): release_idle
    last_arrival_ns: int = field(default=0, repr=False)
    source_key: str | None = field(default=None, repr=False)
    last_run: np.ndarray | None = field(default=None, repr=False)  # the presence run of the last block
    # (key, template) of its Estimates' bytes in the usual case (sinewatch.core.estimate_bytes.estimate_payload)
    template: tuple[tuple[Any, ...], str] | None = field(default=None, repr=False)

    validity_version: int = field(default=VALIDITY_RULES_VERSION, repr=False)  # the pipeline's rules
    # valid_memory_samples, kept once known to be fixed (an estimator with the default memory)
    _valid_memory: int | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.presence is None:
            self.presence = SignalPresence(
                self.sample_rate_hz,
                cycle_frequency_hz(self.estimator),
                hold=self.validity_version >= 2,
                hysteresis=DEFAULT_HYSTERESIS if self.validity_version >= 3 else 0.0,
                fast=self.validity_version >= 4,
                edge=EDGE_RATIO if self.validity_version >= 5 else 0.0,
            )

    @property
    def valid_memory_samples(self) -> int:
        """How many samples of present signal an estimate needs behind its window's end to be
        valid: the estimator's memory, twice for a recursive one from validity rules version
        5 on (``Estimator.REFILL_MEMORIES``: its settling time counts from a state near the truth)."""
        if self._valid_memory is not None:
            return self._valid_memory
        memory = self.estimator.memory_samples
        value = memory * self.estimator.REFILL_MEMORIES if self.validity_version >= 5 else memory
        # read twice an estimate (its valid flag and its hold): kept where it cannot change, the
        # default memory being a function of the estimator's class and sample rate alone (others
        # may follow a design the signal chooses, e.g. pmu's 'auto')
        if type(self.estimator).memory_samples is Estimator.memory_samples:
            self._valid_memory = value
        return value

    @property
    def fixed_valid_memory(self) -> int | None:
        """:attr:`valid_memory_samples` where it cannot change (kept), else None."""
        _ = self.valid_memory_samples
        return self._valid_memory

    def snapshot(self) -> dict[str, Any]:
        counters = ("last_seq", "next_t0_ns", "blocks", "samples", "gaps", "errors", "converged")
        assert self.presence is not None
        return {
            **_attributes(self, "name", "key", "sample_rate_hz", *counters),
            "estimator": self.estimator.get_state(),
            "presence": self.presence.get_state(),
            **({"held": [[p.decode("ascii"), r, w, c] for p, r, w, c in self.held]} if self.held else {}),
        }


@dataclass(slots=True)
class FrameMember:
    """One accepted channel of a frame, waiting for its bank."""

    channel: Channel
    block: Block
    column: int
    gap_blocks: int
    restart: bool
    reset: bool
    jump: bool = False  # a time jump (sinewatch.core.continuity)


@dataclass(slots=True)
class UsualBank:
    """One bank of a :class:`FrameLayout`: what its usual frame hands the compiled calls, made
    once for the layout rather than once a frame (the pipeline's usual frame builds no
    per-column object)."""

    columns: list[int]
    channels: tuple[Channel, ...]
    estimators: list[Estimator]
    detectors: list[SignalPresence]
    every_column: bool  # the bank is the whole frame, in column order (its samples as they are)
    # its detectors run as one bank (read_presence_bank): two or more channels, each estimator's
    # presence signal its block itself
    presence_bank: bool
    # what its Estimates' bytes keep between frames (sinewatch.core.estimate_bytes.BankWriting),
    # once a frame has written them the usual way
    writing: Any = None


@dataclass(frozen=True, slots=True)
class FrameLayout:
    """A frame key's last frame whose every channel went into a bank: its channel names, rate,
    the channels (a column each) and the banks, in the order they ran."""

    names: tuple[str, ...]
    sample_rate_hz: float
    channels: tuple[Channel, ...]
    banks: tuple[UsualBank, ...]


def usual_bank(columns: tuple[int, ...], channels: tuple[Channel, ...], n_columns: int) -> UsualBank:
    """The :class:`UsualBank` of a frame's accepted ``channels`` in ``columns`` (of ``n_columns``)."""
    bank = [channels[c] for c in columns]
    estimators = [ch.estimator for ch in bank]
    return UsualBank(
        list(columns),
        tuple(bank),
        estimators,
        [ch.presence for ch in bank],  # type: ignore[misc]  # (every channel has its detector)
        list(columns) == list(range(n_columns)),
        # a bank's channels share one estimator class (its rule's): asked of the first
        len(bank) >= 2 and type(estimators[0]).presence_samples is Estimator.presence_samples,
    )


@dataclass(frozen=True)
class ResumePoint:
    """Where another daemon left a channel (hot standby, :mod:`sinewatch.runtime.cluster`): the
    last block whose estimate it published. Blocks up to ``published_seq`` (Zenoh's
    history brings them again) bring the estimator's state up to date without publishing
    (they were published once); the first block after it is published, flagged as a gap of
    the blocks nobody estimated."""

    published_seq: int
    next_t0_ns: int | None


@dataclass
class PipelineCounters:
    inputs: int = 0
    estimates: int = 0
    errors: int = 0
    caught_up: int = 0  # blocks taken into the state without publishing (after a takeover)
    held_dropped: int = 0  # held estimates dropped at a change of ownership (the other term's to publish)
    by_kind: Counter[str] = field(default_factory=Counter)


def _attributes(obj: object, *names: str) -> dict[str, Any]:
    """``{name: obj.name}`` for the names given, in that order (status and snapshot dicts)."""
    return {name: getattr(obj, name) for name in names}


def cycle_frequency_hz(estimator: Estimator) -> float:
    """The frequency whose one cycle is the presence detector's window: the estimator's
    nominal frequency, else the lowest it expects (``f_min_hz``, ``min_frequency_hz``), else its
    time unit (``omega_unit_rad_s`` / 2 pi), else 50 Hz. The window need not match the signal:
    over a window of a quarter of a cycle, a steady sine's AC RMS still stays above 0.21 of its
    highest value whatever the phase (above the 0.1 threshold), and over 0.83 to 1.2 cycles (60 Hz
    in a 50 Hz window, or the reverse) within 0.80 of it."""
    if estimator.presence_cycle_hz is not None:
        return estimator.presence_cycle_hz
    params = estimator.params
    for name, scale in (
        ("nominal_frequency_hz", 1.0),
        ("f_min_hz", 1.0),
        ("min_frequency_hz", 1.0),
        ("omega_unit_rad_s", 0.5 / np.pi),
    ):
        value = getattr(params, name, None)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0:
            return float(value) * scale
    return 50.0


def continues_in_time(ch: Channel, block: Block) -> bool:
    """The block's first sample is where the channel's samples ended (within half a block and
    one sample): the inline test of the usual case, :func:`check_continuity` decides the rest."""
    if ch.next_t0_ns is None:
        return True
    period_ns = 1e9 / block.sample_rate_hz
    return abs(block.t0_ns - ch.next_t0_ns) <= max(0.5 * block.n_samples * period_ns, period_ns)
