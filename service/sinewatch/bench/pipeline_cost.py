"""``sinewatch bench pipeline``: the CPU cost of one block through the pipeline, in process.

N channels (default 200) of float32 binary SampleBlocks (a 50 Hz sine with noise, seeded)
go through :meth:`sinewatch.pipeline.Pipeline.process` with a null sink, once with
recording off and once with an MCAP recorder (the config's compression and chunk size, to a
temporary directory) beside it; no transport, so what is measured is the per-block cost of
the pipeline itself, which bounds what one core sustains whatever the intake.

The same blocks are also taken through each step alone, to break the cost down:

* ``estimator``: the channel estimator's ``update`` (``last_only``) on decoded blocks: the
  baseline, measured in the same run; every other figure is also given as a ratio to it;
* ``decode``: the pipeline's decode and limits checks of the raw payload;
* ``presence``: the signal-presence detector (``diagnostics.valid``);
* ``encode``: the Estimate's JSON bytes from the estimator's track;
* ``recorder``: the MCAP recorder's ``on_input`` and ``on_estimate`` for one block;
* ``rest``: the pipeline's cost less the steps above (sequence checks, dispatch to the
  sinks, counters).

Each figure is the median over ``--repeats`` of ``--rounds`` blocks per channel, microseconds
per block (one block = one channel's ``--block`` samples).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from rich.table import Table

from sinewatch.console import make_console, print_table
from sinewatch.estimators import get as get_estimator
from sinewatch.pipeline import Channel, NullSink, Pipeline
from sinewatch.recorder import McapRecorder
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import EstimatorRule, RecordingSection, SinewatchConfig

STEPS = ("estimator", "decode", "presence", "encode", "recorder")


def _params(estimator: str) -> dict[str, Any]:
    if estimator == "ges-kalman":
        from sinewatch.scenarios.demo import KALMAN_10K

        return KALMAN_10K
    return {}


class Feed:
    """Float32 binary blocks of ``channels`` channels, sequence numbers running on across
    calls, so that every measurement sees fresh, in-order blocks."""

    def __init__(self, channels: int, block: int, rate_hz: float, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.names = [f"bench/c{i:04d}" for i in range(channels)]
        self.block, self.rate_hz = block, rate_hz
        t = np.arange(block * 8) / rate_hz
        # eight blocks of signal per channel, reused cyclically (the estimator does not care)
        self.signals = [
            (np.sin(2 * np.pi * 50.0 * t + rng.uniform(0, 2 * np.pi)) + 0.01 * rng.standard_normal(t.size)).astype(
                np.float32
            )
            for _ in range(channels)
        ]
        self.seq = 0
        self.step_ns = round(block * 1e9 / rate_hz)

    def rounds(self, n: int) -> list[list[tuple[str, bytes, Block]]]:
        """``n`` rounds of one block per channel: (key, payload, decoded block)."""
        out = []
        for _ in range(n):
            seq, k = self.seq, self.seq % 8
            self.seq += 1
            row = []
            for name, sig in zip(self.names, self.signals, strict=True):
                blk = Block(name, seq, 1_700_000_000_000_000_000 + seq * self.step_ns, self.rate_hz, sig[k * self.block : (k + 1) * self.block])
                payload = encode_block_binary(blk, "float32")
                blk.samples = np.frombuffer(payload, dtype="<f4", offset=len(payload) - 4 * self.block)
                row.append((f"sinewatch/in/{name}", payload, blk))
            out.append(row)
        return out


def _measure(feed: Feed, rounds: int, repeats: int, step: Callable[[list[list[tuple[str, bytes, Block]]]], None]) -> float:
    """Median microseconds per block of ``step`` over ``repeats`` batches of ``rounds`` rounds."""
    times = []
    for _ in range(repeats):
        batch = feed.rounds(rounds)
        t0 = time.perf_counter()
        step(batch)
        times.append((time.perf_counter() - t0) / (rounds * len(feed.names)) * 1e6)
    return statistics.median(times)


def _config(args: argparse.Namespace, directory: Path) -> SinewatchConfig:
    return SinewatchConfig(
        daemon_id="bench",
        rules=[EstimatorRule(match="sinewatch/in/**", estimator=args.estimator, params=_params(args.estimator))],
        recording=RecordingSection(directory=directory, compression=args.compression),
    )


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Every figure of the bench, as a dict (what ``--json`` writes)."""
    with tempfile.TemporaryDirectory(prefix="sinewatch-bench-pipeline-") as tmp:
        config = _config(args, Path(tmp))
        feed = Feed(args.channels, args.block, args.rate)
        us: dict[str, float] = {}

        # the pipelines first: they also warm up (compile, caches) what the steps use
        off = Pipeline(config, [NullSink()])
        recorder = McapRecorder(config)
        on = Pipeline(config, [NullSink(), recorder])
        for name, pipe in (("pipeline_off", off), ("pipeline_on", on)):

            def run(batch: list[list[tuple[str, bytes, Block]]], pipe: Pipeline = pipe) -> None:
                process = pipe.process
                for row in batch:
                    for key, payload, blk in row:
                        process(key, payload, BLOCK_BINARY_ENCODING, blk.t0_ns)

            run(feed.rounds(2))  # warm-up
            us[name] = _measure(feed, args.rounds, args.repeats, run)
        on.close_sinks()
        assert off.counters.errors == 0 and on.counters.errors == 0, (off.counters, on.counters)

        cls = get_estimator(args.estimator)
        channels = {
            name: Channel(name, f"sinewatch/in/{name}", cls(args.rate, _params(args.estimator)), args.rate)
            for name in feed.names
        }
        tracks: dict[str, Any] = {}

        def estimator(batch: list[list[tuple[str, bytes, Block]]]) -> None:
            for row in batch:
                for _key, _payload, blk in row:
                    tracks[blk.channel] = channels[blk.channel].estimator.update(
                        blk.samples, last_only=True, t0_ns=blk.t0_ns
                    )

        def decode(batch: list[list[tuple[str, bytes, Block]]]) -> None:
            dec = off._decode
            for row in batch:
                for _key, payload, _blk in row:
                    dec(payload, BLOCK_BINARY_ENCODING)

        def presence(batch: list[list[tuple[str, bytes, Block]]]) -> None:
            pres = Pipeline._presence
            for row in batch:
                for _key, _payload, blk in row:
                    pres(channels[blk.channel], blk, False)

        with_estimate: list[bytes | None] = [None]

        def record(batch: list[list[tuple[str, bytes, Block]]]) -> None:
            est = with_estimate[0]
            assert est is not None
            on_input, on_estimate = rec.on_input, rec.on_estimate
            for row in batch:
                for key, payload, blk in row:
                    on_input(key, payload, BLOCK_BINARY_ENCODING, blk.t0_ns)
                    on_estimate(key.replace("/in/", "/est/"), est, blk.t0_ns)

        estimator(feed.rounds(2))
        us["estimator"] = _measure(feed, args.rounds, args.repeats, estimator)
        us["decode"] = _measure(feed, args.rounds, args.repeats, decode)
        presence(feed.rounds(1))
        us["presence"] = _measure(feed, args.rounds, args.repeats, presence)
        sample = feed.rounds(1)
        estimator(sample)
        blk0 = sample[0][0][2]
        with_estimate[0] = on._estimate_payloads(channels[blk0.channel], blk0, tracks[blk0.channel], 0, False, False)[0]

        def encode_same(batch: list[list[tuple[str, bytes, Block]]]) -> None:
            # the tracks of the last estimator batch, encoded for the blocks of this one
            payloads = on._estimate_payloads
            for row in batch:
                for _key, _payload, blk in row:
                    payloads(channels[blk.channel], blk, tracks[blk.channel], 0, False, False)

        us["encode"] = _measure(feed, args.rounds, args.repeats, encode_same)
        rec = McapRecorder(_config(args, Path(tmp) / "steps"))
        record(feed.rounds(1))
        us["recorder"] = _measure(feed, args.rounds, args.repeats, record)
        rec.close()

    base = us["estimator"]
    outside_on = us["pipeline_on"] - base
    outside_off = us["pipeline_off"] - base
    us["rest_on"] = us["pipeline_on"] - sum(us[s] for s in STEPS)
    us["rest_off"] = us["pipeline_off"] - sum(us[s] for s in STEPS if s != "recorder")
    return {
        "channels": args.channels,
        "block": args.block,
        "rate_hz": args.rate,
        "estimator": args.estimator,
        "compression": args.compression,
        "rounds": args.rounds,
        "repeats": args.repeats,
        "us_per_block": us,
        "ratio_to_estimator": {k: v / base for k, v in us.items()},
        "outside_estimator_us": {"recording_on": outside_on, "recording_off": outside_off},
        "blocks_per_s_per_core": {"recording_on": 1e6 / us["pipeline_on"], "recording_off": 1e6 / us["pipeline_off"]},
        "samples_per_s_per_core": {
            "recording_on": 1e6 / us["pipeline_on"] * args.block,
            "recording_off": 1e6 / us["pipeline_off"] * args.block,
        },
    }


def _rows(result: dict[str, Any]) -> Iterator[tuple[str, float, float]]:
    us, ratio = result["us_per_block"], result["ratio_to_estimator"]
    for name in ("pipeline_on", "pipeline_off", *STEPS, "rest_on", "rest_off"):
        yield name, us[name], ratio[name]


def run(args: argparse.Namespace) -> int:
    console = make_console()
    console.print(
        f"{args.channels} channels, {args.estimator}, {args.block}-sample float32 blocks at {args.rate:g} Hz, "
        f"{args.rounds} blocks per channel x {args.repeats} repeats ..."
    )
    result = measure(args)
    table = Table(title="pipeline cost per block (median; ratio to the estimator's update alone)")
    table.add_column("step")
    table.add_column("us/block", justify="right")
    table.add_column("x estimator", justify="right")
    for name, value, ratio in _rows(result):
        table.add_row(name, f"{value:.1f}", f"{ratio:.2f}")
    print_table(console, table)
    for mode in ("recording_on", "recording_off"):
        console.print(
            f"{mode.replace('_', ' ')}: {result['blocks_per_s_per_core'][mode]:,.0f} blocks/s per core "
            f"({result['samples_per_s_per_core'][mode] / 1e6:.2f} M samples/s), "
            f"{result['outside_estimator_us'][mode]:.1f} us per block outside the estimator"
        )
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    return 0


__all__ = ["measure", "run"]
