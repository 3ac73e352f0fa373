"""Replay reproduces what the daemon did with every input, whatever its Zenoh encoding and
whatever else came on the same key: a block whose encoding the daemon refused (an unknown
binary version), a JSON block and an unlabelled one between binary blocks, in a real MCAP
file written by the real recorder."""

from __future__ import annotations

import numpy as np
from conftest import FakeClock, make_config

from sinewatch.apps.cli import main
from sinewatch.core.pipeline import Pipeline
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.runtime.replay import replay
from sinewatch.schemas.codec import (
    BLOCK_BINARY_ENCODING,
    BLOCK_JSON_ENCODING,
    Block,
    encode_block_binary,
    encode_block_json,
)
from sinewatch.schemas.config import RecordingSection

KEY = "sinewatch/in/mixed/a"


def other(b: Block) -> bytes:
    """The block with other samples: had replay taken it where the daemon refused it, the
    estimates that follow would differ."""
    return encode_block_binary(Block(b.channel, b.seq, b.t0_ns, b.sample_rate_hz, 3.0 * b.samples + 1.0))


def blocks(n: int) -> list[Block]:
    rng = np.random.default_rng(7)
    t = np.arange(n * 400) / 10_000.0
    x = np.sin(2 * np.pi * 50.0 * t + 0.3) + 0.01 * rng.standard_normal(t.size)
    return [Block("mixed/a", i, i * 40_000_000, 10_000.0, x[i * 400 : (i + 1) * 400]) for i in range(n)]


def record(tmp_path, inputs):
    config = make_config(
        tmp_path, recording=RecordingSection(directory=tmp_path / "rec", rotate_seconds=None, rotate_bytes=None)
    )
    recorder = McapRecorder(config, snapshot=lambda: pipeline.snapshot(), clock=FakeClock())
    pipeline = Pipeline(config, [recorder])
    for t, (payload, encoding) in enumerate(inputs, start=1):
        pipeline.process(KEY, payload, encoding, t)
    pipeline.release_held(len(inputs) + 1)  # the input's end, as the daemon's drain
    recorder.close()
    return recorder.paths, pipeline


def test_a_refused_encoding_first_on_a_key_does_not_change_how_the_rest_replays(tmp_path):
    bs = blocks(6)
    poison = (other(bs[0]), "application/x-sinewatch-block;v=2")  # refused live
    good = [(encode_block_binary(b), BLOCK_BINARY_ENCODING) for b in bs]
    paths, pipeline = record(tmp_path, [poison, *good])
    assert pipeline.counters.estimates == 6 and pipeline.counters.errors == 1
    r = replay(paths)
    assert r.ok, [m.describe() for m in r.mismatches]
    assert r.matched == r.recorded_estimates == 6
    assert main(["replay", *map(str, paths), "--no-progress"]) == 0


def test_every_encoding_on_one_key_replays(tmp_path):
    """Binary, JSON, unlabelled (sniffed), and refused versions, interleaved on one key."""
    bs = blocks(8)
    inputs = [
        (encode_block_binary(bs[0]), BLOCK_BINARY_ENCODING),
        (encode_block_json(bs[1]), BLOCK_JSON_ENCODING),
        (other(bs[2]), "application/x-sinewatch-block;v=9"),  # refused
        (encode_block_binary(bs[2]), "zenoh/bytes"),  # sniffed: binary
        (encode_block_json(bs[3]), "zenoh/bytes"),  # sniffed: JSON
        (other(bs[4]), "application/json"),  # says JSON, is not: refused
        (encode_block_binary(bs[4]), BLOCK_BINARY_ENCODING),
        (encode_block_json(bs[5]), "text/json"),
        (other(bs[6]), "application/x-sinewatch-block;v=2"),  # refused
        (encode_block_binary(bs[6]), BLOCK_BINARY_ENCODING),
        (encode_block_binary(bs[7]), BLOCK_BINARY_ENCODING),
    ]
    paths, pipeline = record(tmp_path, inputs)
    assert pipeline.counters.estimates == 8 and pipeline.counters.errors == 3
    r = replay(paths)
    assert r.ok, [m.describe() for m in r.mismatches]
    assert r.matched == r.recorded_estimates == 8
    # and replay refused exactly what the daemon refused
    assert r.recorded_errors == r.produced_errors == 3
