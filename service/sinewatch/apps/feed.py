"""The simulated feed: scenarios streamed as SampleBlocks through the client library.

Used by ``sinewatch feed``, ``sinewatch demo`` and ``sinewatch bench e2e``. Each channel
reads its own seeded stream of a scenario from the library (:mod:`sinewatch.scenarios`,
the one description of the signal, its truth, its transport faults and the estimator it
was written for), so a feed is reproducible. Real-time pacing waits
on an Event until each block's due time (no busy loop); ``realtime=False`` publishes as
fast as the transport accepts (BLOCK congestion control makes that the daemon's pace).

The power-quality scenarios (:mod:`sinewatch.scenarios.power_quality_iec`, e.g.
``pq-unbalance-50hz-u2-2pct-harmonics``) are fed too: a three-phase one as three channels
``PREFIX/NAME/a``, ``/b``, ``/c`` (``PREFIX/NAME/COPY/a`` with copies), cut from one
seeded stream so the phases share their samples' times and block boundaries, as a
three-phase group expects (``[[power_quality.groups]]``); a one-phase one as one channel.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from sinewatch import scenarios
from sinewatch.clients.publisher import BlockPublisher
from sinewatch.core.comtrade_file import ComtradeRecord, interleaved_blocks, interleaved_frames
from sinewatch.scenarios import Scenario, ScenarioStream, Truth
from sinewatch.scenarios.power_quality_iec import get_pq, pq_names
from sinewatch.schemas.codec import Block
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.frame import Frame


class Readable(Protocol):
    def read(self, n: int) -> tuple[np.ndarray, Truth]: ...


@dataclass
class FeedChannel:
    channel: str
    scenario: Scenario
    stream: Readable  # a ScenarioStream, or one phase of a multi-phase one
    blocks: int = 0
    last_seq: int = -1
    last_truth: Truth | None = None
    faults_injected: dict[str, int] = field(default_factory=dict)


def make_channels(
    names: list[str], copies: int = 1, seed: int = 0, prefix: str = "sim", **overrides: Any
) -> list[FeedChannel]:
    """One channel per scenario name (``copies`` of each, with different seeds)."""
    out: list[FeedChannel] = []
    pq = set(pq_names())
    for i, name in enumerate(names):
        for c in range(copies):
            channel = f"{prefix}/{name}" if copies == 1 else f"{prefix}/{name}/{c}"
            if name in pq:
                out.extend(_phase_channels(channel, get_pq(name, **overrides), seed + 1000 * i + c))
                continue
            sc = scenarios.get(name, **overrides)
            out.append(FeedChannel(channel, sc, sc.stream(seed + 1000 * i + c)))
    return out


def _phase_channels(channel: str, sc: Scenario, seed: int) -> list[FeedChannel]:
    """The phases of a multi-phase scenario as channels CHANNEL/a, /b, /c that read one
    stream: the first phase to ask for a block reads it, the others take their column."""
    shared = _SharedStream(sc.stream(seed))
    n = int(getattr(sc, "n_phases", 1))
    if n == 1:
        return [FeedChannel(channel, sc, shared.stream)]
    return [FeedChannel(f"{channel}/{'abcdefghijklmnop'[p]}", sc, _PhaseStream(shared, p)) for p in range(n)]


class _SharedStream:
    def __init__(self, stream: ScenarioStream) -> None:
        self.stream = stream
        self._block: tuple[np.ndarray, Truth] | None = None
        self._taken: set[int] = set()

    def read(self, phase: int, n: int) -> tuple[np.ndarray, Truth]:
        if self._block is None or phase in self._taken or self._block[0].shape[0] != n:
            self._block = self.stream.read(n)
            self._taken = set()
        self._taken.add(phase)
        samples, truth = self._block
        return samples[:, phase], truth


class _PhaseStream:
    """One column of a shared multi-phase stream (what FeedChannel.stream needs: ``read``)."""

    def __init__(self, shared: _SharedStream, phase: int) -> None:
        self._shared = shared
        self._phase = phase

    def read(self, n: int) -> tuple[np.ndarray, Truth]:
        return self._shared.read(self._phase, n)


def rules_for(channels: list[FeedChannel], key_prefix: str = "sinewatch/in") -> list[EstimatorRule]:
    """Daemon rules that serve each channel with the estimator its scenario was written
    for (``suggested_estimator`` with ``suggested_params``)."""
    return [
        EstimatorRule(
            match=f"{key_prefix}/{ch.channel}",
            estimator=ch.scenario.suggested_estimator,
            params=ch.scenario.suggested_params,
        )
        for ch in channels
    ]


class Feed:
    """Publishes its channels' blocks round by round; with ``frame_channels`` > 1, the
    channels (consecutive ones of one sample rate) go as SampleFrames of that many channels,
    named ``<prefix>-f<k>`` where ``prefix`` is the first part of their names.

    In frames, a scenario's transport faults stay per channel: ``nan`` puts the NaN in the
    channel's column, ``drop`` leaves the channel out of that frame (the channel set
    changes; the daemon flags the gap on the channel's next estimate), ``duplicate`` is
    not injected (a frame cannot repeat one channel) and is not counted."""

    def __init__(
        self,
        publisher: BlockPublisher,
        channels: list[FeedChannel],
        *,
        block_size: int = 1000,
        realtime: bool = True,
        frame_channels: int = 1,
    ) -> None:
        self.publisher = publisher
        self.channels = channels
        self.block_size = block_size
        self.realtime = realtime
        self.stop = threading.Event()
        self.frames = frame_groups(channels, frame_channels) if frame_channels > 1 else []

    def run(self, duration_s: float, on_block: Callable[[FeedChannel], None] | None = None) -> int:
        """Publish until ``duration_s`` of signal is sent (or ``stop`` is set); return the
        number of blocks published. ``block_size`` counts samples at the first channel's
        rate; a channel at another rate gets blocks of the same duration."""
        if not self.channels:
            return 0
        fs = self.channels[0].scenario.sample_rate_hz
        self._sizes = {id(ch): max(1, round(self.block_size * ch.scenario.sample_rate_hz / fs)) for ch in self.channels}
        rounds = round(duration_s * fs / self.block_size)
        start = time.monotonic()
        sent = 0
        for r in range(rounds):
            if self.realtime:
                due = start + r * self.block_size / fs
                if self.stop.wait(max(0.0, due - time.monotonic())):
                    break
            elif self.stop.is_set():
                break
            if self.frames:
                for name, members in self.frames:
                    sent += self._publish_frame(name, members)
                    if on_block is not None:
                        for ch in members:
                            on_block(ch)
                continue
            for ch in self.channels:
                sent += self._publish(ch)
                if on_block is not None:
                    on_block(ch)
        return sent

    def _publish_frame(self, name: str, members: list[FeedChannel]) -> int:
        """One frame of ``members`` (those not dropped this round); 1 if it went out."""
        names, columns = [], []
        for ch in members:
            samples, truth = ch.stream.read(self._sizes[id(ch)])
            ch.last_truth = truth.last()
            fault = ch.scenario.faults.action(ch.blocks)
            ch.blocks += 1
            if fault == "nan":
                samples = np.array(samples, copy=True)
                samples.flat[len(samples) // 2] = np.nan
            if fault in ("nan", "drop"):
                ch.faults_injected[fault] = ch.faults_injected.get(fault, 0) + 1
            if fault == "drop":
                continue
            names.append(ch.channel)
            columns.append(samples)
        fs = members[0].scenario.sample_rate_hz
        if not names:  # every channel dropped: the frame is not sent (its seq and time are spent)
            self.publisher.frame(name, [members[0].channel], np.zeros((self._sizes[id(members[0])], 1)), fs)
            return 0
        frame = self.publisher.frame(name, names, np.stack(columns, axis=1), fs)
        for ch in members:
            ch.last_seq = frame.seq
        self.publisher.publish_frame_raw(name, self.publisher.encode_frame(frame))
        return 1

    def _publish(self, ch: FeedChannel) -> int:
        samples, truth = ch.stream.read(self._sizes[id(ch)])
        ch.last_truth = truth.last()
        fault = ch.scenario.faults.action(ch.blocks)
        ch.blocks += 1
        fs = ch.scenario.sample_rate_hz
        if fault == "nan":
            samples = np.array(samples, copy=True)
            samples.flat[len(samples) // 2] = np.nan
        block = self.publisher.block(ch.channel, samples, fs)
        ch.last_seq = block.seq
        if fault:
            ch.faults_injected[fault] = ch.faults_injected.get(fault, 0) + 1
        if fault == "drop":
            return 0
        payload = self.publisher.encode(block)
        self.publisher.publish_raw(ch.channel, payload)
        if fault == "duplicate":
            self.publisher.publish_raw(ch.channel, payload)
            return 2
        return 1


def frame_groups(channels: list[FeedChannel], per_frame: int) -> list[tuple[str, list[FeedChannel]]]:
    """Consecutive channels of one sample rate, ``per_frame`` at a time, each group with its
    frame's name: ``<first part of the first channel's name>-f<k>`` (one key chunk, beside
    its channels' keys)."""
    groups: list[tuple[str, list[FeedChannel]]] = []
    current: list[FeedChannel] = []
    for ch in channels:
        if current and (len(current) == per_frame or ch.scenario.sample_rate_hz != current[0].scenario.sample_rate_hz):
            groups.append(("", current))
            current = []
        current.append(ch)
    if current:
        groups.append(("", current))
    return [(f"{members[0].channel.split('/', 1)[0]}-f{k}", members) for k, (_, members) in enumerate(groups)]


def publish_comtrade(
    publisher: BlockPublisher,
    record: ComtradeRecord,
    *,
    block_size: int = 1000,
    realtime: bool = True,
    stop: threading.Event | None = None,
    frames: bool = False,
) -> int:
    """Publish every analog channel of a COMTRADE record in blocks of ``block_size``
    samples at its recorded rate, in the order of the blocks' times (channels interleaved as
    they were sampled); in real time, each block when its last sample is due. With
    ``frames`` the analog channels sampled together go as one SampleFrame per ``block_size``
    samples (:func:`sinewatch.core.comtrade_file.interleaved_frames`). Returns the number of
    messages published."""
    if frames:
        named = interleaved_frames(record, block_size)
        return _paced(
            [frame for _, frame in named],
            lambda k: publisher.publish_frame_raw(named[k][0], publisher.encode_frame(named[k][1])),
            realtime,
            stop,
        )
    blocks = interleaved_blocks(record, block_size)
    return _paced(
        blocks, lambda k: publisher.publish_raw(blocks[k].channel, publisher.encode(blocks[k])), realtime, stop
    )


def _paced(
    messages: Sequence[Block | Frame], send: Callable[[int], None], realtime: bool, stop: threading.Event | None
) -> int:
    """``send(k)`` for each message in turn; in real time each when its last sample is due,
    counted from the first message's time. Returns how many were sent before ``stop``."""
    stop = stop or threading.Event()
    if not messages:
        return 0
    first_ns = messages[0].t0_ns
    start = time.monotonic()
    sent = 0
    for k, msg in enumerate(messages):
        if realtime:
            end_s = (msg.t0_ns - first_ns) / 1e9 + msg.n_samples / msg.sample_rate_hz
            if stop.wait(max(0.0, start + end_s - time.monotonic())):
                break
        elif stop.is_set():
            break
        send(k)
        sent += 1
    return sent
