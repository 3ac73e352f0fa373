"""One large JSON block does not stall the other channels: a JSON block is refused before
it is parsed when it is larger than ``limits.max_json_payload_bytes`` (256 KiB by default,
about 13,000 samples: parsing JSON costs the event loop 50-180 ns a byte, where a binary
block costs nothing to decode), with the typed error ``oversized_block``."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import TIMEOUT, make_config, run_daemon
from conftest import KeepSink as Keep

from sinewatch.clients import BlockPublisher, connect, subscribe_estimates
from sinewatch.core.pipeline import Pipeline
from sinewatch.schemas.codec import (
    BLOCK_BINARY_ENCODING,
    BLOCK_JSON_ENCODING,
    Block,
    encode_block_binary,
    encode_block_json,
)
from sinewatch.schemas.config import EstimatorRule, LimitsSection, RecordingSection


def big_json(n: int = 800_000) -> bytes:
    x = np.random.default_rng(3).standard_normal(n)
    return encode_block_json(Block("big/a", 0, 0, 10_000.0, x))


def test_a_large_json_block_is_refused_before_it_is_parsed(tmp_path):
    keep = Keep()
    pipeline = Pipeline(make_config(tmp_path, hold_estimates=False), [keep])
    payload = big_json()
    assert 15_000_000 < len(payload) < 16 << 20  # under max_payload_bytes (16 MiB)
    for encoding in (BLOCK_JSON_ENCODING, "zenoh/bytes"):  # labelled, or sniffed
        pipeline.process("sinewatch/in/big/a", payload, encoding, 1)
    assert [e["kind"] for e in keep.errors] == ["oversized_block"] * 2
    assert f"JSON payload: expected at most {256 << 10} bytes, got {len(payload)}" in keep.errors[0]["message"]
    # a binary block of the same samples is not a JSON payload: taken as before
    x = np.random.default_rng(3).standard_normal(800_000)
    pipeline.process(
        "sinewatch/in/big/b", encode_block_binary(Block("big/b", 0, 0, 10_000.0, x)), BLOCK_BINARY_ENCODING, 2
    )
    assert [e["channel"] for e in keep.estimates] == ["big/b"]
    # and a JSON block under the limit is decoded
    small = encode_block_json(Block("big/c", 0, 0, 10_000.0, x[:5000]))
    assert len(small) < 256 << 10
    pipeline.process("sinewatch/in/big/c", small, BLOCK_JSON_ENCODING, 3)
    assert [e["channel"] for e in keep.estimates] == ["big/b", "big/c"]


def test_the_limit_is_configurable(tmp_path):
    keep = Keep()
    pipeline = Pipeline(
        make_config(tmp_path, hold_estimates=False, limits=LimitsSection(max_json_payload_bytes=16 << 20)), [keep]
    )
    pipeline.process("sinewatch/in/big/a", big_json(), BLOCK_JSON_ENCODING, 1)
    assert keep.errors == [] and len(keep.estimates) == 1


CHANNELS = [f"lat/{i}" for i in range(10)]
FS, BLOCK = 10_000.0, 500  # 50 ms blocks, real time


@pytest.mark.slow
@pytest.mark.parametrize("n", [800_000, 12_500], ids=["15.7MB-refused", "250kB-largest-accepted"])
def test_other_channels_latency_with_a_large_json_block(tmp_path, n):
    """Ten real-time channels; their estimates' latency (publish to arrival, p99) in 3 s
    without, then 3 s starting with, a JSON block on another channel: 15.7 MB (refused
    unparsed) or the largest accepted by default (about 250 kB, parsed). Prints the ratio
    (a measurement, not an assertion: the machine is shared)."""
    config = make_config(
        tmp_path,
        rules=[EstimatorRule(match="sinewatch/in/**", estimator="ipdft")],
        recording=RecordingSection(enabled=False),
    )
    payload = big_json(n)

    def client(_daemon, ep):
        with connect([ep]) as s:
            est = subscribe_estimates(s)
            pub = BlockPublisher(s)
            for ch in CHANNELS:
                assert pub.wait_for_subscriber(ch, TIMEOUT)
            sent: dict[tuple[str, int], float] = {}
            arrived: dict[tuple[str, int], float] = {}
            n_blocks = int(6.0 * FS / BLOCK)
            last = (CHANNELS[-1], n_blocks - 1)
            got_last = threading.Event()

            def take():
                while not got_last.is_set() and (m := est.get(timeout=TIMEOUT)) is not None:
                    arrived[(m["channel"], m["seq"])] = time.monotonic()
                    if (m["channel"], m["seq"]) == last:
                        got_last.set()

            taker = threading.Thread(target=take)
            taker.start()
            t = np.arange(BLOCK) / FS
            start = time.monotonic()
            for k in range(n_blocks):
                if k == n_blocks // 2:
                    pub.publish_raw("big/a", payload, encoding=BLOCK_JSON_ENCODING)
                for i, ch in enumerate(CHANNELS):
                    pub.publish(ch, np.sin(2 * np.pi * 50.0 * (t + k * BLOCK / FS) + i), FS)
                    sent[(ch, k)] = time.monotonic()
                time.sleep(max(0.0, start + (k + 1) * BLOCK / FS - time.monotonic()))  # the real-time pace
            taker.join()
            return sent, arrived, n_blocks

    (sent, arrived, n_blocks), daemon, code = run_daemon(config, client)
    assert code == 0
    half = n_blocks // 2
    lat = {
        phase: [arrived[k] - sent[k] for k in sent if (k[1] < half) == (phase == "before") and k in arrived]
        for phase in ("before", "after")
    }
    assert len(lat["before"]) + len(lat["after"]) == len(sent)  # every block estimated
    p99 = {phase: float(np.percentile(v, 99)) * 1e3 for phase, v in lat.items()}
    print(
        f"\nother channels' latency p99: {p99['before']:.1f} ms without, {p99['after']:.1f} ms with the "
        f"{len(payload) / 1e6:.1f} MB JSON block (ratio {p99['after'] / p99['before']:.2f}); "
        f"its errors: {dict(daemon.pipeline.counters.by_kind)}"
    )
