"""``sinewatch bench pipeline``: the CPU cost of one block through the pipeline, in process.

N channels (default 200) of float32 binary SampleBlocks (a 50 Hz sine with noise, seeded)
go through :meth:`sinewatch.core.pipeline.Pipeline.process` with a null sink, once with
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

With ``--frame-channels N`` (N > 1) the channels go as SampleFrames of N channels, the
daemon's frame path: ``estimator`` is then one :func:`~sinewatch.estimators.bank.update_bank`
call a frame, ``presence`` the detectors' bank (:func:`~sinewatch.estimators.presence.update_presence_bank`),
``encode`` the frame's Estimate bytes (one compiled call a frame from what the bank keeps between
frames, as the pipeline writes a usual frame's),
``hold`` each channel's accept and hold-back
(:func:`sinewatch.core.hold.hold_at_end`, on by default), ``recorder`` the frame's one input message
and its channels' estimates (one ``on_estimates`` call); ``channel_by_channel_off`` the
pipeline (recording off) with its per-frame steps turned off (:class:`ChannelByChannel`), beside
``pipeline_off`` in the same run; ``rest`` is then the per-channel checks, the grouping into banks
and the hand-out to the sinks.

CPU microseconds per block (one block = one channel's ``--block`` samples; the process's CPU
time, not wall time, so that other processes on the machine count less): each repeat takes
``--rounds`` fresh blocks per channel through every step in turn; a figure is the step's
fastest repeat (the least disturbed by other load on the machine), its median beside it.
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

from sinewatch.apps.console import make_console, print_table
from sinewatch.core.estimate_bytes import BankWriting, bank_payloads, bank_writing, usual_bank_payloads
from sinewatch.core.hold import hold_at_end
from sinewatch.core.pipeline import Channel, NullSink, Pipeline
from sinewatch.estimators import get as get_estimator
from sinewatch.estimators.bank import update_bank
from sinewatch.estimators.presence import PresenceBankReadings, read_presence_bank
from sinewatch.outputs.recorder import FastWriter, McapRecorder
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import EstimatorRule, RecordingSection, SinewatchConfig
from sinewatch.schemas.frame import FRAME_BINARY_ENCODING, Frame, decode_input, encode_frame_binary

STEPS = ("estimator", "decode", "presence", "encode", "recorder")
FRAME_STEPS = ("estimator", "decode", "presence", "encode", "hold", "recorder")


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
                blk = Block(
                    name,
                    seq,
                    1_700_000_000_000_000_000 + seq * self.step_ns,
                    self.rate_hz,
                    sig[k * self.block : (k + 1) * self.block],
                )
                payload = encode_block_binary(blk, "float32")
                blk.samples = np.frombuffer(payload, dtype="<f4", offset=len(payload) - 4 * self.block)
                row.append((f"sinewatch/in/{name}", payload, blk))
            out.append(row)
        return out


Batch = list[list[tuple[str, bytes, Block]]]


def _through(pipe: Pipeline, encoding: str) -> Callable[[Any], None]:
    """The step that takes a batch (rows of (key, payload, decoded input)) through ``pipe``,
    each input logged at its first sample's time."""

    def run(batch: Any) -> None:
        process = pipe.process
        for row in batch:
            for key, payload, item in row:
                process(key, payload, encoding, item.t0_ns)

    return run


class FrameFeed(Feed):
    """The same channels' signals as SampleFrames of ``per`` channels (float32, the layout
    of ``sinewatch bench e2e --frame-channels``): frame k on ``sinewatch/in/f<k>``, its
    channels' keys ``sinewatch/in/bench/c<i>``."""

    def __init__(self, channels: int, block: int, rate_hz: float, per: int, seed: int = 0) -> None:
        super().__init__(channels, block, rate_hz, seed)
        self.layout = [tuple(self.names[i : i + per]) for i in range(0, channels, per)]
        self.stacked = [np.stack(self.signals[i : i + per], axis=1) for i in range(0, channels, per)]

    def frames(self, n: int) -> list[list[tuple[str, bytes, Frame]]]:
        """``n`` rounds of one frame per group: (key, payload, decoded frame of the kernels' kind)."""
        out = []
        for _ in range(n):
            seq, k = self.seq, self.seq % 8
            self.seq += 1
            t0 = 1_700_000_000_000_000_000 + seq * self.step_ns
            row = []
            for f, (names, x) in enumerate(zip(self.layout, self.stacked, strict=True)):
                payload = encode_frame_binary(
                    Frame(names, seq, t0, self.rate_hz, x[k * self.block : (k + 1) * self.block]), "float32"
                )
                frame = decode_input(payload, FRAME_BINARY_ENCODING)
                assert isinstance(frame, Frame)
                frame.samples = np.ascontiguousarray(frame.samples, dtype=np.float64)
                row.append((f"sinewatch/in/f{f:04d}", payload, frame))
            out.append(row)
        return out


FrameBatch = list[list[tuple[str, bytes, Frame]]]


def _frame_steps(
    args: argparse.Namespace, directory: Path, feed: FrameFeed
) -> tuple[dict[str, Callable[[FrameBatch], None]], list[Any]]:
    """The frame path's steps (``--frame-channels``), each taking a batch of frames: each
    step on its own objects (estimators, detectors, channels, a recorder), fed the same frames."""
    config = _config(args, directory)
    off = Pipeline(config, [NullSink()])
    on = Pipeline(_config(args, directory / "pipeline"), [NullSink(), McapRecorder(config)])
    cls = get_estimator(args.estimator)
    params = _params(args.estimator)
    banks = [[cls(args.rate, params) for _ in names] for names in feed.layout]
    channels = {name: Channel(name, f"sinewatch/in/{name}", cls(args.rate, params), args.rate) for name in feed.names}
    detectors = [[channels[name].presence for name in names] for names in feed.layout]
    tracks: dict[str, Any] = {}  # by frame key: the bank's Tracks, as update_bank gives them
    readings: dict[str, PresenceBankReadings] = {}  # by frame key: what its detectors read
    estimates: dict[str, bytes] = {}
    written: dict[str, tuple[bool, bool | None]] = {}  # by channel: its estimate's converged and valid
    writings: dict[str, BankWriting | None] = {}  # by frame key: what its bank's Estimates keep
    step_recorder = McapRecorder(_config(args, directory / "steps"))
    no_gaps = [(0, False, False, False)] * max(len(names) for names in feed.layout)

    def estimator(batch: FrameBatch) -> None:
        for row in batch:
            for (key, _payload, frame), ests in zip(row, banks, strict=True):
                tracks[key] = update_bank(ests, frame.samples, last_only=True, t0_ns=frame.t0_ns)

    def decode(batch: FrameBatch) -> None:
        dec = off._decode
        for row in batch:
            for _key, payload, _frame in row:
                dec(payload, FRAME_BINARY_ENCODING)

    def presence(batch: FrameBatch) -> None:  # the channels' detectors: their runs are what encode reads
        for row in batch:
            for (key, _payload, frame), dets in zip(row, detectors, strict=True):
                read = read_presence_bank(dets, frame.samples, list(range(len(dets))))  # type: ignore[arg-type]
                assert read is not None
                readings[key] = read
                for name, run in zip(frame.channels, read.runs, strict=True):
                    channels[name].last_run = run

    def encode(batch: FrameBatch) -> None:  # the tracks of the estimator step on this batch, a frame in one call
        for row in batch:
            for key, _payload, frame in row:
                t_last = frame.t0_ns + round((frame.n_samples - 1) * 1e9 / frame.sample_rate_hz)
                chs = [channels[name] for name in frame.channels]
                block, runs = frame.block(0), readings[key].run_samples
                # as the pipeline writes a usual frame's: from what the bank keeps, once made
                kept = writings.get(key)
                made = None if kept is None else usual_bank_payloads(on, kept, block, tracks[key], t_last, runs)
                if made is None:
                    made = bank_payloads(on, chs, [block] * len(chs), tracks[key], t_last, no_gaps[: len(chs)], runs)
                    writings[key] = bank_writing(on, chs, block, tracks[key])
                assert made is not None
                estimates.update(zip(frame.channels, (payload for payload, _, _ in made), strict=True))
                written.update(zip(frame.channels, ((c, v) for _, c, v in made), strict=True))

    def hold_back(batch: FrameBatch) -> None:  # each channel's accept and hold of the encode step's estimate
        accept = on._accept
        for row in batch:
            for key, _payload, frame in row:
                latencies = readings[key].onset_latency_samples
                for c, name in enumerate(frame.channels):
                    ch = channels[name]
                    accept(ch, frame.block(c), 0, False, False)
                    converged, valid = written[name]
                    hold_at_end(ch, estimates[name], bool(valid), converged, False, latencies[c])

    def record(batch: FrameBatch) -> None:  # the frame, and its channels' estimates of the encode step
        on_input, on_estimates = step_recorder.on_input, step_recorder.on_estimates
        for row in batch:
            for key, payload, frame in row:
                on_input(key, payload, FRAME_BINARY_ENCODING, frame.t0_ns)
                on_estimates([(f"sinewatch/est/{name}", estimates[name]) for name in frame.channels], frame.t0_ns)

    steps = {
        "pipeline_on": _through(on, FRAME_BINARY_ENCODING),
        "pipeline_off": _through(off, FRAME_BINARY_ENCODING),
        # the frame path without its per-frame steps, recording off: what they save, in this run
        "channel_by_channel_off": _through(ChannelByChannel(config, [NullSink()]), FRAME_BINARY_ENCODING),
        "estimator": estimator,
        "decode": decode,
        "presence": presence,
        "encode": encode,
        "hold": hold_back,
        "recorder": record,
    }
    return steps, [on, off, step_recorder]


class ChannelByChannel(Pipeline):
    """The frame path as it was before its per-frame steps (``channel_by_channel_off``): each
    channel checked on its own (no usual frame), its Estimate written, held and handed to
    the sinks on its own (no bank's Estimates in one call): the same estimates, at their cost."""

    def _usual_frame(self, key: str, frame: Frame) -> None:
        return None

    def _bank_estimates(self, *args: Any, **kwargs: Any) -> bool:
        return False


def _config(args: argparse.Namespace, directory: Path) -> SinewatchConfig:
    return SinewatchConfig(
        daemon_id="bench",
        rules=[EstimatorRule(match="sinewatch/in/**", estimator=args.estimator, params=_params(args.estimator))],
        recording=RecordingSection(directory=directory, compression=args.compression),
    )


def _steps(
    args: argparse.Namespace, directory: Path, names: list[str]
) -> tuple[dict[str, Callable[[Batch], None]], list[Any]]:
    """Every measured step, by name, each taking a batch of blocks; and what to close after."""
    config = _config(args, directory)
    off = Pipeline(config, [NullSink()])
    recorder = McapRecorder(config)
    on = Pipeline(_config(args, directory / "pipeline"), [NullSink(), recorder])
    cls = get_estimator(args.estimator)
    channels = {
        name: Channel(name, f"sinewatch/in/{name}", cls(args.rate, _params(args.estimator)), args.rate)
        for name in names
    }
    tracks: dict[str, Any] = {}
    step_recorder = McapRecorder(_config(args, directory / "steps"))
    estimates: dict[str, bytes] = {}

    def estimator(batch: Batch) -> None:
        for row in batch:
            for _key, _payload, blk in row:
                tracks[blk.channel] = channels[blk.channel].estimator.update(
                    blk.samples, last_only=True, t0_ns=blk.t0_ns
                )

    def decode(batch: Batch) -> None:
        dec = off._decode
        for row in batch:
            for _key, payload, _blk in row:
                dec(payload, BLOCK_BINARY_ENCODING)

    def presence(batch: Batch) -> None:
        pres = Pipeline._presence
        for row in batch:
            for _key, _payload, blk in row:
                pres(channels[blk.channel], blk, False)

    def encode(batch: Batch) -> None:  # the tracks of the estimator step on this batch
        payload = on._estimate_payload  # one Estimate's bytes (holding it back, by default, is in "rest")
        for row in batch:
            for _key, _payload, blk in row:
                t_last = blk.t0_ns + round((blk.n_samples - 1) * 1e9 / blk.sample_rate_hz)
                estimates[blk.channel] = payload(
                    channels[blk.channel], blk, tracks[blk.channel], t_last, t_last, 0, False, False
                )[0]

    def record(batch: Batch) -> None:  # the input, and the channel's estimate of the encode step
        on_input, on_estimate = step_recorder.on_input, step_recorder.on_estimate
        for row in batch:
            for key, payload, blk in row:
                on_input(key, payload, BLOCK_BINARY_ENCODING, blk.t0_ns)
                on_estimate(key.replace("/in/", "/est/"), estimates[blk.channel], blk.t0_ns)

    steps = {
        "pipeline_on": _through(on, BLOCK_BINARY_ENCODING),
        "pipeline_off": _through(off, BLOCK_BINARY_ENCODING),
        "estimator": estimator,
        "decode": decode,
        "presence": presence,
        "encode": encode,
        "recorder": record,
    }
    return steps, [on, off, step_recorder]


def _recorder_of(item: Any) -> McapRecorder | None:
    """The MCAP recorder among a pipeline's sinks (or the recorder itself), if any."""
    if isinstance(item, McapRecorder):
        return item
    for sink in getattr(item, "sinks", ()):
        if isinstance(sink.sink, McapRecorder):
            return sink.sink
    return None


def _chunks_written(recorders: list[McapRecorder | None]) -> None:
    """Wait for each recorder's chunk in flight: the recorder compresses and writes a full chunk
    on a thread of its own (``FastWriter``) while the pipeline goes on, and the process's CPU
    time counts that thread, so a chunk finished near a step's end would be counted in whichever
    step ran next (the recorder step's in the next repeat's pipeline, recording on)."""
    for recorder in recorders:
        writer = None if recorder is None else recorder._writer
        if isinstance(writer, FastWriter):
            writer.wait()


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Every figure of the bench, as a dict (what ``--json`` writes).

    Each repeat takes a fresh batch of ``rounds`` blocks per channel through every step in
    turn (interleaved, so that a burst of load from elsewhere hits all steps alike); a step's
    figure is its fastest repeat (the least disturbed), its median is given beside it."""
    per = getattr(args, "frame_channels", 1)
    step_names = FRAME_STEPS if per > 1 else STEPS
    with tempfile.TemporaryDirectory(prefix="sinewatch-bench-pipeline-") as tmp:
        steps: dict[str, Callable[[Any], None]]
        if per > 1:
            frame_feed = FrameFeed(args.channels, args.block, args.rate, per)
            steps, to_close = _frame_steps(args, Path(tmp), frame_feed)
            make: Callable[[int], Any] = frame_feed.frames
        else:
            feed = Feed(args.channels, args.block, args.rate)
            steps, to_close = _steps(args, Path(tmp), feed.names)
            make = feed.rounds
        times: dict[str, list[float]] = {name: [] for name in steps}
        recorders = [_recorder_of(item) for item in to_close]
        for repeat in range(args.repeats + 1):  # the first is the warm-up (compile, caches)
            batch = make(args.rounds if repeat else 2)
            for name, step in steps.items():
                t0 = time.process_time()
                step(batch)
                _chunks_written(recorders)
                if repeat:
                    times[name].append((time.process_time() - t0) / (args.rounds * args.channels) * 1e6)
        on, off, step_recorder = to_close
        on.close_sinks()
        step_recorder.close()
        if on.counters.errors or off.counters.errors:
            raise RuntimeError(f"the bench's blocks were rejected: {on.counters.by_kind + off.counters.by_kind}")
    us = {name: min(t) for name, t in times.items()}
    median = {name: statistics.median(t) for name, t in times.items()}
    base = us["estimator"]
    us["rest_on"] = us["pipeline_on"] - sum(us[s] for s in step_names)
    us["rest_off"] = us["pipeline_off"] - sum(us[s] for s in step_names if s != "recorder")
    outside = {"recording_on": us["pipeline_on"] - base, "recording_off": us["pipeline_off"] - base}
    return {
        "channels": args.channels,
        "frame_channels": per,
        "block": args.block,
        "rate_hz": args.rate,
        "estimator": args.estimator,
        "compression": args.compression,
        "rounds": args.rounds,
        "repeats": args.repeats,
        "us_per_block": us,
        "us_per_block_median": median,
        "ns_per_sample": {k: 1e3 * v / args.block for k, v in us.items()},
        "ratio_to_estimator": {k: v / base for k, v in us.items()},
        "outside_estimator_us": outside,
        "outside_estimator_ratio": {k: v / base for k, v in outside.items()},
        "blocks_per_s_per_core": {"recording_on": 1e6 / us["pipeline_on"], "recording_off": 1e6 / us["pipeline_off"]},
        "samples_per_s_per_core": {
            "recording_on": 1e6 / us["pipeline_on"] * args.block,
            "recording_off": 1e6 / us["pipeline_off"] * args.block,
        },
    }


def _rows(result: dict[str, Any]) -> Iterator[tuple[str, float, float | None, float]]:
    us, median, ratio = result["us_per_block"], result["us_per_block_median"], result["ratio_to_estimator"]
    steps = FRAME_STEPS if result["frame_channels"] > 1 else STEPS
    extra = ("channel_by_channel_off",) if result["frame_channels"] > 1 else ()
    for name in ("pipeline_on", "pipeline_off", *extra, *steps, "rest_on", "rest_off"):
        yield name, us[name], median.get(name), ratio[name]


def run(args: argparse.Namespace) -> int:
    console = make_console()
    per = getattr(args, "frame_channels", 1)
    unit = f"frames of {per} channels" if per > 1 else "blocks"
    console.print(
        f"{args.channels} channels, {args.estimator}, {args.block}-sample float32 {unit} at {args.rate:g} Hz, "
        f"{args.rounds} blocks per channel x {args.repeats} repeats ..."
    )
    result = measure(args)
    table = Table(
        title="pipeline cost per channel's block (fastest repeat; ratio to the estimator alone)"
        + (f", frames of {per}" if per > 1 else "")
    )
    table.add_column("step")
    table.add_column("us/block", justify="right")
    table.add_column("median", justify="right")
    table.add_column("ns/sample", justify="right")
    table.add_column("x estimator", justify="right")
    for name, value, median, ratio in _rows(result):
        median_text = "" if median is None else f"{median:.1f}"
        table.add_row(name, f"{value:.1f}", median_text, f"{1e3 * value / args.block:.1f}", f"{ratio:.2f}")
    print_table(console, table)
    for mode in ("recording_on", "recording_off"):
        console.print(
            f"{mode.replace('_', ' ')}: {result['blocks_per_s_per_core'][mode]:,.0f} blocks/s per core "
            f"({result['samples_per_s_per_core'][mode] / 1e6:.2f} M samples/s), "
            f"{result['outside_estimator_us'][mode]:.1f} us per block outside the estimator "
            f"({result['outside_estimator_ratio'][mode]:.2f} x the estimator)"
        )
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    return 0


__all__ = ["measure", "run"]
