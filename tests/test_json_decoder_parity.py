"""The JSON decoder refuses what the binary decoder refuses, with the same typed error
(DecodeError, a ValueError; ErrorReport kind ``decode_error``) and a message saying what
was expected: a sample rate that is not a finite positive number (``Infinity``, ``1e309``,
``"inf"``, ``"50"``, ``true``), samples given as strings or booleans."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import make_config

from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.schemas.codec import BLOCK_JSON_ENCODING, Block, decode_block, encode_block_binary
from sinewatch.schemas.errors import DecodeError

GOOD = {"channel": "j/a", "seq": 0, "t0_ns": 0, "sample_rate_hz": 10000.0, "samples": [0.0, 0.5, 1.0, 0.5]}


def payload(**change) -> bytes:
    return json.dumps(GOOD | change).replace('"__INF__"', "Infinity").replace('"__BIG__"', "1e309").encode()


BAD = {
    "rate Infinity": payload(sample_rate_hz="__INF__"),
    "rate 1e309": payload(sample_rate_hz="__BIG__"),
    "rate string inf": payload(sample_rate_hz="inf"),
    "rate string number": payload(sample_rate_hz="10000"),
    "rate boolean": payload(sample_rate_hz=True),
    "samples strings": payload(samples=["0.0", "0.5", "1.0", "0.5"]),
    "samples booleans": payload(samples=[True, False, True, False]),
    "samples mixed": payload(samples=[0.0, "0.5", 1.0, 0.5]),
    "rows of strings": payload(samples=[["0.0", "1"], ["0.5", "1"]], columns=2),
    "rows of booleans": payload(samples=[[0.0, True], [0.5, False]], columns=2),
}


def test_the_good_payload_decodes():
    blk = decode_block(payload(), BLOCK_JSON_ENCODING)
    assert blk.sample_rate_hz == 10000.0 and np.array_equal(blk.samples, [0.0, 0.5, 1.0, 0.5])


@pytest.mark.parametrize("name", list(BAD))
def test_json_refuses_it_with_a_typed_error(name):
    with pytest.raises(DecodeError, match=r"JSON block: (sample_rate_hz|samples).*should be.*, got ") as exc:
        decode_block(BAD[name], BLOCK_JSON_ENCODING)
    assert isinstance(exc.value, ValueError)  # the expected thing and what came instead


@pytest.mark.parametrize("rate", [float("inf"), float("nan"), -1.0, 0.0])
def test_binary_refuses_the_same_rates(rate):
    with pytest.raises(DecodeError, match="sample_rate_hz: expected a finite value > 0"):
        decode_block(encode_block_binary(Block("j/a", 0, 0, rate, np.zeros(4))))


def test_in_the_pipeline_they_are_decode_errors_not_estimator_errors(tmp_path):
    class Keep(NullSink):
        def __init__(self) -> None:
            self.kinds: list[str] = []

        def on_error(self, key: str, data: bytes, log_time_ns: int) -> None:
            self.kinds.append(json.loads(data)["kind"])

    keep = Keep()
    pipeline = Pipeline(make_config(tmp_path), [keep])
    for i, p in enumerate(BAD.values()):
        pipeline.process("sinewatch/in/j/a", p, BLOCK_JSON_ENCODING, i)
    assert keep.kinds == ["decode_error"] * len(BAD)
    assert pipeline.channels == {}
