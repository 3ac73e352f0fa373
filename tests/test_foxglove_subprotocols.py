"""Foxglove for every client: the live view answers a client asking for subprotocol
``foxglove.sdk.v1`` (Foxglove today) and one asking for ``foxglove.websocket.v1`` (Lichtblick,
PlotJuggler, Foxglove Studio before the SDK), on the same port. Each test is an independent
client (the ``websockets`` package) subscribing to an estimate topic and a samples topic of
a real daemon fed over real Zenoh, and checks every message that arrives against the JSON
Schema its channel advertised (``jsonschema``)."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
from conftest import make_config, publishing, run_daemon, take

pytest.importorskip("foxglove", reason="the foxglove extra (pip install '.[foxglove]')")
websockets = pytest.importorskip("websockets")
jsonschema = pytest.importorskip("jsonschema")

from test_foxglove_live import FoxgloveClient, last_seq  # noqa: E402

from sinewatch.clients import subscribe_estimates  # noqa: E402
from sinewatch.clients.session import free_loopback_port  # noqa: E402
from sinewatch.outputs.foxglove_live import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL, offered_subprotocols  # noqa: E402
from sinewatch.schemas.codec import Block, encode_block_binary  # noqa: E402
from sinewatch.schemas.config import FoxgloveSection  # noqa: E402


def _blocks(n: int, fs: float = 10_000.0, size: int = 1000) -> list[Block]:
    rng = np.random.default_rng(5)
    t = np.arange(n * size) / fs
    x = 2.0 * np.sin(2 * np.pi * 60.0 * t) + 0.01 * rng.standard_normal(t.size)
    return [
        Block("sp/a", i, 1_700_000_000_000_000_000 + i * 100_000_000, fs, x[i * size : (i + 1) * size])
        for i in range(n)
    ]


@pytest.mark.parametrize("subprotocol", [SDK_SUBPROTOCOL, LEGACY_SUBPROTOCOL])
def test_a_client_of_either_subprotocol_gets_estimates_and_samples_matching_their_schemas(tmp_path, subprotocol):
    port = free_loopback_port()
    config = make_config(tmp_path, foxglove=FoxgloveSection(port=port, input_points=50))
    blocks = _blocks(8)
    est_topic, samples_topic = "sinewatch/est/sp/a", "sinewatch/samples/sp/a"

    def client(daemon, ep):
        with publishing(ep, "sp/a", subscribe_estimates) as (pub, [zenoh_est]):

            async def session() -> tuple[FoxgloveClient, str | None]:
                async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[subprotocol]) as ws:
                    fc = FoxgloveClient(ws)
                    await fc.until(lambda: fc.server_info is not None)
                    pub.publish_raw("sp/a", encode_block_binary(blocks[0]))
                    assert take(zenoh_est, 1)
                    await fc.until(lambda: est_topic in fc.channels and samples_topic in fc.channels)
                    await fc.subscribe_all([est_topic, samples_topic], daemon.foxglove.subscriptions)
                    for blk in blocks[1:]:
                        pub.publish_raw("sp/a", encode_block_binary(blk))
                    n = len(blocks) - 1
                    await fc.until(lambda: last_seq(fc, est_topic) == n and fc.count(samples_topic) >= n)
                    return fc, ws.subprotocol

            fc, agreed = asyncio.run(session())
            return fc, agreed, daemon.foxglove.relay.legacy_clients

    (fc, agreed, legacy_clients), _daemon, code = run_daemon(config, client)
    assert code == 0
    assert agreed == subprotocol  # the server answered with the very subprotocol asked for
    assert legacy_clients == (1 if subprotocol == LEGACY_SUBPROTOCOL else 0)
    assert fc.server_info["name"] == "sinewatch test"
    for topic, schema_name in ((est_topic, "sinewatch.Estimate"), (samples_topic, "sinewatch.SamplesSummary")):
        ch = fc.channels[topic]
        assert (ch["encoding"], ch["schemaName"], ch.get("schemaEncoding", "jsonschema")) == (
            "json",
            schema_name,
            "jsonschema",
        )
        validator = jsonschema.Draft202012Validator(json.loads(ch["schema"]))
        messages = [json.loads(p) for _, p in fc.messages[topic]]
        assert len(messages) >= len(blocks) - 1
        for m in messages:
            validator.validate(m)
    estimates = [json.loads(p) for _, p in fc.messages[est_topic]]
    assert abs(estimates[-1]["frequency_hz"][0] - 60.0) < 0.05 and abs(estimates[-1]["amplitude"][0] - 2.0) < 0.05
    summaries = [json.loads(p) for _, p in fc.messages[samples_topic]]
    assert summaries[-1]["samples"] == blocks[-1].samples[::20].tolist()


def test_offered_subprotocols_are_read_from_every_header_of_the_request():
    request = (
        b"GET / HTTP/1.1\r\nHost: x\r\nsec-websocket-protocol: a, foxglove.websocket.v1\r\n"
        b"Sec-WebSocket-Protocol:b\r\n\r\n"
    )
    assert offered_subprotocols(request) == ["a", "foxglove.websocket.v1", "b"]
