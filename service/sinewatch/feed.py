"""The simulated feed: scenarios streamed as SampleBlocks through the client library.

Used by ``sinewatch feed``, ``sinewatch demo`` and ``sinewatch bench e2e``. Each channel
reads its own seeded stream of a scenario from the library (:mod:`sinewatch.scenarios`,
the one description of the signal, its truth, its transport faults and the estimator it
was written for), so a feed is reproducible. Real-time pacing waits
on an Event until each block's due time (no busy loop); ``realtime=False`` publishes as
fast as the transport accepts (BLOCK congestion control makes that the daemon's pace).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sinewatch import scenarios
from sinewatch.clients.publisher import BlockPublisher
from sinewatch.scenarios import Scenario, ScenarioStream, Truth
from sinewatch.schemas.config import EstimatorRule


@dataclass
class FeedChannel:
    channel: str
    scenario: Scenario
    stream: ScenarioStream
    blocks: int = 0
    last_seq: int = -1
    last_truth: Truth | None = None
    faults_injected: dict[str, int] = field(default_factory=dict)


def make_channels(
    names: list[str], copies: int = 1, seed: int = 0, prefix: str = "sim", **overrides: Any
) -> list[FeedChannel]:
    """One channel per scenario name (``copies`` of each, with different seeds)."""
    out: list[FeedChannel] = []
    for i, name in enumerate(names):
        for c in range(copies):
            sc = scenarios.get(name, **overrides)
            channel = f"{prefix}/{name}" if copies == 1 else f"{prefix}/{name}/{c}"
            out.append(FeedChannel(channel, sc, sc.stream(seed + 1000 * i + c)))
    return out


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
    def __init__(
        self, publisher: BlockPublisher, channels: list[FeedChannel], *, block_size: int = 1000, realtime: bool = True
    ) -> None:
        self.publisher = publisher
        self.channels = channels
        self.block_size = block_size
        self.realtime = realtime
        self.stop = threading.Event()

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
            for ch in self.channels:
                sent += self._publish(ch)
                if on_block is not None:
                    on_block(ch)
        return sent

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
