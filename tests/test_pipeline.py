"""Pipeline details that need no transport."""

from __future__ import annotations

import json
import logging

from conftest import make_config

from sinewatch.pipeline import NullSink, Pipeline


class Collect(NullSink):
    def __init__(self):
        self.errors = []

    def on_error(self, key, payload, log_time_ns):
        self.errors.append(json.loads(payload))


def test_a_flood_of_bad_input_is_counted_in_full_but_logged_sparingly(tmp_path, caplog):
    sink = Collect()
    pipeline = Pipeline(make_config(tmp_path), [sink])
    with caplog.at_level(logging.WARNING, logger="sinewatch.pipeline"):
        for i in range(2000):
            pipeline.process("sinewatch/in/x", b"\x00garbage", "", i)
    assert len(sink.errors) == 2000 and sink.errors[-1]["count"] == 2000
    assert pipeline.counters.by_kind["decode_error"] == 2000
    logged = [r for r in caplog.records if "rejected input" in r.getMessage()]
    assert len(logged) == 5 + 3  # the first five, then the 10th, 100th and 1000th
    assert "[1000 so far on this key" in logged[-1].getMessage()
