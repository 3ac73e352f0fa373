"""Live Foxglove (``serve --foxglove PORT``): a real WebSocket client speaking the Foxglove
protocol to a real in-process daemon fed over real Zenoh on 127.0.0.1.

The client is a few lines over ``websockets``: the SDK's server speaks subprotocol
``foxglove.sdk.v1`` (the Foxglove WebSocket protocol: JSON ``serverInfo`` and
``advertise`` text frames; the client sends ``subscribe`` with its own subscription ids;
each message arrives as a binary frame: opcode 0x01, subscription id (u32 LE), log time
(u64 LE, ns), payload).
"""

from __future__ import annotations

import asyncio
import json
import struct
import subprocess
import sys
from typing import Any

import numpy as np
import pytest
from conftest import TIMEOUT, make_config, publishing, run_daemon, take
from mcap.reader import make_reader

pytest.importorskip("foxglove", reason="the foxglove extra (pip install '.[foxglove]')")
websockets = pytest.importorskip("websockets")

from sinewatch.clients import subscribe_estimates  # noqa: E402
from sinewatch.clients.session import free_loopback_port  # noqa: E402
from sinewatch.outputs.foxglove_live import LOG_TOPIC, summarise  # noqa: E402
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary  # noqa: E402
from sinewatch.schemas.config import FoxgloveSection  # noqa: E402

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01


class FoxgloveClient:
    """The protocol's client side, as much of it as the test needs."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}  # topic -> advertised channel
        self.server_info: dict[str, Any] | None = None
        self._sub_topic: dict[int, str] = {}
        self.messages: dict[str, list[tuple[int, bytes]]] = {}  # topic -> [(log time, payload)]

    async def _read_one(self) -> None:
        frame = await asyncio.wait_for(self.ws.recv(), TIMEOUT)
        if isinstance(frame, bytes):
            assert frame[0] == MESSAGE_DATA, frame[:1]
            sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
            self.messages.setdefault(self._sub_topic[sub_id], []).append((log_time, frame[13:]))
            return
        msg = json.loads(frame)
        if msg["op"] == "serverInfo":
            self.server_info = msg
        elif msg["op"] == "advertise":
            for ch in msg["channels"]:
                self.channels[ch["topic"]] = ch

    async def until(self, done: Any) -> None:
        """Read frames until ``done()`` (each read times out after TIMEOUT)."""
        while not done():
            await self._read_one()

    async def subscribe(self, topics: list[str]) -> None:
        subs = []
        for topic in topics:
            sub_id = len(self._sub_topic) + 1
            self._sub_topic[sub_id] = topic
            subs.append({"id": sub_id, "channelId": self.channels[topic]["id"]})
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    async def subscribe_all(self, topics: list[str], server_side: Any) -> None:
        """Subscribe, and return once the server's listener has seen every subscription.
        foxglove-sdk 0.30 sometimes answers a subscription to a channel it has just advertised
        with "Unknown channel ID" (its own state lags its advertise): then ask again."""
        for _ in range(5):
            await self.subscribe(topics)
            if await asyncio.to_thread(server_side.wait, topics, 2.0):
                return
        raise AssertionError(f"the server never took the subscriptions to {topics}")

    def count(self, topic: str) -> int:
        return len(self.messages.get(topic, []))


def last_seq(fc: FoxgloveClient, topic: str) -> int | None:
    """The sequence number of the last estimate the client received on ``topic``."""
    got = fc.messages.get(topic)
    return int(json.loads(got[-1][1])["seq"]) if got else None


def _blocks(n: int, fs: float = 10_000.0, size: int = 1000) -> list[Block]:
    rng = np.random.default_rng(18)
    t = np.arange(n * size) / fs
    x = 1.5 * np.sin(2 * np.pi * 50.0 * t + 0.3) + 0.2 + 0.01 * rng.standard_normal(t.size)
    t0 = 1_700_000_000_123_456_789  # beyond 2^53 ns: only {sec, nsec} carries it exactly in JavaScript
    return [Block("fox/a", i, t0 + i * round(size * 1e9 / fs), fs, x[i * size : (i + 1) * size]) for i in range(n)]


def test_a_foxglove_client_receives_live_estimates_input_summaries_and_log_lines(tmp_path):
    port = free_loopback_port()
    config = make_config(tmp_path, foxglove=FoxgloveSection(port=port, input_points=100))
    blocks = _blocks(12)
    bad = Block("fox/a", 99, blocks[0].t0_ns, 10_000.0, np.array([0.1, np.nan]))
    est_topic, samples_topic = "sinewatch/est/fox/a", "sinewatch/samples/fox/a"

    def client(daemon, ep):
        with publishing(ep, "fox/a", subscribe_estimates) as (pub, [zenoh_est]):

            async def session() -> FoxgloveClient:
                async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
                    assert ws.subprotocol == SUBPROTOCOL
                    fc = FoxgloveClient(ws)
                    await fc.until(lambda: fc.server_info is not None and LOG_TOPIC in fc.channels)
                    # the first block makes the channel's topics; the client subscribes to them
                    pub.publish_raw("fox/a", encode_block_binary(blocks[0]))
                    assert take(zenoh_est, 1)
                    await fc.until(lambda: est_topic in fc.channels and samples_topic in fc.channels)
                    await fc.subscribe_all([est_topic, samples_topic, LOG_TOPIC], daemon.foxglove.subscriptions)
                    for blk in [*blocks[1:], bad]:
                        pub.publish_raw("fox/a", encode_block_binary(blk))
                    n = len(blocks) - 1
                    await fc.until(
                        lambda: (
                            last_seq(fc, est_topic) == n and fc.count(samples_topic) >= n and fc.count(LOG_TOPIC) >= 1
                        )
                    )
                    return fc

            fc = asyncio.run(session())
            return fc, take(zenoh_est, len(blocks) - 1)

    (fc, zenoh_estimates), daemon, code = run_daemon(config, client)
    assert code == 0

    # estimates: on their Zenoh key, with the Estimate JSON Schema, the very bytes Zenoh carried
    ch = fc.channels[est_topic]
    assert ch["encoding"] == "json" and ch["schemaName"] == "sinewatch.Estimate"
    assert json.loads(ch["schema"])["properties"]["timestamp"]
    live = [json.loads(p) for _, p in fc.messages[est_topic]]
    # the live view sends on its own task, so block 0's estimate may still be on its way when the
    # client subscribes (then it arrives too): every later one, in order, and nothing else
    seqs = [e["seq"] for e in live]
    assert seqs in (list(range(1, len(blocks))), list(range(len(blocks))))
    live = live[-(len(blocks) - 1) :]
    assert live == [{k: v for k, v in e.items() if k != "_key"} for e in zenoh_estimates]
    for e in live:  # Foxglove's time beside timestamp_ns, exact
        assert e["timestamp"]["sec"] * 1_000_000_000 + e["timestamp"]["nsec"] == e["timestamp_ns"]
    assert abs(live[-1]["frequency_hz"][0] - 50.0) < 0.05 and abs(live[-1]["amplitude"][0] - 1.5) < 0.05

    # live log times are the recording's: a live session and its MCAP file line up
    [path] = daemon.recording_paths
    with open(path, "rb") as f:
        recorded = {
            json.loads(m.data)["seq"]: m.log_time
            for _, c, m in make_reader(f).iter_messages(topics=[est_topic])
            if c.topic == est_topic
        }
    assert [t for t, _ in fc.messages[est_topic]] == [recorded[e["seq"]] for e in live]

    # input summaries: what numpy says about the blocks sent
    assert fc.channels[samples_topic]["schemaName"] == "sinewatch.SamplesSummary"
    summaries = [json.loads(p) for _, p in fc.messages[samples_topic]]
    assert [m["seq"] for m in summaries] == list(range(1, len(blocks)))
    for m, blk in zip(summaries, blocks[1:], strict=True):
        x = blk.samples  # sent as float64 (encode_block_binary)
        assert m["timestamp_ns"] == blk.t0_ns and m["timestamp"] == {
            "sec": blk.t0_ns // 1_000_000_000,
            "nsec": blk.t0_ns % 1_000_000_000,
        }
        assert m["n_samples"] == 1000 and m["stride"] == 10 and m["samples"] == x[::10].tolist()
        assert m["min"] == x.min() and m["max"] == x.max() and m["mean"] == pytest.approx(x.mean(), abs=1e-12)
        assert m["rms"] == pytest.approx(np.sqrt(np.mean(x**2)), rel=1e-12)

    # the log line of the rejected block, as foxglove.Log
    log_ch = fc.channels[LOG_TOPIC]
    assert log_ch["schemaName"] == "foxglove.Log" and log_ch["encoding"] == "protobuf"
    assert any(b"rejected input on sinewatch/in/fox/a (non_finite)" in p for _, p in fc.messages[LOG_TOPIC])
    assert daemon.foxglove.counters.inputs_dropped == 0 and daemon.foxglove.counters.input_summaries >= 11


def test_summaries_of_a_block_decimate_to_at_most_input_points():
    x = np.arange(1001, dtype=np.float64)
    blk = Block("s/a", 3, -1_500_000_000, 1000.0, np.column_stack([x, -x]))  # column 0 is the measurement
    m = summarise(encode_block_binary(blk), BLOCK_BINARY_ENCODING, 100)
    assert m["stride"] == 11 and m["samples"] == x[::11].tolist() and len(m["samples"]) == 91
    assert (m["min"], m["max"], m["mean"]) == (0.0, 1000.0, 500.0)
    assert m["timestamp"] == {"sec": -2, "nsec": 500_000_000}  # floor: negative times too


def test_without_the_foxglove_extra_serve_says_so_in_one_line(tmp_path):
    """The daemon as a user runs it, with the foxglove package made unimportable."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f'[zenoh]\nlisten = ["tcp/127.0.0.1:{free_loopback_port()}"]\n[recording]\nenabled = false\n'
        '[[rules]]\nestimator = "ipdft"\n'
    )
    code = (
        "import sys; sys.modules['foxglove'] = None; from sinewatch.apps.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    r = subprocess.run(
        [sys.executable, "-c", code, "serve", "--config", str(cfg), "--foxglove", "0"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        "sinewatch: error: --foxglove / [foxglove] needs the 'foxglove' extra: pip install 'sinewatch[foxglove]' "
        "(expected the foxglove-sdk package, got no module 'foxglove')"
    )


def test_input_summaries_past_the_rate_are_skipped_and_counted(tmp_path):
    """input_rate_hz below one a second: the bucket never holds a whole token, so every
    block is skipped on the event loop's side (counted), none reaches the worker."""
    from sinewatch.outputs.foxglove_live import FoxgloveSink

    config = make_config(tmp_path, foxglove=FoxgloveSection(port=0, input_rate_hz=0.5))
    sink = FoxgloveSink(config)
    try:
        payload = encode_block_binary(_blocks(1)[0])
        for i in range(10):
            sink.on_input("sinewatch/in/fox/a", payload, BLOCK_BINARY_ENCODING, i)
    finally:
        sink.close()  # waits for the worker: it has seen nothing
    c = sink.counters
    assert (c.inputs_over_rate, c.input_summaries, c.inputs_unreadable, c.inputs_dropped) == (10, 0, 0, 0)
    assert "sinewatch/samples/fox/a" not in sink._topics  # the worker never decoded a block
    assert sink.port > 0
