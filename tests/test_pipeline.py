"""Pipeline details that need no transport."""

from __future__ import annotations

import json
import logging

from conftest import make_config

from sinewatch.core.pipeline import NullSink, Pipeline


class Collect(NullSink):
    def __init__(self):
        self.errors = []

    def on_error(self, key, payload, log_time_ns):
        self.errors.append(json.loads(payload))


def test_a_flood_of_bad_input_is_counted_in_full_but_logged_sparingly(tmp_path, caplog):
    sink = Collect()
    pipeline = Pipeline(make_config(tmp_path), [sink])
    with caplog.at_level(logging.WARNING, logger="sinewatch.core.pipeline"):
        for i in range(2000):
            pipeline.process("sinewatch/in/x", b"\x00garbage", "", i)
    assert len(sink.errors) == 2000 and sink.errors[-1]["count"] == 2000
    assert pipeline.counters.by_kind["decode_error"] == 2000
    logged = [r for r in caplog.records if "rejected input" in r.getMessage()]
    assert len(logged) == 5 + 3  # the first five, then the 10th, 100th and 1000th
    assert "[1000 so far on this key" in logged[-1].getMessage()


class Keep(NullSink):
    def __init__(self):
        self.estimates, self.errors = [], []

    def on_estimate(self, key, payload, log_time_ns):
        self.estimates.append(json.loads(payload))

    def on_error(self, key, payload, log_time_ns):
        self.errors.append(json.loads(payload))


def _send(pipeline, seq, t0_ns, n=100, fs=10_000.0):
    import numpy as np

    from sinewatch.schemas.codec import Block, encode_block_binary

    x = np.sin(2 * np.pi * 50 * (t0_ns / 1e9 + np.arange(n) / fs))
    pipeline.process("sinewatch/in/r", encode_block_binary(Block("r", seq, t0_ns, fs, x)), "", t0_ns)


def test_a_sender_that_restarts_its_count_is_accepted_and_flagged(tmp_path):
    sink = Keep()
    pipeline = Pipeline(make_config(tmp_path, hold_estimates=True), [sink])  # estimates held back
    step = 10_000_000  # 100 samples at 10 kHz
    for seq in range(5):
        _send(pipeline, seq, seq * step)
    _send(pipeline, 3, 3 * step)  # seq back, time back: a replayed old block
    _send(pipeline, 0, 9 * step)  # seq back to 0, time forward: the gateway restarted
    _send(pipeline, 1, 10 * step)
    # estimates wait for the presence detector's onset latency: after a reset its quarter-cycle
    # test is not armed for its first cycle, so the restarted block 0 waits 2 cycles (400
    # samples), the blocks after it a third of a cycle (61 samples): four come out with
    # three more blocks, in order
    assert [e["seq"] for e in sink.estimates] == [0, 1, 2, 3, 4]
    assert not any(e["diagnostics"]["valid"] for e in sink.estimates[2:])  # unconfirmed at the restart
    for seq in (2, 3, 4):
        _send(pipeline, seq, (9 + seq) * step)
    assert len(sink.estimates) == 9
    assert [e["kind"] for e in sink.errors] == ["out_of_order"]
    d = [e["diagnostics"] for e in sink.estimates]
    assert [e["seq"] for e in sink.estimates] == [0, 1, 2, 3, 4, 0, 1, 2, 3]
    assert [x["restart"] for x in d] == [False] * 5 + [True, False, False, False]
    assert d[5]["gap"] and d[5]["gap_blocks"] == 0 and not d[6]["gap"]
