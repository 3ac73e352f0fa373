"""The measuring side of ``sinewatch bench e2e`` and the benches built on it: the daemon's
processes read from ``/proc`` (memory, CPU, the event loop's run and wait times), the
estimates' latency (:class:`LatencyProbe`) and a Foxglove client (:class:`FoxgloveProbe`,
its own process)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import zenoh


def process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants (a ``serve`` supervisor and its worker processes)."""
    pids = [pid]
    for p in pids:
        for task in Path(f"/proc/{p}/task").glob("*/children"):
            with contextlib.suppress(OSError):
                pids.extend(int(c) for c in task.read_text().split())
    return pids


def rss_mb(pid: int) -> float:
    """Resident memory of the process and its children (the workers), MB."""
    total = 0.0
    for p in process_tree(pid):
        with contextlib.suppress(OSError):
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024
    return total


def cpu_seconds(pid: int) -> float:
    """CPU time of the process and its living children (the workers), seconds."""
    total = 0.0
    for p in process_tree(pid):
        with contextlib.suppress(OSError):
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def main_thread_times(pid: int) -> tuple[int, int]:
    """Nanoseconds the process's main thread (the daemon's event loop) has run on a CPU and
    waited in the run queue for one (``/proc/<pid>/schedstat``; (0, 0) where unreadable).
    Over an interval of wall time, the rest is time it slept: blocked in a Zenoh put
    (CongestionControl.BLOCK), waiting for the GIL, or idle with nothing to do."""
    try:
        run_ns, wait_ns, _slices = Path(f"/proc/{pid}/schedstat").read_text().split()
    except (OSError, ValueError):
        return 0, 0
    return int(run_ns), int(wait_ns)


class LatencyProbe:
    """Estimate subscriber: latency = arrival - the estimate's timestamp, which the bench
    feeder sets to the block's publish time (CLOCK_MONOTONIC, system-wide on Linux).

    The probe shares the machine with the daemon it measures, so it costs as little as it
    can: the estimates are drained from a Zenoh FIFO by one thread, many per wake-up (a
    callback takes the GIL once per estimate), and only the three fields it needs are read
    from the JSON as the daemon writes it (compact, ``"timestamp_ns":`` before
    ``"diagnostics"``), not the whole message parsed: 40 -> 29 us an estimate at 1,000
    channels (``sinewatch bench e2e --channels 1000``, the ``cpu_us_per_block`` field)."""

    def __init__(self, session: Any, key: str) -> None:
        self.latencies_ns: list[int] = []
        self.received = 0
        self.gaps = 0  # estimates that say blocks were missing before them
        self.gap_blocks = 0
        self.done = threading.Event()
        self.expected: int | None = None
        self._sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(4096))
        self._thread = threading.Thread(target=self._drain, name="bench-latency-probe", daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        handler = self._sub.handler
        with contextlib.suppress(zenoh.ZError):  # raised once undeclared and drained: the probe is over
            while True:
                sample = handler.recv()
                while sample is not None:
                    self._on(sample.payload.to_bytes(), time.monotonic_ns())
                    sample = handler.try_recv()

    def _on(self, payload: bytes, now_ns: int) -> None:
        timestamp_ns, gap_blocks = probe_fields(payload)
        self.latencies_ns.append(now_ns - timestamp_ns)
        self.received += 1
        if gap_blocks is not None:
            self.gaps += 1
            self.gap_blocks += gap_blocks
        if self.expected is not None and self.received >= self.expected:
            self.done.set()

    def close(self) -> None:
        self._sub.undeclare()
        self._thread.join(5.0)


_TIMESTAMP_NS = re.compile(rb'"timestamp_ns":(-?[0-9]+)')


def probe_fields(payload: bytes) -> tuple[int, int | None]:
    """An Estimate's ``timestamp_ns``, and its ``diagnostics.gap_blocks`` when it flags a
    gap (None when not), read from its JSON bytes as the daemon writes them."""
    match = _TIMESTAMP_NS.search(payload)  # one C call (a digit loop in Python was 3 us of ~5)
    if match is None:
        raise ValueError(f"estimate: expected a timestamp_ns, got {payload[:80]!r}")
    timestamp_ns = int(match.group(1))
    diagnostics = payload.index(b'"diagnostics":')
    if payload.find(b'"gap":true', diagnostics) < 0:
        return timestamp_ns, None
    return timestamp_ns, _json_int(payload, b'"gap_blocks":', diagnostics)


def _json_int(payload: bytes, key: bytes, start: int = 0) -> int:
    """The integer after ``key`` (``"name":``) in compact JSON: its first occurrence from ``start``."""
    start = payload.index(key, start) + len(key)
    end = start
    while payload[end] in b"-0123456789":
        end += 1
    return int(payload[start:end])


class FoxgloveProbe:
    """A Foxglove WebSocket client, run as its own process (:func:`foxglove_probe_main`) so
    that reading the stream cannot slow this process's Zenoh subscriber (which would push
    back on the daemon through CongestionControl.BLOCK and be mistaken for the daemon's
    cost): subscribes to every channel the daemon advertises and counts the messages (and
    bytes) per topic kind."""

    SUBPROTOCOL = "foxglove.sdk.v1"

    def __init__(self, port: int) -> None:
        import importlib.util

        from sinewatch.schemas.errors import SinewatchError

        if importlib.util.find_spec("websockets") is None:
            raise SinewatchError(
                "bench e2e --foxglove: expected the websockets package for its client "
                "(pip install 'sinewatch[test]'), got none installed"
            )
        code = "import sys; from sinewatch.apps.bench.e2e_probes import foxglove_probe_main; sys.exit(foxglove_probe_main(sys.argv[1]))"
        self._proc = subprocess.Popen(
            [sys.executable, "-c", code, str(port)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        assert self._proc.stdout is not None
        if self._proc.stdout.readline().strip() != "connected":
            raise RuntimeError("the daemon's Foxglove server did not accept the probe")
        self.messages: dict[str, int] = {}
        self.bytes = 0

    def close(self) -> None:
        out, _ = self._proc.communicate(timeout=60)  # stdin closed: the probe reports and exits
        counts = json.loads(out)
        self.messages, self.bytes = counts["messages"], counts["bytes"]


def foxglove_probe_main(port: str) -> int:
    import asyncio

    messages: dict[str, int] = {}
    total = [0]
    asyncio.run(_foxglove_probe(int(port), messages, total))
    print(json.dumps({"messages": dict(sorted(messages.items())), "bytes": total[0]}), flush=True)
    return 0


async def _foxglove_probe(port: int, messages: dict[str, int], total: list[int]) -> None:
    import asyncio
    import struct

    import websockets
    from websockets.typing import Subprotocol

    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), loop.call_soon_threadsafe(stop.set)), daemon=True).start()
    topics: dict[int, str] = {}  # channel id -> topic
    subs: dict[int, str] = {}  # subscription id -> topic kind
    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=[Subprotocol(FoxgloveProbe.SUBPROTOCOL)]
    ) as ws:
        print("connected", flush=True)

        async def subscribe(ids: list[int]) -> None:
            batch = []
            for cid in ids:
                sid = len(subs) + 1
                subs[sid] = "/".join(topics[cid].split("/")[:2])  # sinewatch/est, sinewatch/samples, ...
                batch.append({"id": sid, "channelId": cid})
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": batch}))

        stopped = asyncio.ensure_future(stop.wait())
        while not stop.is_set():
            recv = asyncio.ensure_future(ws.recv())
            await asyncio.wait([recv, stopped], return_when=asyncio.FIRST_COMPLETED)
            if not recv.done():
                recv.cancel()
                break
            frame = recv.result()
            if isinstance(frame, bytes):
                (sid,) = struct.unpack_from("<I", frame, 1)
                messages[subs[sid]] = messages.get(subs[sid], 0) + 1
                total[0] += len(frame)
                continue
            msg = json.loads(frame)
            if msg["op"] == "advertise":
                for ch in msg["channels"]:
                    topics[ch["id"]] = ch["topic"]
                await subscribe([ch["id"] for ch in msg["channels"]])
            elif msg["op"] == "status" and "Unknown channel ID" in msg["message"]:
                # foxglove-sdk 0.30 may not know a channel it has just advertised: ask again
                await subscribe([int(msg["message"].rsplit(":", 1)[1])])
