"""The data path: source -> channel -> estimator -> sinks.

A source (the Zenoh intake in the daemon, or an MCAP file in replay) calls
:meth:`Pipeline.process` with each raw input in arrival order. The pipeline records the
raw input, decodes and checks it against its channel, runs the channel's estimator and
hands one Estimate per accepted block to the sinks (Zenoh publisher, MCAP recorder,
replay comparator). A rejected input produces one ErrorReport instead; an estimator never
sees a bad sample and its state is untouched by a rejected block. When configured
(``[power_quality]``), the power-quality stage (:mod:`sinewatch.power_quality.stage`)
then takes the accepted block and its estimate, and its messages (harmonics, aggregates,
three-phase groups) go to the sinks' ``on_output``.

Everything here is deterministic given the inputs, their order and the config: that is
what makes replay bit-exact. Wall-clock values (latency) stay out of the messages that
replay compares.

Gap policy (``on_gap``): on a sequence gap the block is accepted and the next Estimate
carries ``gap = true`` and ``gap_blocks``; with ``coast`` (default) the estimator keeps
its state and simply continues (its phase is then off by the missing samples until it
re-converges); with ``reset`` it is reset first and the Estimate says ``reset = true``.
A sample-rate change on a channel is rejected (``sample_rate_change``): an estimator's
discretisation depends on the rate, so a new rate needs a new channel name.
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from math import isfinite
from typing import Any, Protocol

import numpy as np
import zenoh

from sinewatch.core.continuity import VALIDITY_RULES_VERSION, check_continuity
from sinewatch.estimators import get as get_estimator
from sinewatch.estimators.bank import update_bank
from sinewatch.estimators.base import Estimator, Track, TrackStd
from sinewatch.estimators.presence import DEFAULT_HYSTERESIS, SignalPresence, update_presence_bank
from sinewatch.power_quality.stage import PqStage
from sinewatch.schemas.codec import (
    TIME_QUALITY_JSON,
    Block,
    dumps,
    encode_error,
    encode_estimate_values,
    finite_or_none,
    is_json_block,
    json_string,
    time_quality_model,
)
from sinewatch.schemas.config import EstimatorRule, SinewatchConfig
from sinewatch.schemas.errors import InputError, ParameterError, SinewatchError
from sinewatch.schemas.frame import Frame, channel_key, decode_input
from sinewatch.schemas.messages import (
    ESTIMATE_FORMAT_VERSION,
    Diagnostics,
    ErrorKind,
    ErrorReport,
    Estimate,
    Fencing,
    Uncertainty,
)
from sinewatch.schemas.power_quality import PQ_FORMAT_VERSION

log = logging.getLogger("sinewatch.core.pipeline")


class Sink(Protocol):
    """Where the pipeline's outputs go. ``log_time_ns`` is the input's receive time."""

    def on_input(self, key: str, payload: bytes, encoding: str, log_time_ns: int) -> None: ...
    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None: ...
    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None: ...
    def on_status(self, key: str, payload: bytes, log_time_ns: int) -> None: ...
    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        """Any other output message; ``kind`` is its message name (e.g. ``HarmonicsReport``)."""

    def close(self) -> None: ...


class NullSink:
    """A sink that ignores everything; subclass and override what you need."""

    def on_input(self, key: str, payload: bytes, encoding: str, log_time_ns: int) -> None:
        pass

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        pass

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        pass

    def on_status(self, key: str, payload: bytes, log_time_ns: int) -> None:
        pass

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        pass

    def close(self) -> None:
        pass


class GuardedSink:
    """A sink whose failures are caught, counted and reported, never raised into the
    pipeline: a full disk or a closed Zenoh session must not stop estimation. The sink's
    ``on_input``, ``on_estimate`` and ``on_output`` are looked up once, when it is wrapped.

    After a failure the sink is skipped (each output it misses is counted) for
    ``retry_s``; the next *input* after that reopens it (its ``recover()``, if it has
    one) and tries again. Recovery waits for an input so that a recorder restarts on a
    block boundary, where its state snapshot is exact.
    """

    def __init__(
        self,
        sink: Sink,
        name: str,
        on_failure: Callable[[str, str], None],
        *,
        retry_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.sink = sink
        self.name = name
        self._on_failure = on_failure
        self._retry_s = retry_s
        self._clock = clock
        self.ok = True
        self.failures = 0
        self.skipped = 0
        self.recoveries = 0
        self.last_error: str | None = None
        self._retry_at = 0.0
        # the sink's per-message methods, looked up once (None: NullSink's, which does nothing)
        self._on_input: Callable[[str, bytes, str, int], None] | None = _own_method(sink, "on_input")
        self._on_estimate: Callable[[str, bytes, int], None] | None = _own_method(sink, "on_estimate")
        self._on_output: Callable[[str, str, bytes, int], None] | None = _own_method(sink, "on_output")

    def _call(self, method: str, *args: Any) -> None:
        if not self.ok and (method != "on_input" or self._clock() < self._retry_at or not self._recover()):
            self.skipped += 1
            return
        try:
            getattr(self.sink, method)(*args)
        except Exception as exc:  # noqa: BLE001 (a sink's fault is the sink's: isolate it, report it)
            self._fail(f"{method}", exc)

    def _recover(self) -> bool:
        recover = getattr(self.sink, "recover", None)
        try:
            if recover is not None:
                recover()
        except Exception as exc:  # noqa: BLE001 (still failing: stay failed, retry later)
            self._fail("recover", exc)
            return False
        self.ok = True
        self.recoveries += 1
        log.warning("sink %s: resumed after %d skipped output(s)", self.name, self.skipped)
        return True

    def _fail(self, where: str, exc: Exception) -> None:
        self.failures += 1
        self.last_error = f"{type(exc).__name__}: {exc}"
        first = self.ok
        self.ok = False
        self._retry_at = self._clock() + self._retry_s
        if first:  # one report per outage, not one per skipped output
            log.error(
                "sink %s failed in %s (%s); estimation goes on, retrying every %g s",
                self.name,
                where,
                self.last_error,
                self._retry_s,
            )
            self._on_failure(self.name, f"{self.name} failed in {where}: {self.last_error}")

    # The per-message methods: the same as _call(name, ...), without its getattr and
    # argument tuple (one call per block each, the pipeline's hot path); a method the sink
    # leaves as NullSink's (it does nothing) is not called at all while the sink is ok.
    def on_input(self, key: str, payload: bytes, encoding: str, log_time_ns: int) -> None:
        if not self.ok and (self._clock() < self._retry_at or not self._recover()):
            self.skipped += 1
            return
        if self._on_input is not None:
            try:
                self._on_input(key, payload, encoding, log_time_ns)
            except Exception as exc:  # noqa: BLE001 (a sink's fault is the sink's: isolate it, report it)
                self._fail("on_input", exc)

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        if not self.ok:
            self.skipped += 1
        elif self._on_estimate is not None:
            try:
                self._on_estimate(key, payload, log_time_ns)
            except Exception as exc:  # noqa: BLE001 (isolated, as in _call)
                self._fail("on_estimate", exc)

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._call("on_error", key, payload, log_time_ns)

    def on_status(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._call("on_status", key, payload, log_time_ns)

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        if not self.ok:
            self.skipped += 1
        elif self._on_output is not None:
            try:
                self._on_output(kind, key, payload, log_time_ns)
            except Exception as exc:  # noqa: BLE001 (isolated, as in _call)
                self._fail("on_output", exc)

    def open(self) -> None:
        if hasattr(self.sink, "open"):
            self._call("open")

    def flush(self) -> None:
        if self.ok and hasattr(self.sink, "flush"):
            self._call("flush")

    def close(self) -> None:
        try:
            self.sink.close()
        except Exception as exc:  # noqa: BLE001 (closing at shutdown: report, close the others)
            self.failures += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            log.error("sink %s failed to close: %s", self.name, self.last_error)

    def status(self) -> dict[str, Any]:
        return _attributes(self, "name", "ok", "failures", "skipped", "recoveries", "last_error")


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
    # (validity rules version 3): (payload, release at sample count, window start or -1, converged), see _hold
    held: deque[tuple[bytes, int, int, bool]] = field(default_factory=deque, repr=False)
    last_run: np.ndarray | None = field(default=None, repr=False)  # the presence run of the last block
    last_log_ns: int = field(default=0, repr=False)  # log time of its last accepted block (release_idle)
    # (key, template) of its Estimates' bytes in the usual case (Pipeline._fast_payload)
    template: tuple[tuple[Any, ...], str] | None = field(default=None, repr=False)

    validity_version: int = field(default=VALIDITY_RULES_VERSION, repr=False)  # the pipeline's rules

    def __post_init__(self) -> None:
        if self.presence is None:
            self.presence = SignalPresence(
                self.sample_rate_hz,
                _cycle_frequency_hz(self.estimator),
                hold=self.validity_version >= 2,
                hysteresis=DEFAULT_HYSTERESIS if self.validity_version >= 3 else 0.0,
                fast=self.validity_version >= 4,
            )

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
class _Member:
    """One accepted channel of a frame, waiting for its bank."""

    channel: Channel
    block: Block
    column: int
    gap_blocks: int
    restart: bool
    reset: bool
    jump: bool = False  # a time jump (sinewatch.core.continuity)


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
    by_kind: Counter[str] = field(default_factory=Counter)


class Pipeline:
    def __init__(
        self,
        config: SinewatchConfig,
        sinks: list[Sink],
        *,
        rules: list[EstimatorRule] | None = None,
        estimate_version: int = ESTIMATE_FORMAT_VERSION,
        pq_version: int = PQ_FORMAT_VERSION,
        validity_version: int = VALIDITY_RULES_VERSION,
    ) -> None:
        self.config = config
        self.estimate_version = estimate_version  # < current to reproduce recordings of earlier builds
        self.validity_version = validity_version  # likewise (sinewatch.core.continuity)
        # hold estimates back (_hold): version 3 only where its config asked (its default was off)
        holds = config.hold_estimates and (validity_version >= 4 or "hold_estimates" in config.model_fields_set)
        self._holds = holds and validity_version >= 3 and estimate_version >= 3
        self.sinks = [
            GuardedSink(
                sink,
                getattr(sink, "sink_name", type(sink).__name__),
                self._report_sink_failure,
                retry_s=config.sink_retry_s,
            )
            for sink in sinks
        ]
        self.rules = list(rules if rules is not None else config.rules)
        self._rule_exprs = [zenoh.KeyExpr(r.match) for r in self.rules]
        self.channels: dict[str, Channel] = {}
        self.counters = PipelineCounters()
        self._error_counts: Counter[tuple[str, str]] = Counter()  # (key, kind) -> count, for ErrorReport.count
        self._rule_cache: dict[str, EstimatorRule | None] = {}
        self._frame_keys: dict[tuple[str, tuple[str, ...]], tuple[str, ...]] = {}  # (frame key, names) -> channel keys
        self.resume_points: dict[str, ResumePoint] = {}  # by channel: after a takeover (cluster)
        self.fencing: Fencing | None = None  # the shard and term this daemon owns its channels under (cluster)
        self._fencing_json = "null"
        self.pq = PqStage(
            config, _key_matches, pq_version
        )  # power quality (harmonics, groups, aggregates): off unless configured

    def set_fencing(self, fencing: Fencing | None) -> None:
        """The shard and election term every estimate from now on carries (format 4): set
        by the cluster when this daemon wins its shard's election, and by a snapshot."""
        self.fencing = fencing
        self._fencing_json = "null" if fencing is None else dumps(fencing.model_dump()).decode()

    # ---- the one entry point ---------------------------------------------------------------
    def process(
        self, key: str, payload: bytes, encoding: str, log_time_ns: int, received_ns: int | None = None
    ) -> None:
        """Take one raw input through the pipeline. Never raises for bad input."""
        self.counters.inputs += 1
        for sink in self.sinks:
            sink.on_input(key, payload, encoding, log_time_ns)
        channel: Channel | None = None
        block: Block | None = None
        stage = "decode"
        try:
            decoded = self._decode(payload, encoding)
            if isinstance(decoded, Frame):
                self._process_frame(key, decoded, log_time_ns, received_ns)
                return
            block = decoded
            stage = "channel"
            channel = self._channel_for(key, block)
            if channel.name in self.resume_points and self._catch_up(channel, block):
                return
            gap_blocks, restart, jump, reset = self._continuity(channel, block)
            stage = "estimator"
            track = self._update(channel, block, reset)
            self._presence(channel, block, reset)
            stage = "estimate"
            self._accept(channel, block, gap_blocks, restart, reset, jump)
            payloads = self._estimate_payloads(channel, block, track, gap_blocks, restart, reset, jump)
        except InputError as exc:
            self._forget_unborn(channel)
            self._reject(key, block, channel, exc.kind, str(exc), log_time_ns)
            return
        except SinewatchError as exc:  # e.g. parameters that do not fit this channel's rate
            self._forget_unborn(channel)
            self._reject(key, block, channel, "estimator_error", str(exc), log_time_ns)
            return
        except Exception as exc:  # noqa: BLE001 (a bug in one channel's path must not stop the others)
            self._forget_unborn(channel)
            self._fault(key, block, channel, stage, exc, log_time_ns)
            return
        self._hand_out(key, channel, block, track, payloads, reset, log_time_ns, received_ns)

    # ---- multi-channel frames ----------------------------------------------------------------
    def _process_frame(self, key: str, frame: Frame, log_time_ns: int, received_ns: int | None) -> None:
        """One decoded frame (already recorded whole by the sinks' ``on_input``): each column
        is checked as its channel's block would be, the accepted channels that share a rule
        advance together through :func:`update_bank`, and each gets its own Estimate.

        Everything that can go wrong goes wrong per channel: a NaN column, a duplicate, a
        channel over the limit or with no rule is that channel's ErrorReport (on its own key),
        and the others are estimated. The channel set may change from one frame to the next:
        each channel is followed as if its column had been sent alone with the frame's seq,
        so a channel that comes back after k frames without it is flagged as a gap of k
        blocks, and a new one starts afresh."""
        keys = self._frame_channel_keys(key, frame.channels)
        x = frame.samples
        if x.dtype != _F64:
            x = x.astype(np.float64)  # once per frame: each column then is what its block would give
            frame.samples = x
        finite = np.isfinite(x).all(axis=0).tolist() if not _all_finite_2d(x) else None
        banks: dict[tuple[int, str, float], list[_Member]] = {}
        for c, ckey in enumerate(keys):
            block = frame.block(c)
            channel: Channel | None = None
            try:
                channel = self._channel_for(ckey, block)
                if channel.name in self.resume_points and self._catch_up_checked(channel, block, finite, c):
                    continue
                member = self._frame_member(channel, block, c, finite)
            except InputError as exc:
                self._forget_unborn(channel)
                self._reject(ckey, block, channel, exc.kind, str(exc), log_time_ns)
                continue
            except SinewatchError as exc:
                self._forget_unborn(channel)
                self._reject(ckey, block, channel, "estimator_error", str(exc), log_time_ns)
                continue
            except Exception as exc:  # noqa: BLE001 (one channel's fault, not the frame's)
                self._forget_unborn(channel)
                self._fault(ckey, block, channel, "channel", exc, log_time_ns)
                continue
            est = channel.estimator
            banks.setdefault((id(self._rule_for(ckey)), est.name, est.sample_rate_hz), []).append(member)
        n_all = len(keys)
        for members in banks.values():
            tracks = self._run_bank(members, x, n_all, frame.t0_ns, log_time_ns)
            presence_done = self._presence_bank(members, tracks, x)
            for member, track in zip(members, tracks, strict=True):
                if track is not None:
                    self._frame_estimate(member, track, log_time_ns, received_ns, presence_done)

    def _frame_channel_keys(self, key: str, names: tuple[str, ...]) -> tuple[str, ...]:
        """Each channel's key (:func:`sinewatch.schemas.frame.channel_key`), once per layout."""
        cached = self._frame_keys.get((key, names))
        if cached is None:
            if len(self._frame_keys) > 4 * self.config.limits.max_channels:
                self._frame_keys.clear()  # bounded: hostile senders may invent layouts
            cached = self._frame_keys[(key, names)] = tuple(channel_key(key, name) for name in names)
        return cached

    @staticmethod
    def _update(channel: Channel, block: Block, reset: bool) -> Track:
        """The channel's estimator on the block, reset first when ``reset``. A block the
        estimator rejects (a NaN, the wrong shape) leaves the state as it was, reset or not:
        a rejected block must not start a channel over."""
        est = channel.estimator
        if not reset:
            return est.update(block.samples, last_only=True, t0_ns=block.t0_ns)
        before = est.get_state()
        est.reset()
        try:
            return est.update(block.samples, last_only=True, t0_ns=block.t0_ns)
        except Exception:
            est.set_state(before)
            raise

    def _continuity(self, channel: Channel, block: Block) -> tuple[int, bool, bool, bool]:
        """(gap blocks, restart, time jump, reset) of a block on its channel
        (:func:`sinewatch.core.continuity.check_continuity`; raises InputError for a duplicate or a
        block from the past). A restart or a time jump starts the channel over
        (validity rules version 2); a gap follows ``on_gap``."""
        last_seq = channel.last_seq
        if (
            last_seq is not None
            and block.seq == last_seq + 1
            and (self.validity_version < 2 or _continues_in_time(channel, block))
        ):  # the usual case, before the full check
            return 0, False, False, False
        cont = check_continuity(
            last_seq,
            channel.next_t0_ns,
            block.seq,
            block.t0_ns,
            block.n_samples,
            block.sample_rate_hz,
            rules_version=self.validity_version,
        )
        gap_blocks, restart, jump = cont.gap_blocks, cont.restart, cont.time_jump_ns != 0
        reset = cont.starts_over(self.validity_version) or (
            (gap_blocks > 0 or restart) and self.config.on_gap == "reset"
        )
        return gap_blocks, restart, jump, reset

    def _frame_member(self, channel: Channel, block: Block, c: int, finite: list[bool] | None) -> _Member:
        """Check column ``c`` as its channel's block (sequence, values, shape); raise InputError."""
        gap_blocks, restart, jump, reset = self._continuity(channel, block)
        if finite is not None and not finite[c]:
            bad = int(np.count_nonzero(~np.isfinite(block.samples)))
            raise InputError(f"samples: expected finite values, got {bad} NaN/Inf", kind="non_finite")
        if channel.estimator.n_inputs != 1:
            raise InputError(
                f"samples: expected {channel.estimator.n_inputs} columns for {channel.estimator.name}, "
                "got 1 (a frame's channel is one column)",
                kind="shape_mismatch",
            )
        return _Member(channel, block, c, gap_blocks, restart, reset, jump)

    def _catch_up_checked(self, channel: Channel, block: Block, finite: list[bool] | None, c: int) -> bool:
        if finite is not None and not finite[c]:
            raise InputError("samples: expected finite values, got NaN/Inf", kind="non_finite")
        return self._catch_up(channel, block)

    def _run_bank(
        self, members: list[_Member], x: np.ndarray, n_all: int, t0_ns: int, log_time_ns: int
    ) -> list[Track | None]:
        """Advance one rule's channels together; a bank that raises is rolled back (kernels
        return new states, so the old ones are intact) and run channel by channel, so that
        only the faulty channel's block is lost (``estimator_fault``)."""
        ests = [m.channel.estimator for m in members]
        for m in members:
            if m.reset:
                m.channel.estimator.reset()
        cols = [m.column for m in members]
        samples = x if len(cols) == n_all and cols == list(range(n_all)) else x[:, cols]
        saved = [est._state for est in ests]
        try:
            return list(update_bank(ests, samples, last_only=True, t0_ns=t0_ns))
        except Exception:  # noqa: BLE001 (isolated below, channel by channel)
            for est, state in zip(ests, saved, strict=True):
                est._state = state
        tracks: list[Track | None] = []
        for m in members:
            try:
                tracks.append(m.channel.estimator.update(m.block.samples, last_only=True, t0_ns=t0_ns))
            except InputError as exc:
                self._forget_unborn(m.channel)
                self._reject(m.channel.key, m.block, m.channel, exc.kind, str(exc), log_time_ns)
                tracks.append(None)
            except Exception as exc:  # noqa: BLE001 (one channel's fault)
                self._forget_unborn(m.channel)
                self._fault(m.channel.key, m.block, m.channel, "estimator", exc, log_time_ns)
                tracks.append(None)
        return tracks

    @staticmethod
    def _presence_bank(members: list[_Member], tracks: list[Track | None], x: np.ndarray) -> bool:
        """The presence detectors of a bank's accepted channels in one compiled call
        (:func:`update_presence_bank`: each detector's run and state exactly what
        :meth:`_presence` gives it); False when it does not apply (then each channel's own
        runs in :meth:`_frame_estimate`, which also isolates a fault to its channel)."""
        live = [m for m, track in zip(members, tracks, strict=True) if track is not None]
        if len(live) < 2 or any(
            type(m.channel.estimator).presence_samples is not Estimator.presence_samples for m in live
        ):
            return False
        detectors = [m.channel.presence for m in live]
        for m, det in zip(live, detectors, strict=True):
            assert det is not None
            if m.reset:
                det.reset()
        try:
            runs = update_presence_bank(detectors, x, [m.column for m in live])  # type: ignore[arg-type]
        except Exception:  # noqa: BLE001 (the state is untouched: each channel runs its own, isolated)
            return False
        if runs is None:
            return False
        for m, run in zip(live, runs, strict=True):
            m.channel.last_run = run
        return True

    def _frame_estimate(
        self, m: _Member, track: Track, log_time_ns: int, received_ns: int | None, presence_done: bool = False
    ) -> None:
        """What :meth:`process` does after the estimator, for one channel of a frame (its
        presence detector already run by :meth:`_presence_bank` when ``presence_done``)."""
        channel, block = m.channel, m.block
        try:
            if not presence_done:
                self._presence(channel, block, m.reset)
            self._accept(channel, block, m.gap_blocks, m.restart, m.reset, m.jump)
            payloads = self._estimate_payloads(channel, block, track, m.gap_blocks, m.restart, m.reset, m.jump)
        except Exception as exc:  # noqa: BLE001 (one channel's fault)
            self._forget_unborn(channel)
            self._fault(channel.key, block, channel, "estimate", exc, log_time_ns)
            return
        self._hand_out(channel.key, channel, block, track, payloads, m.reset, log_time_ns, received_ns)

    def _power_quality(
        self, key: str, channel: Channel, block: Block, track: Track, reset: bool, log_time_ns: int
    ) -> None:
        """The power-quality stage (:mod:`sinewatch.pq_stage`) on an accepted block; its
        outputs go to the sinks' ``on_output``. A fault there is reported like any other and
        leaves the estimate (already out) and the stage's state untouched."""
        try:
            outputs, problem = self.pq.on_block(key, channel.name, block, track, reset)
        except Exception as exc:  # noqa: BLE001 (the stage's fault must not stop the channel)
            self._fault(key, block, channel, "power_quality", exc, log_time_ns)
            return
        for kind, out_key, payload in outputs:
            for sink in self.sinks:
                sink.on_output(kind, out_key, payload, log_time_ns)
        if problem is not None:
            self._reject(key, block, channel, "estimator_error", problem, log_time_ns)

    def _fault(
        self, key: str, block: Block | None, channel: Channel | None, stage: str, exc: Exception, log_time_ns: int
    ) -> None:
        """An unexpected exception while processing one input. The estimator's state is
        untouched (kernels return a new state, assigned only on success), so the channel
        goes on with its next block; the input is reported like a rejected one."""
        kind = "estimator_fault" if stage == "estimator" else "internal_error"
        if self._error_counts[(key, kind)] < 5:  # the traceback, for the first few only
            log.error("unexpected %s in %s stage on %s", type(exc).__name__, stage, key, exc_info=exc)
        message = f"{stage}: unexpected {type(exc).__name__}: {str(exc)[:300]}"
        self._reject(key, block, channel, kind, message, log_time_ns)

    def _report_sink_failure(self, sink_name: str, message: str) -> None:
        """A sink failed: tell the other sinks (the failed one is skipping by now)."""
        self._reject(f"sink/{sink_name}", None, None, "sink_error", message, time.time_ns())

    # ---- steps -----------------------------------------------------------------------------
    def _decode(self, payload: bytes, encoding: str) -> Block | Frame:
        limits = self.config.limits
        if len(payload) > limits.max_payload_bytes:
            raise InputError(
                f"payload: expected at most {limits.max_payload_bytes} bytes, got {len(payload)}",
                kind="oversized_block",
            )
        if len(payload) > limits.max_json_payload_bytes and is_json_block(payload, encoding):
            # refused unparsed: parsing holds the event loop (every channel) ~0.1 us a byte
            # (a JSON frame too: it starts with "{" as a JSON block does)
            raise InputError(
                f"JSON payload: expected at most {limits.max_json_payload_bytes} bytes, got {len(payload)} "
                "(send large blocks in the binary encoding)",
                kind="oversized_block",
            )
        block = decode_input(payload, encoding)
        if block.n_samples == 0:
            raise InputError("samples: expected at least one sample, got 0", kind="empty_block")
        if block.n_samples > limits.max_block_samples:
            raise InputError(
                f"samples: expected at most {limits.max_block_samples} per block, got {block.n_samples}",
                kind="oversized_block",
            )
        return block

    def _channel_for(self, key: str, block: Block) -> Channel:
        ch = self.channels.get(block.channel)
        if ch is not None:
            if ch.key != key:
                raise InputError(
                    f"channel {block.channel!r}: expected on key {ch.key!r}, got {key!r}",
                    kind="channel_key_mismatch",
                )
            if block.sample_rate_hz != ch.sample_rate_hz:
                raise InputError(
                    f"sample_rate_hz: expected {ch.sample_rate_hz} (this channel's rate), got {block.sample_rate_hz}",
                    kind="sample_rate_change",
                )
            return ch
        if len(self.channels) >= self.config.limits.max_channels:
            raise InputError(
                f"channels: expected at most {self.config.limits.max_channels}, got one more ({block.channel!r})",
                kind="channel_limit",
            )
        rule = self._rule_for(key)
        if rule is None:
            raise InputError(f"key {key!r}: no rule matches it", kind="no_rule")
        try:
            estimator = get_estimator(rule.estimator)(block.sample_rate_hz, rule.params)
        except ParameterError as exc:
            raise InputError(f"{rule.estimator} at {block.sample_rate_hz} Hz: {exc}", kind="estimator_error") from None
        ch = Channel(block.channel, key, estimator, block.sample_rate_hz, validity_version=self.validity_version)
        self.channels[block.channel] = ch
        log.info("channel %s on %s: %s at %g Hz", block.channel, key, rule.estimator, block.sample_rate_hz)
        return ch

    def _hand_out(
        self,
        key: str,
        channel: Channel,
        block: Block,
        track: Track,
        payloads: list[bytes],
        reset: bool,
        log_time_ns: int,
        received_ns: int | None,
    ) -> None:
        """An accepted block's estimates to the sinks, then its power-quality stage and the
        channel's latency: the same for a single block and a frame's column."""
        out_key = channel.out_key
        if out_key is None:
            out_key = channel.out_key = f"{self.config.keys.estimates_prefix}/{channel.name}"
        channel.last_log_ns = log_time_ns
        for payload_out in payloads:
            for sink in self.sinks:
                sink.on_estimate(out_key, payload_out, log_time_ns)
        self.counters.estimates += len(payloads)
        if self.pq.enabled:
            self._power_quality(key, channel, block, track, reset, log_time_ns)
        if received_ns is not None:
            channel.last_latency_ns = time.monotonic_ns() - received_ns

    def release_held(self, log_time_ns: int, out_key: str | None = None) -> int:
        """The end of a finite input (the daemon's drain, a replay's last message): every
        estimate still held back (``hold_estimates``) goes to the sinks, in order, so that
        everything accepted is published; with ``out_key``, only the channel publishing there
        (a replay meeting the idle release of :meth:`release_idle`). One that waited for the
        detector to confirm its window is published not valid: the samples that would have
        confirmed it never came. Returns how many were released."""
        n = 0
        for ch in self.channels.values():
            if not ch.held:
                continue
            key = ch.out_key or f"{self.config.keys.estimates_prefix}/{ch.name}"
            if out_key is not None and key != out_key:
                continue
            ch.out_key = key
            while ch.held:
                payload, _, window_start, _ = ch.held.popleft()
                payload = _not_valid(payload) if window_start >= 0 else payload
                for sink in self.sinks:
                    sink.on_estimate(key, payload, log_time_ns)
                n += 1
            ch.converged = False
        self.counters.estimates += n
        return n

    def release_idle(self, now_ns: int) -> int:
        """A feed that pauses: the estimates of every channel whose last block came at least
        ``idle_release_s`` before ``now_ns`` are released as at the input's end
        (:meth:`release_held`), so that a paused or finished stream's last estimates do not
        wait for a block that may never come. Their windows stay unconfirmed: not valid. A
        replay meets them as recorded estimates with nothing produced yet and releases that
        channel there, so it reproduces them bit for bit. Returns how many were released."""
        idle_ns = round(self.config.idle_release_s * 1e9)
        n = 0
        for ch in self.channels.values():
            if ch.held and now_ns - ch.last_log_ns >= idle_ns:
                n += self.release_held(now_ns, ch.out_key or f"{self.config.keys.estimates_prefix}/{ch.name}")
        return n

    def _forget_unborn(self, ch: Channel | None) -> None:
        """A channel whose first block was refused has accepted nothing and holds no state:
        it gives its slot back, so refused blocks (cheap to send, each on a new channel
        name) cannot use up ``limits.max_channels``."""
        if ch is not None and ch.last_seq is None and ch.name not in self.resume_points:
            del self.channels[ch.name]

    def _catch_up(self, ch: Channel, block: Block) -> bool:
        """A block of a channel taken over from another daemon: True when it was taken into
        the state only (already published by the other daemon, or already in the state)."""
        point = self.resume_points[ch.name]
        if block.seq > point.published_seq:  # the first block to publish: the gap is what nobody estimated
            del self.resume_points[ch.name]
            if ch.last_seq is None or ch.last_seq < point.published_seq:
                ch.last_seq, ch.next_t0_ns = point.published_seq, point.next_t0_ns
            return False
        if ch.last_seq is None or block.seq > ch.last_seq:
            ch.estimator.update(block.samples, last_only=True, t0_ns=block.t0_ns)
            self._accept(ch, block, 0, False, False)
        self.counters.caught_up += 1
        return True

    def _rule_for(self, key: str) -> EstimatorRule | None:
        if key not in self._rule_cache:
            if len(self._rule_cache) > 4 * self.config.limits.max_channels:
                self._rule_cache.clear()  # bounded: hostile senders may invent keys
            ke = zenoh.KeyExpr(key)
            self._rule_cache[key] = next(
                (r for r, expr in zip(self.rules, self._rule_exprs, strict=True) if expr.includes(ke)), None
            )
        return self._rule_cache[key]

    @staticmethod
    def _presence(ch: Channel, block: Block, reset: bool) -> None:
        """Run the channel's signal-presence detector over the block's signal (column 0, or
        what the estimator says), after the estimator accepted it; reset with the estimator."""
        assert ch.presence is not None
        if reset:
            ch.presence.reset()
        ch.last_run = ch.presence.update(ch.estimator.presence_samples(block.samples))[0]

    def _accept(
        self, ch: Channel, block: Block, gap_blocks: int, restart: bool, reset: bool, jump: bool = False
    ) -> None:
        ch.last_seq = block.seq
        ch.next_t0_ns = block.t0_ns + round(block.n_samples * 1e9 / block.sample_rate_hz)
        ch.blocks += 1
        ch.samples += block.n_samples
        if gap_blocks or restart or jump:
            ch.gaps += 1
            what = (
                "sender restarted its sequence at"
                if restart
                else "time jumped at"
                if jump
                else f"{gap_blocks} block(s) missing before"
            )
            log.warning("channel %s: %s seq %d%s", ch.name, what, block.seq, " (estimator reset)" if reset else "")

    def _estimate_payloads(
        self, ch: Channel, block: Block, track: Track, gap_blocks: int, restart: bool, reset: bool, jump: bool = False
    ) -> list[bytes]:
        """One Estimate at the block's last sample; or, for an estimator that reports on a
        time grid, one per report the block completed (zero, one or several), at its time.
        With ``hold_estimates`` (on by default from validity rules version 4) they are held back
        (:meth:`_hold`) and what this block releases is returned."""
        grid = track.reports
        t_last = block.t0_ns + round((block.n_samples - 1) * 1e9 / block.sample_rate_hz)
        made: list[tuple[bytes, bool, int]] = []  # payload, converged, timestamp
        if grid is None:
            payload, converged = self._estimate_payload(
                ch, block, track, t_last, t_last, gap_blocks, restart, reset, jump
            )
            made.append((payload, converged, t_last))
        else:
            if self.validity_version >= 2:  # a block without a report passes its flags on to the next report
                held = ch.held_flags
                if held is not None:
                    gap_blocks, restart, reset, jump = (
                        gap_blocks + held[0],
                        restart or held[1],
                        reset or held[2],
                        jump or held[3],
                    )
                    ch.held_flags = None
                if grid.n_reports == 0 and (gap_blocks or restart or reset or jump):
                    ch.held_flags = (gap_blocks, restart, reset, jump)
            for r, t_ns in enumerate(grid.timestamps_ns()):
                row = grid.track.rows(slice(r, r + 1))
                payload, converged = self._estimate_payload(
                    ch, block, row, t_ns, t_last, gap_blocks, restart, reset, jump
                )
                made.append((payload, converged, t_ns))
        if not self._holds:
            if made:
                ch.converged = made[-1][1]
            return [m[0] for m in made]
        return self._hold(ch, t_last, made, reset)

    def _hold(self, ch: Channel, t_last_ns: int, made: list[tuple[bytes, bool, int]], reset: bool) -> list[bytes]:
        """Validity rules version 3: no estimate is published valid while its window may hold
        an event the presence detector has not read yet. Each estimate waits until the
        detector has seen ``onset_latency_samples`` past the last sample its window holds (the
        block's last, or a grid report's ``lookahead_samples`` after its time; counted in
        samples, not wall time: replay reproduces it), and is then published valid only if
        the signal was present at that sample throughout its window and since (the run of
        presence there reaches back to the window's start). An estimate not valid when made
        stays so; estimates held when the channel starts over (a reset) are published not
        valid: the detector that was to confirm them starts afresh. Order is kept: an
        estimate leaves after every estimate made before it."""
        assert ch.presence is not None
        out: list[bytes] = []
        held = ch.held
        if reset:
            while held:
                payload, _, window_start, _ = held.popleft()
                out.append(_not_valid(payload) if window_start >= 0 else payload)
        n_now = ch.samples
        latency = ch.presence.onset_latency_samples
        memory = ch.estimator.memory_samples
        fs = ch.sample_rate_hz
        ahead = getattr(ch.estimator, "lookahead_samples", None)  # a grid report's window ends after its time
        for payload, converged, t_ns in made:
            valid = _DIAGNOSTICS_VALID[0] in payload or _DIAGNOSTICS_VALID[1] in payload
            lag = max(0, round((t_last_ns - t_ns) * fs / 1e9))
            end = n_now if ahead is None else min(n_now, n_now - lag + ahead)  # the window's last sample
            held.append((payload, end + latency, n_now - lag - memory if valid else -1, converged))
        run = ch.last_run
        start = n_now if run is None else n_now - run.shape[0]  # the channel's sample count before this block
        converged_out = None
        while held and held[0][1] <= n_now:
            payload, at, window_start, converged = held.popleft()
            if window_start >= 0:
                i = max(at - start - 1, 0)
                if run is None or run[i] < start + 1 + i - window_start:  # absent somewhere since the window began
                    payload, converged = _not_valid(payload), False
            out.append(payload)
            converged_out = converged
        if converged_out is not None:
            ch.converged = converged_out
        return out

    def _valid(
        self,
        ch: Channel,
        timestamp_ns: int,
        t_last_ns: int,
        frequency_hz: list[float | None],
        amplitude: list[float | None],
    ) -> bool:
        """``diagnostics.valid`` (format 3): the signal has been present (the presence
        detector, :mod:`sinewatch.estimators.presence`) from the estimator's memory before
        the estimate's time up to the block's last sample, and the estimate is finite
        (``frequency_hz`` and ``amplitude`` as :func:`_finite_list` made them: None where
        not finite)."""
        assert ch.presence is not None
        lag = max(0, round((t_last_ns - timestamp_ns) * ch.sample_rate_hz / 1e9))
        if ch.presence.run_samples < ch.estimator.memory_samples + lag:
            return False
        return None not in frequency_hz and None not in amplitude

    def _estimate_payload(
        self,
        ch: Channel,
        block: Block,
        track: Track,
        timestamp_ns: int,
        t_last_ns: int,
        gap_blocks: int,
        restart: bool,
        reset: bool,
        jump: bool = False,
    ) -> tuple[bytes, bool]:
        """The Estimate's bytes, and its ``converged``. From format 3 on, an estimate that is
        not valid is not converged either.

        The bytes are built without the pydantic model (:func:`encode_estimate_values`, the
        same bytes as ``encode_estimate(estimate_model(...))``; tests/test_codec_estimate_fast.py
        proves it), one estimate per block being the pipeline's hot path."""
        fast = self._fast_payload(ch, block, track, timestamp_ns, t_last_ns, gap_blocks, restart, reset, jump)
        if fast is not None:
            return fast
        converged = bool(track.converged[-1])
        frequency_hz = _finite_list(track.frequency_hz[-1])
        amplitude = _finite_list(track.amplitude[-1])
        valid = True
        version = self.estimate_version
        if version >= 3:
            valid = self._valid(ch, timestamp_ns, t_last_ns, frequency_hz, amplitude)
            converged = converged and valid
        std = track.std
        names = ch.json_names
        if names is None:
            names = ch.json_names = (json_string(ch.name), json_string(ch.estimator.name))
        payload = encode_estimate_values(
            version,
            names[0],
            block.seq,
            int(timestamp_ns),
            block.n_samples,
            names[1],
            frequency_hz,
            amplitude,
            _finite_list(track.phase_rad[-1]),
            finite_or_none(track.offset[-1]),
            None if track.rocof_hz_per_s is None else _finite_list(track.rocof_hz_per_s[-1]),
            None
            if std is None
            else (
                _finite_list(std.frequency_hz[-1]),
                _finite_list(std.amplitude[-1]),
                _finite_list(std.phase_rad[-1]),
                finite_or_none(std.offset[-1]),
            ),
            converged,
            valid,
            finite_or_none(track.residual_rms),
            gap_blocks > 0 or restart or jump,
            gap_blocks,
            restart,
            reset,
            {k: _last_value(v) for k, v in track.extras.items()} if track.extras else {},
            self._fencing_json,
            # the input's time quality (a frame's is each of its columns'), passed through as stated
            TIME_QUALITY_JSON[block.time_quality],
        )
        return payload, converged

    def _fast_payload(
        self,
        ch: Channel,
        block: Block,
        track: Track,
        timestamp_ns: int,
        t_last_ns: int,
        gap_blocks: int,
        restart: bool,
        reset: bool,
        jump: bool,
    ) -> tuple[bytes, bool] | None:
        """:meth:`_estimate_payload`'s bytes in the usual case (format 3 or later, every value
        finite, no extras), built by one ``%`` formatting of a template cached on the channel
        (:func:`_estimate_template`) with every float of the estimate gathered by one numpy
        call: ``%r`` of a float is its ``repr``, which is what :func:`encode_estimate_values`
        writes, so the bytes are the same (tests/test_pipeline_hot_path.py compares them). None
        when the case is not the usual one (the general path then builds them)."""
        version = self.estimate_version
        if version < 3 or track.extras:
            return None
        std, rocof = track.std, track.rocof_hz_per_s
        parts = [track.frequency_hz[-1], track.amplitude[-1], track.phase_rad[-1], track.offset[-1:]]
        if rocof is not None:
            parts.append(rocof[-1])
        if std is not None:
            parts += (std.frequency_hz[-1], std.amplitude[-1], std.phase_rad[-1], std.offset[-1:])
        values = np.concatenate(parts)
        if values.dtype != _F64:
            return None
        floats = values.tolist()
        # a NaN or an infinity makes the sum non-finite (so may an overflow: then the general path)
        if not isfinite(sum(floats)):
            return None
        k = track.frequency_hz.shape[-1]
        key = (version, k, rocof is not None, std is not None, self._fencing_json, block.time_quality)
        template = ch.template
        if template is None or template[0] != key:
            names = ch.json_names
            if names is None:
                names = ch.json_names = (json_string(ch.name), json_string(ch.estimator.name))
            template = ch.template = (key, _estimate_template(names, *key))
        lag = max(0, round((t_last_ns - timestamp_ns) * ch.sample_rate_hz / 1e9))
        assert ch.presence is not None
        valid = ch.presence.run_samples >= ch.estimator.memory_samples + lag  # _valid, every value finite
        converged = valid and bool(track.converged[-1])
        sec, nsec = divmod(int(timestamp_ns), 1_000_000_000)
        rms = track.residual_rms
        gap = gap_blocks > 0 or restart or jump
        payload = template[1] % (
            block.seq,
            int(timestamp_ns),
            sec,
            nsec,
            block.n_samples,
            *floats,
            _TRUE_FALSE[converged],
            _TRUE_FALSE[valid],
            "null" if rms is None or not isfinite(rms) else repr(float(rms)),
            _TRUE_FALSE[gap],
            gap_blocks,
            _TRUE_FALSE[restart],
            _TRUE_FALSE[reset],
        )
        return payload.encode("ascii"), converged

    def _reject(
        self,
        key: str,
        block: Block | None,
        ch: Channel | None,
        kind: str,
        message: str,
        log_time_ns: int,
        *,
        count: int = 1,
    ) -> None:
        """One ErrorReport for ``count`` rejected inputs (more than one only for inputs the
        intake dropped in one go)."""
        self.counters.errors += count
        self.counters.by_kind[kind] += count
        self._error_counts[(key, kind)] += count
        if ch is not None:
            ch.errors += 1
        channel_name = block.channel if block is not None else None
        report = ErrorReport(
            key=key,
            channel=channel_name,
            seq=block.seq if block is not None else None,
            kind=ErrorKind(kind),
            message=message,
            count=self._error_counts[(key, kind)],
        )
        n = self._error_counts[(key, kind)]
        if n <= 5 or _is_power_of_ten(n):  # a hostile flood must not flood the log too
            log.warning(
                "rejected input on %s (%s): %s%s",
                key,
                kind,
                message,
                f" [{n} so far on this key; further ones logged at powers of ten]" if n >= 5 else "",
            )
        out_key = f"{self.config.keys.errors_prefix}/{channel_name or '_unknown'}"
        payload = encode_error(report)
        for sink in self.sinks:
            sink.on_error(out_key, payload, log_time_ns)

    # ---- introspection ---------------------------------------------------------------------
    def report_error(self, key: str, kind: str, message: str, log_time_ns: int, *, count: int = 1) -> None:
        """An error found outside the pipeline (e.g. the intake queue dropped ``count`` inputs)."""
        self._reject(key, None, None, kind, message, log_time_ns, count=count)

    def sink_status(self) -> list[dict[str, Any]]:
        return [sink.status() for sink in self.sinks]

    def open_sinks(self) -> None:
        for sink in self.sinks:
            sink.open()

    def flush_sinks(self) -> None:
        for sink in self.sinks:
            sink.flush()

    def close_sinks(self) -> None:
        for sink in self.sinks:
            sink.close()

    def snapshot(self) -> dict[str, Any]:
        """The state of every channel, enough to resume bit-exactly (written at rotation)."""
        return {
            "format_version": 1,
            "channels": [ch.snapshot() for ch in self.channels.values()],
            "error_counts": [[k, kind, n] for (k, kind), n in self._error_counts.items()],
            **(
                {"resume_points": {ch: [p.published_seq, p.next_t0_ns] for ch, p in self.resume_points.items()}}
                if self.resume_points
                else {}
            ),
            **({"power_quality": self.pq.snapshot()} if self.pq.enabled else {}),
            **({"fencing": self.fencing.model_dump()} if self.fencing is not None else {}),
        }

    def restore(self, snapshot: dict[str, Any]) -> None:
        if "fencing" in snapshot:  # the term the estimates after this state were published under
            self.set_fencing(Fencing.model_validate(snapshot["fencing"]))
        for item in snapshot["channels"]:
            est = get_estimator(item["estimator"]["estimator"]).from_state(item["estimator"])
            ch = Channel(
                item["name"], item["key"], est, float(item["sample_rate_hz"]), validity_version=self.validity_version
            )
            for attr in ("last_seq", "next_t0_ns", "blocks", "samples", "gaps", "errors", "converged"):
                setattr(ch, attr, item[attr])
            if "presence" in item:  # snapshots of earlier builds have none: it starts afresh
                assert ch.presence is not None
                ch.presence.set_state(item["presence"])
            ch.held.extend((p.encode("ascii"), int(r), int(w), bool(c)) for p, r, w, c in item.get("held", ()))
            self.channels[ch.name] = ch
        for key, kind, n in snapshot.get("error_counts", []):
            self._error_counts[(key, kind)] = n
        for ch_name, (seq, next_t0) in snapshot.get("resume_points", {}).items():
            self.resume_points[ch_name] = ResumePoint(seq, next_t0)
        if "power_quality" in snapshot:
            self.pq.restore(snapshot["power_quality"])

    def channel_status(self) -> list[dict[str, Any]]:
        return [
            {
                "channel": ch.name,
                "key": ch.key,
                "estimator": ch.estimator.name,
                "sample_rate_hz": ch.sample_rate_hz,
                "blocks": ch.blocks,
                "samples": ch.samples,
                "errors": ch.errors,
                "gaps": ch.gaps,
                "last_seq": ch.last_seq,
                "last_latency_us": None if ch.last_latency_ns is None else ch.last_latency_ns / 1e3,
                "converged": ch.converged,
            }
            for ch in self.channels.values()
        ]


_DIAGNOSTICS_VALID = (
    b'"diagnostics":{"converged":true,"valid":true,',
    b'"diagnostics":{"converged":false,"valid":true,',
)
_DIAGNOSTICS_NOT_VALID = b'"diagnostics":{"converged":false,"valid":false,'


def _not_valid(payload: bytes) -> bytes:
    """An Estimate's bytes (format 3 or later) with ``valid`` and ``converged`` false: the
    diagnostics object's opening is unique in the message (names are JSON-escaped, so their
    quotes never read as these bytes)."""
    for flag in _DIAGNOSTICS_VALID:
        if flag in payload:
            return payload.replace(flag, _DIAGNOSTICS_NOT_VALID, 1)
    return payload


_TRUE_FALSE = ("false", "true")


def _estimate_template(
    names: tuple[str, str],
    version: int,
    k: int,
    rocof: bool,
    std: bool,
    fencing_json: str,
    time_quality: int,
) -> str:
    """The ``%`` template of an Estimate (format 3 or later, no extras) with ``k`` components:
    :func:`encode_estimate_values`'s layout, field for field, with ``%d`` for seq,
    timestamp_ns, sec, nsec, n_samples and gap_blocks, ``%r`` for each float (in the order
    :meth:`Pipeline._fast_payload` gathers them) and ``%s`` for converged, valid,
    residual_rms, gap, restart and reset. Constant text is escaped (``%`` doubled)."""

    def const(text: str) -> str:
        return text.replace("%", "%%")

    floats = "[" + ",".join(["%r"] * k) + "]"
    out = (
        f'{{"format_version":{version},"channel":{const(names[0])},"seq":%d,"timestamp_ns":%d,'
        f'"timestamp":{{"sec":%d,"nsec":%d}},"n_samples":%d,"estimator":{const(names[1])},'
        f'"frequency_hz":{floats},"amplitude":{floats},"phase_rad":{floats},"offset":%r,'
        f'"rocof_hz_per_s":{floats if rocof else "null"},'
        + (
            f'"std":{{"frequency_hz":{floats},"amplitude":{floats},"phase_rad":{floats},"offset":%r}},'
            if std
            else '"std":null,'
        )
        + '"diagnostics":{"converged":%s,"valid":%s,"residual_rms":%s,"gap":%s,"gap_blocks":%d,'
        '"restart":%s,"reset":%s,"extras":{}}'
        + (f',"fencing":{const(fencing_json)}' if version >= 4 else "")
        + (f',"time_quality":{const(TIME_QUALITY_JSON[time_quality])}}}' if version >= 5 else "}")
    )
    return out


def _own_method(sink: Sink, name: str) -> Any:
    """``sink.<name>`` (bound once), or None when it is NullSink's, which does nothing."""
    method = getattr(sink, name)
    return None if getattr(method, "__func__", None) is getattr(NullSink, name) else method


def _attributes(obj: object, *names: str) -> dict[str, Any]:
    """``{name: obj.name}`` for the names given, in that order (status and snapshot dicts)."""
    return {name: getattr(obj, name) for name in names}


def _key_matches(expr: str, key: str) -> bool:
    return bool(zenoh.KeyExpr(expr).includes(zenoh.KeyExpr(key)))


def _cycle_frequency_hz(estimator: Estimator) -> float:
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


def _continues_in_time(ch: Channel, block: Block) -> bool:
    """The block's first sample is where the channel's samples ended (within half a block and
    one sample): the inline test of the usual case, :func:`check_continuity` decides the rest."""
    if ch.next_t0_ns is None:
        return True
    period_ns = 1e9 / block.sample_rate_hz
    return abs(block.t0_ns - ch.next_t0_ns) <= max(0.5 * block.n_samples * period_ns, period_ns)


def _is_power_of_ten(n: int) -> bool:
    while n >= 10 and n % 10 == 0:
        n //= 10
    return n == 1


_F64 = np.dtype(np.float64)


def _all_finite_2d(x: np.ndarray) -> bool:
    """Whether every value of a frame is finite (the usual case: one pass, no per-column work)."""
    return bool(np.isfinite(x.reshape(-1) if x.flags.c_contiguous else x).all())


def _finite_list(row: np.ndarray) -> list[float | None]:
    """``[finite_or_none(v) for v in row]``, faster for the usual float64 row."""
    if type(row) is np.ndarray and row.dtype == _F64 and row.ndim == 1:
        return [v if isfinite(v) else None for v in row.tolist()]
    return [finite_or_none(v) for v in row]


def estimate_model(
    ch: Channel,
    block: Block,
    track: Track,
    timestamp_ns: int,
    converged: bool,
    valid: bool,
    gap_blocks: int,
    restart: bool,
    reset: bool,
    fencing: Fencing | None = None,
) -> Estimate:
    """The Estimate the pipeline's bytes encode, as the pydantic model: the schema's way of
    building it, what :meth:`Pipeline._estimate_payload` equals byte for byte (tests)."""
    return Estimate(
        channel=ch.name,
        seq=block.seq,
        timestamp_ns=timestamp_ns,
        n_samples=block.n_samples,
        estimator=ch.estimator.name,
        frequency_hz=[finite_or_none(v) for v in track.frequency_hz[-1]],
        amplitude=[finite_or_none(v) for v in track.amplitude[-1]],
        phase_rad=[finite_or_none(v) for v in track.phase_rad[-1]],
        offset=finite_or_none(track.offset[-1]),
        rocof_hz_per_s=None if track.rocof_hz_per_s is None else [finite_or_none(v) for v in track.rocof_hz_per_s[-1]],
        std=None if track.std is None else _uncertainty(track.std),
        diagnostics=Diagnostics(
            converged=converged,
            valid=valid,
            residual_rms=finite_or_none(track.residual_rms),
            gap=gap_blocks > 0 or restart,
            gap_blocks=gap_blocks,
            restart=restart,
            reset=reset,
            extras={k: _last_value(v) for k, v in track.extras.items()},
        ),
        fencing=fencing,
        time_quality=time_quality_model(block.time_quality),
    )


def _uncertainty(std: TrackStd) -> Uncertainty:
    return Uncertainty(
        frequency_hz=[finite_or_none(v) for v in std.frequency_hz[-1]],
        amplitude=[finite_or_none(v) for v in std.amplitude[-1]],
        phase_rad=[finite_or_none(v) for v in std.phase_rad[-1]],
        offset=finite_or_none(std.offset[-1]),
    )


def _last_value(arr: np.ndarray) -> float | list[float | None] | None:
    last = arr[-1]
    if np.ndim(last) == 0:
        return finite_or_none(last)
    return [finite_or_none(v) for v in np.ravel(last)]


def sanitize_log_time(previous: int, now: int) -> int:
    """Strictly increasing log times, even if the clock stalls or steps back."""
    return now if now > previous else previous + 1


__all__ = ["Channel", "GuardedSink", "NullSink", "Pipeline", "Sink", "sanitize_log_time"]
