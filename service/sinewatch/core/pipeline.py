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
from collections import Counter
from collections.abc import Callable, Container, Mapping, Sequence
from typing import Any

import numpy as np
import zenoh

from sinewatch.core.channel import (
    Channel,
    FrameLayout,
    FrameMember,
    PipelineCounters,
    ResumePoint,
    UsualBank,
    continues_in_time,
    usual_bank,
)
from sinewatch.core.continuity import check_continuity, rules_version
from sinewatch.core.estimate_bytes import (
    bank_payloads,
    bank_writing,
    estimate_model,
    estimate_payload,
    usual_bank_payloads,
)
from sinewatch.core.hold import hold, hold_at_end, not_valid, take_over
from sinewatch.core.sinks import GuardedSink, NullSink, Sink
from sinewatch.estimators import get as get_estimator
from sinewatch.estimators.bank import ColumnTracks, update_bank, update_bank_reporting_at, update_reporting_at
from sinewatch.estimators.base import Estimator, Track, kernel_samples
from sinewatch.estimators.presence import PresenceBankReadings, read_presence_bank
from sinewatch.power_quality.stage import PqStage
from sinewatch.schemas.codec import Block, dumps, encode_error, is_json_block
from sinewatch.schemas.config import EstimatorRule, SinewatchConfig
from sinewatch.schemas.errors import InputError, ParameterError, SinewatchError
from sinewatch.schemas.frame import Frame, channel_key, decode_input
from sinewatch.schemas.messages import ESTIMATE_FORMAT_VERSION, ErrorKind, ErrorReport, Fencing
from sinewatch.schemas.power_quality import PQ_FORMAT_VERSION

log = logging.getLogger("sinewatch.core.pipeline")


class Pipeline:
    def __init__(
        self,
        config: SinewatchConfig,
        sinks: list[Sink],
        *,
        rules: list[EstimatorRule] | None = None,
        estimate_version: int = ESTIMATE_FORMAT_VERSION,
        pq_version: int = PQ_FORMAT_VERSION,
        validity_version: int | None = None,
    ) -> None:
        self.config = config
        if validity_version is None:  # a new pipeline's: what its config asks for
            validity_version = rules_version(config.report_in_block)
        self.estimate_version = estimate_version  # < current to reproduce recordings of earlier builds
        self.validity_version = validity_version  # likewise (sinewatch.core.continuity)
        # hold estimates back (_hold) where the config asks, from validity rules version 3 on
        self._holds = config.hold_estimates and validity_version >= 3 and estimate_version >= 3
        # with the hold, from validity rules version 6: each block's estimate at the sample its
        # detector has read its onset latency past, in the same block (released at once)
        self._reports_early = self._holds and validity_version >= 6
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
        self._layouts: dict[str, FrameLayout] = {}  # by frame key: its last frame's channels and banks
        self._bank_estimate_failures = 0  # bank_payloads raising (a bug): logged the first few times
        self.resume_points: dict[str, ResumePoint] = {}  # by channel: after a takeover (cluster)
        self.fencing: Fencing | None = None  # the shard and term this daemon owns its channels under (cluster)
        self.fencing_json = "null"
        self.pq = PqStage(
            config, _key_matches, pq_version
        )  # power quality (harmonics, groups, aggregates): off unless configured

    def set_fencing(self, fencing: Fencing | None) -> None:
        """The shard and election term every estimate from now on carries (format 4): set
        by the cluster when this daemon wins its shard's election, and by a snapshot."""
        self.fencing = fencing
        self.fencing_json = "null" if fencing is None else dumps(fencing.model_dump()).decode()

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
            track, lag = self._estimate_and_detect(channel, block, reset)
            stage = "estimate"
            self._accept(channel, block, gap_blocks, restart, reset, jump)
            payloads = self._estimate_payloads(channel, block, track, (gap_blocks, restart, reset, jump), lag)
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
        x = frame.samples  # of the kernels' kind (``_decode``): each column what its block would give
        finite = np.isfinite(x).all(axis=0).tolist() if not _all_finite_2d(x) else None
        t_last = frame.t0_ns + round((frame.n_samples - 1) * 1e9 / frame.sample_rate_hz)
        layout = self._usual_frame(key, frame) if finite is None else None
        if layout is not None:
            for bank in layout.banks:
                self._usual_bank(bank, frame, x, t_last, log_time_ns, received_ns)
            return
        keys = self._frame_channel_keys(key, frame.channels)
        banks = self._checked_frame(key, keys, frame, finite, log_time_ns)
        for members in banks.values():
            self._bank(members, x, len(keys), frame.t0_ns, t_last, log_time_ns, received_ns)

    def _bank(
        self,
        members: list[FrameMember],
        x: np.ndarray,
        n_all: int,
        t0_ns: int,
        t_last: int,
        log_time_ns: int,
        received_ns: int | None,
        tracks: Sequence[Track | None] | None = None,
    ) -> None:
        """One bank of a frame, each channel checked on its own: the estimators together
        (:meth:`_run_bank`; ``tracks`` when they have run already), then the detectors, each
        channel's Estimate, hold and hand-out (together where :meth:`_bank_estimates` applies).
        Reporting early (validity rules version 6), each channel as its block alone would go
        (:meth:`_column_alone`: its detector first); a usual frame's bank goes together
        (:meth:`_usual_bank`)."""
        if tracks is None and self._reports_early and _not_grid(members[0].channel.estimator):
            for m in members:
                self._column_alone(m, log_time_ns, received_ns)
            return
        if tracks is None:
            tracks = self._run_bank(members, x, n_all, t0_ns, log_time_ns)
        readings = self._presence_bank(members, tracks, x)
        presence_done = readings is not None
        if readings is not None and self._bank_estimates(members, tracks, t_last, log_time_ns, received_ns, readings):
            return
        for member, track in zip(members, tracks, strict=True):
            if track is not None:
                self._frame_estimate(member, track, log_time_ns, received_ns, presence_done)

    def _column_alone(self, m: FrameMember, log_time_ns: int, received_ns: int | None) -> None:
        """What :meth:`process` does with a checked block, for one channel of a frame."""
        channel, block = m.channel, m.block
        stage = "estimator"
        try:
            track, lag = self._estimate_and_detect(channel, block, m.reset)
            stage = "estimate"
            self._accept(channel, block, m.gap_blocks, m.restart, m.reset, m.jump)
            payloads = self._estimate_payloads(channel, block, track, (m.gap_blocks, m.restart, m.reset, m.jump), lag)
        except InputError as exc:
            self._forget_unborn(channel)
            self._reject(channel.key, block, channel, exc.kind, str(exc), log_time_ns)
            return
        except SinewatchError as exc:  # as process reports it
            self._forget_unborn(channel)
            self._reject(channel.key, block, channel, "estimator_error", str(exc), log_time_ns)
            return
        except Exception as exc:  # noqa: BLE001 (one channel's fault)
            self._forget_unborn(channel)
            self._fault(channel.key, block, channel, stage, exc, log_time_ns)
            return
        self._hand_out(channel.key, channel, block, track, payloads, m.reset, log_time_ns, received_ns)

    def _usual_frame(self, key: str, frame: Frame) -> FrameLayout | None:
        """The key's last layout when this frame is its usual case, without
        :meth:`_checked_frame`'s calls a channel: the same channels as the key's last frame, every
        one of which was accepted into the same banks (:attr:`_layouts`), every value finite,
        every channel the next block of its sequence and time, no takeover under way. None
        otherwise (then every channel is checked on its own): nothing is changed before that is known."""
        layout = self._layouts.get(key)
        if layout is None or layout.names != frame.channels or self.resume_points:
            return None
        if frame.sample_rate_hz != layout.sample_rate_hz:
            return None
        channels, seq, t0 = self.channels, frame.seq, frame.t0_ns
        # continues_in_time, once for the frame: its channels share t0, rate and length
        period_ns = 1e9 / frame.sample_rate_hz
        tolerance = max(0.5 * frame.n_samples * period_ns, period_ns) if self.validity_version >= 2 else None
        for ch in layout.channels:
            if channels.get(ch.name) is not ch or ch.last_seq != seq - 1:
                return None
            if tolerance is not None and ch.next_t0_ns is not None and abs(t0 - ch.next_t0_ns) > tolerance:
                return None
        for ch in layout.channels:
            ch.source_key = key  # a queued frame of this key holds its next block (release_idle)
        return layout

    def _usual_bank(
        self, bank: UsualBank, frame: Frame, x: np.ndarray, t_last: int, log_time_ns: int, received_ns: int | None
    ) -> None:
        """One bank of a usual frame (:meth:`_usual_frame`: every channel the next block of its
        sequence, no gap, reset or time jump, every value finite): what :meth:`_bank` does, from
        the layout's lists, without a :class:`FrameMember` or a :class:`Block` a column. Anything
        unusual on the way (a bank that raises, detectors that do not run as a bank, the
        power-quality stage, Estimates not written in one call) hands the bank to
        :meth:`_bank` at that point, with the same results."""
        ests = bank.estimators
        if self._reports_early and _not_grid(ests[0]):
            if bank.presence_bank:
                self._usual_bank_early(bank, frame, x, t_last, log_time_ns, received_ns)
            else:  # (a bank of one, or detectors that read another signal than the block's)
                for m in self._members(bank, frame):
                    self._column_alone(m, log_time_ns, received_ns)
            return
        samples = x if bank.every_column else x[:, bank.columns]
        saved = [est._state_checkpoint() for est in ests]  # (not est._state: that takes it out of its bank's stack)
        try:
            tracks = update_bank(ests, samples, last_only=True, t0_ns=frame.t0_ns, finite=True)
        except Exception:  # noqa: BLE001 (isolated by _bank, which runs the bank again, channel by channel)
            for est, state in zip(ests, saved, strict=True):
                est._state_rollback(state)
            self._bank(self._members(bank, frame), x, frame.n_channels, frame.t0_ns, t_last, log_time_ns, received_ns)
            return
        readings = self._usual_presence(bank, x)
        if (
            readings is None
            or self.pq.enabled
            or not self._usual_estimates(bank, frame, tracks, t_last, log_time_ns, received_ns, readings)
        ):
            members = self._members(bank, frame)
            if readings is None:  # each channel's own detector, isolated (as _bank does it)
                self._bank(members, x, frame.n_channels, frame.t0_ns, t_last, log_time_ns, received_ns, tracks)
                return
            for member, track in zip(members, tracks, strict=True):
                self._frame_estimate(member, track, log_time_ns, received_ns, True)

    def _usual_bank_early(
        self, bank: UsualBank, frame: Frame, x: np.ndarray, t_last: int, log_time_ns: int, received_ns: int | None
    ) -> None:
        """:meth:`_usual_bank` reporting early (validity rules version 6): the detectors' bank
        first, then the estimators' bank reporting each channel at the sample its detector has
        read its onset latency past (:func:`update_bank_reporting_at`: one call a distinct row,
        usually two in all), each channel exactly as :meth:`_estimate_and_detect` runs it alone.
        A bank that raises leaves every estimator and detector as it was, and each channel then
        goes alone (:meth:`_column_alone`)."""
        ests, detectors = bank.estimators, bank.detectors
        before = [(d.sums, d.counters, d.ring) for d in detectors]  # (the kernels return new arrays)
        readings = self._usual_presence(bank, x)
        n = frame.n_samples
        if readings is not None:
            lags = [lat if lat < n else 0 for lat in readings.onset_latency_samples]
            samples = x if bank.every_column else x[:, bank.columns]
            saved = [est._state_checkpoint() for est in ests]
            try:
                tracks = update_bank_reporting_at(
                    ests, samples, [n - 1 - lag for lag in lags], t0_ns=frame.t0_ns, finite=True
                )
            except Exception:  # noqa: BLE001 (isolated below, channel by channel)
                for est, state in zip(ests, saved, strict=True):
                    est._state_rollback(state)
                readings = None
        if readings is None:
            for d, (sums, counters, ring) in zip(detectors, before, strict=True):
                d.sums, d.counters, d.ring = sums, counters, ring
            for m in self._members(bank, frame):
                self._column_alone(m, log_time_ns, received_ns)
            return
        lag = lags[0] if lags.count(lags[0]) == len(lags) else None
        if (
            lag is None
            or self.pq.enabled
            or not self._usual_estimates(bank, frame, tracks, t_last, log_time_ns, received_ns, readings, lag)
        ):
            for member, track, lag_c in zip(self._members(bank, frame), tracks, lags, strict=True):
                self._frame_estimate(member, track, log_time_ns, received_ns, True, lag_c)

    @staticmethod
    def _usual_presence(bank: UsualBank, x: np.ndarray) -> PresenceBankReadings | None:
        """:meth:`_presence_bank` of a usual frame's bank (no channel reset, every track made)."""
        if not bank.presence_bank:
            return None
        try:
            readings = read_presence_bank(bank.detectors, x, bank.columns)
        except Exception:  # noqa: BLE001 (the state is untouched: each channel runs its own, isolated)
            return None
        if readings is not None:
            for ch, run in zip(bank.channels, readings.runs, strict=True):
                ch.last_run = run
        return readings

    @staticmethod
    def _members(bank: UsualBank, frame: Frame) -> list[FrameMember]:
        """A usual bank's channels as :meth:`_checked_frame` would have made them (no gap, no reset)."""
        return [
            FrameMember(ch, frame.block(c), c, 0, False, False, False)
            for c, ch in zip(bank.columns, bank.channels, strict=True)
        ]

    def _checked_frame(
        self, key: str, keys: tuple[str, ...], frame: Frame, finite: list[bool] | None, log_time_ns: int
    ) -> dict[tuple[int, str, float], list[FrameMember]]:
        """Each column checked as its channel's block would be (a refused one reported on its
        channel's key); the accepted ones grouped into banks (the channels that share a rule,
        an estimator and a rate), in column order. A frame all of whose channels went into
        banks is kept as its key's layout (:meth:`_usual_frame`)."""
        banks: dict[tuple[int, str, float], list[FrameMember]] = {}
        accepted = 0
        for c, ckey in enumerate(keys):
            block = frame.block(c)
            channel: Channel | None = None
            try:
                channel = self._channel_for(ckey, block)
                channel.source_key = key  # a queued frame of this key holds its next block (release_idle)
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
            accepted += 1
        if accepted == len(keys):
            self._keep_layout(key, frame, banks)
        else:
            self._layouts.pop(key, None)
        return banks

    def _keep_layout(self, key: str, frame: Frame, banks: dict[tuple[int, str, float], list[FrameMember]]) -> None:
        """Remember a frame key's channels and banks (every channel accepted, one column each)."""
        channels: list[Channel | None] = [None] * len(frame.channels)
        for members in banks.values():
            for m in members:
                channels[m.column] = m.channel
        if len(self._layouts) > self.config.limits.max_channels:
            self._layouts.clear()  # bounded: hostile senders may invent frame keys
        self._layouts[key] = FrameLayout(
            frame.channels,
            frame.sample_rate_hz,
            tuple(channels),  # type: ignore[arg-type]  # (every column is one accepted channel's)
            tuple(
                usual_bank(tuple(m.column for m in members), tuple(channels), len(channels))  # type: ignore[arg-type]
                for members in banks.values()
            ),
        )

    def _frame_channel_keys(self, key: str, names: tuple[str, ...]) -> tuple[str, ...]:
        """Each channel's key (:func:`sinewatch.schemas.frame.channel_key`), once per layout."""
        cached = self._frame_keys.get((key, names))
        if cached is None:
            if len(self._frame_keys) > 4 * self.config.limits.max_channels:
                self._frame_keys.clear()  # bounded: hostile senders may invent layouts
            cached = self._frame_keys[(key, names)] = tuple(channel_key(key, name) for name in names)
        return cached

    def _estimate_and_detect(self, channel: Channel, block: Block, reset: bool) -> tuple[Track, int]:
        """The channel's estimator and presence detector over an accepted block (reset first when
        ``reset``): the Track its estimate is made of, and that estimate's lag, the samples from
        its row to the block's last. Up to validity rules version 5 (or without the hold) the
        estimator runs first and reports at the block's last sample (lag 0). From version 6 the
        detector (which reads the block's samples, not the estimator's output) runs first, and
        the estimator reports at the sample L = ``onset_latency_samples`` before the block's last
        (:func:`update_reporting_at`): the detector has read L past it, so the hold confirms it in
        this block. A block of L samples or fewer, and an estimator that reports on a time grid,
        report as before. A block the estimator rejects leaves both states as they were."""
        est = channel.estimator
        if not self._reports_early or not _not_grid(est):
            track = self._update(channel, block, reset)
            self._presence(channel, block, reset)
            return track, 0
        x = est._as_block(block.samples)  # the typed errors of a bad block, before any state changes
        detector = channel.presence
        assert detector is not None
        before = (detector.sums, detector.counters, detector.ring)  # (the kernel returns new arrays)
        if reset:
            detector.reset()
        channel.last_run = detector.update(est.presence_samples(x))[0]
        latency = detector.onset_latency_samples
        lag = latency if latency < block.n_samples else 0  # a block of L samples or fewer: held as before
        try:
            return self._update(channel, block, reset, block.n_samples - 1 - lag), lag
        except Exception:
            detector.sums, detector.counters, detector.ring = before
            raise

    @staticmethod
    def _update(channel: Channel, block: Block, reset: bool, row: int | None = None) -> Track:
        """The channel's estimator on the block, reset first when ``reset``. A block the
        estimator rejects (a NaN, the wrong shape) leaves the state as it was, reset or not:
        a rejected block must not start a channel over."""
        est = channel.estimator
        if not reset:
            if row is None:
                return est.update(block.samples, last_only=True, t0_ns=block.t0_ns)
            return update_reporting_at(est, block.samples, row, t0_ns=block.t0_ns)
        before = est.get_state()
        est.reset()
        try:
            if row is None:
                return est.update(block.samples, last_only=True, t0_ns=block.t0_ns)
            return update_reporting_at(est, block.samples, row, t0_ns=block.t0_ns)
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
            and (self.validity_version < 2 or continues_in_time(channel, block))
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

    def _frame_member(self, channel: Channel, block: Block, c: int, finite: list[bool] | None) -> FrameMember:
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
        return FrameMember(channel, block, c, gap_blocks, restart, reset, jump)

    def _catch_up_checked(self, channel: Channel, block: Block, finite: list[bool] | None, c: int) -> bool:
        if finite is not None and not finite[c]:
            raise InputError("samples: expected finite values, got NaN/Inf", kind="non_finite")
        return self._catch_up(channel, block)

    def _run_bank(
        self, members: list[FrameMember], x: np.ndarray, n_all: int, t0_ns: int, log_time_ns: int
    ) -> Sequence[Track | None]:
        """Advance one rule's channels together; a bank that raises is rolled back (kernels
        return new states, so the old ones are intact) and run channel by channel, so that
        only the faulty channel's block is lost (``estimator_fault``). The bank's Tracks as
        :func:`update_bank` gives them (a :class:`ColumnTracks` is made only when read);
        None for a channel whose block was lost."""
        ests = [m.channel.estimator for m in members]
        for m in members:
            if m.reset:
                m.channel.estimator.reset()
        cols = [m.column for m in members]
        samples = x if len(cols) == n_all and cols == list(range(n_all)) else x[:, cols]
        saved = [est._state_checkpoint() for est in ests]  # (not est._state: that takes it out of its bank's stack)
        try:
            return update_bank(ests, samples, last_only=True, t0_ns=t0_ns)
        except Exception:  # noqa: BLE001 (isolated below, channel by channel)
            for est, state in zip(ests, saved, strict=True):
                est._state_rollback(state)
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
    def _presence_bank(
        members: list[FrameMember], tracks: Sequence[Track | None], x: np.ndarray
    ) -> PresenceBankReadings | None:
        """The presence detectors of a bank's accepted channels in one compiled call
        (:func:`read_presence_bank`: each detector's run and state exactly what
        :meth:`_presence` gives it), and what they read after the frame; None when it does not
        apply (then each channel's own runs in :meth:`_frame_estimate`, which also isolates a
        fault to its channel)."""
        live = members if _every_track(tracks) else [m for m, t in zip(members, tracks, strict=True) if t is not None]
        # a bank's channels share one estimator class (its rule's): asked of the first
        if len(live) < 2 or type(live[0].channel.estimator).presence_samples is not Estimator.presence_samples:
            return None
        detectors = [m.channel.presence for m in live]
        for m, det in zip(live, detectors, strict=True):
            assert det is not None
            if m.reset:
                det.reset()
        try:
            readings = read_presence_bank(detectors, x, [m.column for m in live])  # type: ignore[arg-type]
        except Exception:  # noqa: BLE001 (the state is untouched: each channel runs its own, isolated)
            return None
        if readings is None:
            return None
        for m, run in zip(live, readings.runs, strict=True):
            m.channel.last_run = run
        return readings

    def _bank_estimates(
        self,
        members: list[FrameMember],
        tracks: Sequence[Track | None],
        t_last: int,
        log_time_ns: int,
        received_ns: int | None,
        readings: PresenceBankReadings,
    ) -> bool:
        """What :meth:`_frame_estimate` does for each of a bank's channels, their presence
        detectors run (``readings``: what they read, a channel each), for the whole bank at
        once: every Estimate's bytes in one compiled call
        (:func:`sinewatch.core.estimate_bytes.bank_payloads`, the same bytes), each channel's
        accept and hold, then every estimate the bank releases handed to each sink in one call
        (``on_estimates``: the same messages in the same order). False, with nothing done,
        where that does not apply (a channel whose bank failed, the power-quality stage on:
        its messages go out between a channel's estimate and the next, or a bank's tracks
        that are not its usual case); then each channel goes on its own."""
        if self.pq.enabled or not _every_track(tracks):
            return False
        live: Sequence[Track] = tracks  # type: ignore[assignment]  # (none is None)
        chs = [m.channel for m in members]
        made = self._in_one_call(
            lambda: bank_payloads(
                self,
                chs,
                [m.block for m in members],
                live,
                t_last,
                [(m.gap_blocks, m.restart, m.reset, m.jump) for m in members],
                readings.run_samples,
            )
        )
        if made is None:
            return False
        self._hold_and_hand_out(
            chs, made, readings.onset_latency_samples, t_last, log_time_ns, received_ns, members=members
        )
        return True

    def _in_one_call(
        self, write: Callable[[], list[tuple[bytes, bool, bool | None]] | None]
    ) -> list[tuple[bytes, bool, bool | None]] | None:
        """A bank's Estimates written in one call (``write``), or None where that does not apply
        or failed: nothing is changed by then, so each channel written on its own then isolates
        the fault (a bug, logged the first few times, not every frame)."""
        try:
            return write()
        except Exception:  # nothing changed by then: each channel on its own isolates it
            self._bank_estimate_failures += 1
            if self._bank_estimate_failures <= 5:
                log.exception("a bank's Estimates in one call failed; each channel's written on its own")
            return None

    def _usual_estimates(
        self,
        bank: UsualBank,
        frame: Frame,
        tracks: Sequence[Track],
        t_last: int,
        log_time_ns: int,
        received_ns: int | None,
        readings: PresenceBankReadings,
        lag: int = 0,
    ) -> bool:
        """:meth:`_bank_estimates` of a usual frame's bank (no gap, restart, reset or jump), from
        the layout's lists. The Estimates' bytes read of a block only what a frame's columns
        share (seq, sample count, time quality): the first column's block stands for all.
        ``lag``: every channel's estimate at the block's sample ``lag`` before its last."""
        block = frame.block(bank.columns[0])
        t_row = t_last if lag == 0 else _row_time(frame.t0_ns, frame.n_samples - 1 - lag, frame.sample_rate_hz)

        def write() -> list[tuple[bytes, bool, bool | None]] | None:
            if bank.writing is not None:  # the bank's usual case, from what its last frame left
                made = usual_bank_payloads(self, bank.writing, block, tracks, t_row, readings.run_samples, lag)
                if made is not None:
                    return made
            n = len(bank.channels)
            made = bank_payloads(
                self, bank.channels, [block] * n, tracks, t_last, _NO_GAPS * n, readings.run_samples, lag, t_row
            )
            bank.writing = None if made is None else bank_writing(self, bank.channels, block, tracks)
            return made

        made = self._in_one_call(write)
        if made is None:
            return False
        self._hold_and_hand_out(
            bank.channels,
            made,
            readings.onset_latency_samples,
            t_last,
            log_time_ns,
            received_ns,
            usual=(bank, frame),
            lag=lag,
            t_row=t_row,
        )
        return True

    def _hold_and_hand_out(
        self,
        chs: Sequence[Channel],
        made: list[tuple[bytes, bool, bool | None]],
        latencies: list[int],
        t_last: int,
        log_time_ns: int,
        received_ns: int | None,
        *,
        members: list[FrameMember] | None = None,
        usual: tuple[UsualBank, Frame] | None = None,
        lag: int = 0,
        t_row: int | None = None,
    ) -> None:
        """A bank's written Estimates (``made``: bytes, converged, valid) on: each channel's block
        accepted (``members``' own checks; ``usual``: a usual frame's, every channel the next
        block of its sequence, so without _accept's call and gap test a channel), each estimate
        held (:func:`hold_at_end`), then every estimate the bank releases handed to each sink in
        one call (``on_estimates``: the same messages in the same order). ``lag``, ``t_row``: the
        estimates are at the block's sample ``lag`` before its last, at time ``t_row``."""
        out: list[tuple[str, bytes]] = []  # (key, payload) of every estimate the bank releases, in order
        handed: list[Channel] = []
        arrival = log_time_ns if received_ns is None else received_ns
        holds = self._holds
        if usual is not None:
            frame = usual[1]
            seq, n = frame.seq, frame.n_samples
            next_t0 = frame.t0_ns + round(n * 1e9 / frame.sample_rate_hz)  # what _accept gives each column
        for i, (ch, (payload, converged, valid)) in enumerate(zip(chs, made, strict=True)):
            reset = False
            try:
                if members is not None:
                    m = members[i]
                    self._accept(ch, m.block, m.gap_blocks, m.restart, m.reset, m.jump)
                    reset = m.reset
                else:
                    ch.last_seq, ch.next_t0_ns = seq, next_t0
                    ch.blocks += 1
                    ch.samples += n
                if not holds:
                    ch.converged, released = converged, [payload]
                elif valid is None:  # written the general way: its bytes say whether it is valid
                    released = hold(ch, t_last, [(payload, converged, t_last if t_row is None else t_row)], reset)
                else:
                    released = hold_at_end(ch, payload, valid, converged, reset, latencies[i], lag)
            except Exception as exc:  # noqa: BLE001 (one channel's fault)
                self._forget_unborn(ch)
                block = members[i].block if members is not None else usual[1].block(usual[0].columns[i])  # type: ignore[index]
                self._fault(ch.key, block, ch, "estimate", exc, log_time_ns)
                continue
            out_key = self._out_key(ch)
            for p in released:
                out.append((out_key, p))
            ch.last_log_ns, ch.last_arrival_ns = log_time_ns, arrival
            handed.append(ch)
        for sink in self.sinks:
            sink.on_estimates(out, log_time_ns)
        self.counters.estimates += len(out)
        if received_ns is not None:
            latency = time.monotonic_ns() - received_ns
            for ch in handed:
                ch.last_latency_ns = latency

    def _frame_estimate(
        self,
        m: FrameMember,
        track: Track,
        log_time_ns: int,
        received_ns: int | None,
        presence_done: bool = False,
        lag: int = 0,
    ) -> None:
        """What :meth:`process` does after the estimator, for one channel of a frame (its
        presence detector already run by :meth:`_presence_bank` when ``presence_done``)."""
        channel, block = m.channel, m.block
        try:
            if not presence_done:
                self._presence(channel, block, m.reset)
            self._accept(channel, block, m.gap_blocks, m.restart, m.reset, m.jump)
            payloads = self._estimate_payloads(channel, block, track, (m.gap_blocks, m.restart, m.reset, m.jump), lag)
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
        # the samples as every kernel takes them, once here for the estimator, its bank, the
        # presence detector and the power-quality stage alike (``kernel_samples``: a float64
        # payload decodes to a read-only view, another numba type than a writable array)
        block.samples = kernel_samples(block.samples)
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
        out_key = self._out_key(channel)
        channel.last_log_ns = log_time_ns
        channel.last_arrival_ns = log_time_ns if received_ns is None else received_ns
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
        return sum(
            self._release(ch, log_time_ns)
            for ch in self.channels.values()
            if ch.held and (out_key is None or self._out_key(ch) == out_key)
        )

    def release_idle(self, now_ns: int, *, log_time_ns: int | None = None, waiting: Container[str] = ()) -> int:
        """A feed that pauses: the estimates of every channel whose last block arrived at least
        ``idle_release_s`` before ``now_ns`` (on the clock of :meth:`process`'s ``received_ns``;
        its log time where none was given) are released as at the input's end
        (:meth:`release_held`), so that a paused or finished stream's last estimates do not
        wait for a block that may never come. Their windows stay unconfirmed: not valid.

        Judged by arrival, not by when the last block was processed: a daemon working off a
        backlog processes each channel's blocks late and far apart, yet its feed never paused.
        A channel whose input key is in ``waiting`` (inputs received, not processed yet) is not
        idle: its next block is there to confirm what it holds. A replay meets released
        estimates as recorded ones with nothing produced yet and releases that channel there, so
        it reproduces them bit for bit. Returns how many were released (at ``log_time_ns``,
        ``now_ns`` when not given)."""
        idle_ns = round(self.config.idle_release_s * 1e9)
        at = now_ns if log_time_ns is None else log_time_ns
        return sum(
            self._release(ch, at)
            for ch in self.channels.values()
            if ch.held and now_ns - ch.last_arrival_ns >= idle_ns and (ch.source_key or ch.key) not in waiting
        )

    def take_over_held(self, published: Mapping[str, tuple[int, int]]) -> int:
        """A change of ownership, once the new term is set (:meth:`set_fencing`): the estimates
        the restored state holds were made under its previous owner's term. Those it was seen
        to publish (``published``: channel -> (seq, timestamp_ns) of its last estimate) are
        dropped, the rest carry this daemon's term from now on (:func:`sinewatch.core.hold.take_over`):
        an estimate never leaves under a term this daemon does not hold. Returns how many were dropped."""
        dropped = 0
        for ch in self.channels.values():
            if ch.held:
                seen = published.get(ch.name)
                dropped += take_over(ch, None if seen is None else seen[1], self.fencing_json)
        return self._held_dropped(dropped, "takeover: %d held estimate(s) the previous owner published dropped")

    def drop_held(self) -> int:
        """A deposed owner (or a standby stopping with a state restored ahead): what every
        channel holds is dropped, not released: it was made under a term this daemon no longer
        holds, and its successor publishes it. Returns how many."""
        dropped = 0
        for ch in self.channels.values():
            dropped += len(ch.held)
            ch.held.clear()
        return self._held_dropped(
            dropped, "%d held estimate(s) dropped: made under an ownership this daemon no longer holds"
        )

    def _held_dropped(self, dropped: int, message: str) -> int:
        """Count (and log, when any) ``dropped`` held estimates; returns it."""
        self.counters.held_dropped += dropped
        if dropped:
            log.warning(message, dropped)
        return dropped

    def _release(self, ch: Channel, log_time_ns: int) -> int:
        """Publish every estimate ``ch`` holds, in order; one that waited for the detector to
        confirm its window goes out not valid. Returns how many."""
        key = self._out_key(ch)
        n = len(ch.held)
        while ch.held:
            payload, _, window_start, _ = ch.held.popleft()
            payload = not_valid(payload) if window_start >= 0 else payload
            for sink in self.sinks:
                sink.on_estimate(key, payload, log_time_ns)
        ch.converged = False
        self.counters.estimates += n
        return n

    def _out_key(self, ch: Channel) -> str:
        """The key ``ch``'s estimates are published on (kept on the channel once made)."""
        if ch.out_key is None:
            ch.out_key = f"{self.config.keys.estimates_prefix}/{ch.name}"
        return ch.out_key

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
        self, ch: Channel, block: Block, track: Track, flags: tuple[int, bool, bool, bool], lag: int = 0
    ) -> list[bytes]:
        """One Estimate at the block's sample ``lag`` before its last (validity rules version 6:
        :meth:`_estimate_and_detect`; else its last); or, for an estimator that reports on a
        time grid, one per report the block completed (zero, one or several), at its time.
        ``flags``: the block's gap blocks, restart, reset and time jump. With ``hold_estimates``
        (on by default) they are held back (:func:`sinewatch.core.hold.hold`) and what this
        block releases is returned."""
        gap_blocks, restart, reset, jump = flags
        grid = track.reports
        t_last = block.t0_ns + round((block.n_samples - 1) * 1e9 / block.sample_rate_hz)
        made: list[tuple[bytes, bool, int]] = []  # payload, converged, timestamp
        if grid is None:
            t_row = t_last if lag == 0 else _row_time(block.t0_ns, block.n_samples - 1 - lag, block.sample_rate_hz)
            payload, converged = self._estimate_payload(
                ch, block, track, t_row, t_last, gap_blocks, restart, reset, jump
            )
            made.append((payload, converged, t_row))
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
        return hold(ch, t_last, made, reset)

    # An estimate's bytes from this pipeline's format and fencing (the function takes the
    # pipeline as its settings: a method, so that a test's subclass may compare each one).
    _estimate_payload = estimate_payload

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


def _key_matches(expr: str, key: str) -> bool:
    return bool(zenoh.KeyExpr(expr).includes(zenoh.KeyExpr(key)))


def _is_power_of_ten(n: int) -> bool:
    while n >= 10 and n % 10 == 0:
        n //= 10
    return n == 1


_NO_GAPS = [(0, False, False, False)]  # a usual frame's channel: no gap, restart, reset or time jump


def _every_track(tracks: Sequence[Track | None]) -> bool:
    """Whether no channel of a bank lost its block (a bank's own Tracks, unread, hold none)."""
    return isinstance(tracks, ColumnTracks) or all(track is not None for track in tracks)


def _not_grid(est: Estimator) -> bool:
    """Whether ``est`` reports at a block's samples, not on a time grid of its own (pmu's)."""
    return getattr(est, "lookahead_samples", None) is None


def _row_time(t0_ns: int, row: int, sample_rate_hz: float) -> int:
    """The time of a block's sample ``row`` (its last's is reckoned so: ``t_last``)."""
    return t0_ns + round(row * 1e9 / sample_rate_hz)


def _all_finite_2d(x: np.ndarray) -> bool:
    """Whether every value of a frame is finite (the usual case: one pass, no per-column work)."""
    return bool(np.isfinite(x.reshape(-1) if x.flags.c_contiguous else x).all())


def sanitize_log_time(previous: int, now: int) -> int:
    """Strictly increasing log times, even if the clock stalls or steps back."""
    return now if now > previous else previous + 1


# the names other modules and tests import from here (the pipeline's public face)
__all__ = [
    "Channel",
    "GuardedSink",
    "NullSink",
    "Pipeline",
    "PipelineCounters",
    "ResumePoint",
    "Sink",
    "estimate_model",
    "sanitize_log_time",
]
