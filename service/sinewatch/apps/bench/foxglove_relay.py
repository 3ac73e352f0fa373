"""What the subprotocol relay of the live view costs, against a client of the SDK's server.

``python -m sinewatch.apps.bench.foxglove_relay [--messages N] [--repeats R]`` (``make
bench-foxglove-relay``) starts the live view (:class:`~sinewatch.outputs.foxglove_live.FoxgloveSink`)
and, R times interleaved, subscribes one WebSocket client (``websockets``) to an estimate
topic, either on the SDK's own port (``direct``, subprotocol ``foxglove.sdk.v1``) or through
the relay on the configured port (``relay``, subprotocol ``foxglove.websocket.v1``), logs N
Estimate messages (~600 bytes each) as fast as the sink takes them and waits until the
client has all of them. It prints one JSON line per path: messages a second (wall time,
best of the repeats) and CPU microseconds a message (this process, every thread: the SDK's
server, the relay, the client), with the relay's ratios to ``direct`` in the same run.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from typing import Any

from sinewatch.outputs.foxglove_live import LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL, FoxgloveSink
from sinewatch.schemas.config import FoxgloveSection, SinewatchConfig

TOPIC = "sinewatch/est/bench/a"


def estimate(i: int) -> bytes:
    return json.dumps(
        {
            "format_version": 3,
            "channel": "bench/a",
            "seq": i,
            "timestamp_ns": 1_763_900_000_000_000_000 + i,
            "timestamp": {"sec": 1_763_900_000, "nsec": i},
            "n_samples": 1024,
            "estimator": "ipdft",
            "frequency_hz": [50.00123456789],
            "amplitude": [1.4999876543],
            "phase_rad": [0.123456789],
            "offset": 0.000123,
            "rocof_hz_per_s": [0.0012345],
            "std": {"frequency_hz": [1.2e-5], "amplitude": [3.4e-5], "phase_rad": [5.6e-5], "offset": 7.8e-6},
            "diagnostics": {
                "converged": True,
                "valid": True,
                "residual_rms": 0.0123,
                "gap": False,
                "gap_blocks": 0,
                "restart": False,
                "reset": False,
                "extras": {},
            },
        }
    ).encode()


async def one_run(sink: FoxgloveSink, port: int, subprotocol: str, n: int) -> tuple[float, float]:
    """(wall seconds, CPU seconds) until the client has received n messages."""
    import websockets  # the test extra's client
    from websockets.typing import Subprotocol

    url = f"ws://127.0.0.1:{port}"
    async with websockets.connect(url, subprotocols=[Subprotocol(subprotocol)], max_size=None) as ws:
        channel_id = None
        while channel_id is None:
            msg = json.loads(await ws.recv())
            if msg["op"] == "advertise":
                channel_id = next((c["id"] for c in msg["channels"] if c["topic"] == TOPIC), None)
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel_id}]}))
        await asyncio.to_thread(sink.subscriptions.wait, [TOPIC], 10.0)
        payloads = [estimate(i) for i in range(n)]
        wall, cpu = time.perf_counter(), time.process_time()

        def produce() -> None:
            for i, p in enumerate(payloads):
                sink.on_estimate(TOPIC, p, i)

        producer = asyncio.create_task(asyncio.to_thread(produce))
        got = 0
        while got < n:
            frame = await ws.recv()
            if isinstance(frame, bytes):
                got += 1
                if json.loads(frame[13:])["seq"] == n - 1:
                    break  # a slow client loses the oldest (backlog): the last one ends the run
        await producer
        return time.perf_counter() - wall, time.process_time() - cpu


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=20_000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    config = SinewatchConfig(daemon_id="bench", foxglove=FoxgloveSection(port=0, inputs=False, backlog=args.messages))
    sink = FoxgloveSink(config)
    sink.on_estimate(TOPIC, estimate(0), 0)  # advertises the topic
    paths: dict[str, tuple[int, str]] = {
        "direct": (sink.server.port, SDK_SUBPROTOCOL),
        "relay": (sink.port, LEGACY_SUBPROTOCOL),
    }
    best: dict[str, list[float]] = {k: [float("inf"), float("inf")] for k in paths}
    try:
        for _ in range(args.repeats):
            for name, (port, subprotocol) in paths.items():
                wall, cpu = asyncio.run(one_run(sink, port, subprotocol, args.messages))
                best[name] = [min(best[name][0], wall), min(best[name][1], cpu)]
    finally:
        sink.close()
    base: dict[str, Any] = {}
    for name, (wall, cpu) in best.items():
        line: dict[str, Any] = {
            "path": name,
            "messages": args.messages,
            "msgs_per_s": round(args.messages / wall),
            "cpu_us_per_msg": round(cpu / args.messages * 1e6, 2),
        }
        if name == "direct":
            base = line
        else:
            line["throughput_vs_direct"] = round(line["msgs_per_s"] / base["msgs_per_s"], 3)
            line["cpu_vs_direct"] = round(line["cpu_us_per_msg"] / base["cpu_us_per_msg"], 3)
        print(json.dumps(line))


if __name__ == "__main__":
    main()
