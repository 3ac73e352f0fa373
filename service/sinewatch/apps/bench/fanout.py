"""``sinewatch bench fanout``: how a supervisor's inputs reach its worker processes,
both ways measured in the same run.

* **zenoh** (what ``serve --workers`` does): each worker's own Zenoh session subscribes
  to every input key; Zenoh (in its own threads) delivers every block to every worker,
  and each drops the blocks another worker owns (:func:`sinewatch.runtime.cluster.worker_of`)
  before copying them out of Zenoh's buffer. What it adds: the delivery of the N - 1
  foreign blocks into each worker's Python per block.
* **shm**: one dispatcher receives every block in Python (as the single daemon does),
  copies it into a shared-memory ring (``multiprocessing.shared_memory``) of the owning
  worker and tells it through a pipe; the worker reads the block where it lies and
  returns the slot. What it adds: the dispatcher's receive and copy, the ring's bookkeeping
  and the wake-ups, and one more process whose single Python lock every block crosses.

A publisher process offers ``--blocks`` blocks of ``--block`` float32 samples over
``--channels`` keys, ``--rate`` blocks a second as sensors send them (default 10,000: 1,000
channels at 10 kHz; 0: as fast as Zenoh takes them, which batches messages and hides their
per-message cost), CongestionControl.BLOCK (nothing is lost),
through a router session in this process. Reported per way: the blocks/s through, and
the CPU time per block of the receiving processes (user + system, summed), and the ratio
shm / zenoh. Neither decodes nor estimates: only the fan-out is compared.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import multiprocessing.shared_memory
import os
import struct
import time
from multiprocessing.connection import Connection
from typing import Any

from rich.table import Table

from sinewatch.apps.console import make_console, print_table
from sinewatch.runtime.cluster import worker_of

HEADER = struct.Struct("<II")  # slot, length
DEADLINE_S = 120.0


def _keys(channels: int) -> list[str]:
    return [f"fanout/in/{i:05d}" for i in range(channels)]


def _session(endpoint: str) -> Any:
    from sinewatch.clients.session import client_section, open_session

    return open_session(client_section([endpoint]))


def _cpu() -> float:
    t = os.times()
    return t.user + t.system


# ---- the publisher ---------------------------------------------------------------------------
def _publish(endpoint: str, channels: int, block: int, blocks: int, rate: float, go: Connection) -> None:
    import threading

    import zenoh

    payload = bytes(4 * block)
    tick = threading.Event()
    with _session(endpoint) as session:
        pubs = [session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k in _keys(channels)]
        go.send("ready")
        go.recv()  # every receiver subscribed
        start = time.monotonic()
        for n in range(blocks):
            if rate > 0:  # paced as sensors are: the blocks due within a millisecond go out together
                delay = start + n / rate - time.monotonic()
                if delay > 0:
                    tick.wait(max(delay, 0.001))
            pubs[n % channels].put(payload)
        go.send("done")
        go.recv()  # stay connected until everything was delivered


# ---- way 1: every worker subscribes and drops the others' blocks ---------------------------------
def _zenoh_worker(endpoint: str, index: int, workers: int, expected: int, report: Connection) -> None:
    import zenoh

    with _session(endpoint) as session:
        fifo: zenoh.handlers.FifoChannel[zenoh.Sample] = zenoh.handlers.FifoChannel(1024)
        sub = session.declare_subscriber("fanout/in/**", fifo)
        report.send("ready")
        cpu0, kept, seen = _cpu(), 0, 0
        deadline = time.monotonic() + DEADLINE_S
        while seen < expected and time.monotonic() < deadline:
            sample = sub.handler.recv()
            seen += 1
            if worker_of(str(sample.key_expr), workers) == index:
                data = sample.payload.to_bytes()  # the copy a worker makes of its own blocks
                kept += len(data) > 0
        report.send({"cpu_s": _cpu() - cpu0, "kept": kept, "seen": seen})


# ---- way 2: a dispatcher copies each block into its worker's shared-memory ring ---------------
def _dispatcher(
    endpoint: str, workers: int, slots: int, slot_bytes: int, expected: int, rings: list[Any], report: Connection
) -> None:
    import zenoh

    notify, credit = zip(*rings, strict=True)
    free = [list(range(slots)) for _ in range(workers)]
    shm = [multiprocessing.shared_memory.SharedMemory(name=f"{os.getppid()}-fanout-{w}") for w in range(workers)]
    with _session(endpoint) as session:
        fifo: zenoh.handlers.FifoChannel[zenoh.Sample] = zenoh.handlers.FifoChannel(1024)
        sub = session.declare_subscriber("fanout/in/**", fifo)
        report.send("ready")
        cpu0, seen = _cpu(), 0
        deadline = time.monotonic() + DEADLINE_S
        while seen < expected and time.monotonic() < deadline:
            sample = sub.handler.recv()
            seen += 1
            w = worker_of(str(sample.key_expr), workers) - 1
            while not free[w]:  # the worker returns slots it has read
                free[w].extend(credit[w].recv())
            slot = free[w].pop()
            data = sample.payload.to_bytes()
            buf = shm[w].buf
            assert buf is not None
            buf[slot * slot_bytes : slot * slot_bytes + len(data)] = data
            notify[w].send_bytes(HEADER.pack(slot, len(data)))
        for conn in notify:
            conn.send_bytes(b"")  # end
        report.send({"cpu_s": _cpu() - cpu0, "seen": seen})
    for m in shm:
        m.close()


def _shm_worker(index: int, slot_bytes: int, notify: Connection, credit: Connection, report: Connection) -> None:
    import numpy as np

    shm = multiprocessing.shared_memory.SharedMemory(name=f"{os.getppid()}-fanout-{index}")
    report.send("ready")
    cpu0, kept = _cpu(), 0
    while msg := notify.recv_bytes():
        slot, length = HEADER.unpack(msg)
        assert shm.buf is not None
        samples = np.frombuffer(shm.buf, np.float32, length // 4, slot * slot_bytes)  # read where it lies
        kept += samples.size > 0
        del samples
        credit.send([slot])
    report.send({"cpu_s": _cpu() - cpu0, "kept": kept})
    shm.close()


# ---- the run -------------------------------------------------------------------------------------
def _run_way(way: str, args: argparse.Namespace, endpoint: str) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    keys = _keys(args.channels)
    share = [0] * args.workers
    for n in range(args.blocks):
        share[worker_of(keys[n % args.channels], args.workers) - 1] += 1
    receivers: list[tuple[Any, Connection]] = []
    shm: list[Any] = []
    if way == "zenoh":
        for w in range(1, args.workers + 1):
            mine, theirs = ctx.Pipe()
            receivers.append(
                (ctx.Process(target=_zenoh_worker, args=(endpoint, w, args.workers, args.blocks, theirs)), mine)
            )
    else:
        slot_bytes, slots = 4 * args.block + 64, 256
        shm = [
            multiprocessing.shared_memory.SharedMemory(
                name=f"{os.getpid()}-fanout-{w}", create=True, size=slots * slot_bytes
            )
            for w in range(args.workers)
        ]
        rings = []
        for w in range(args.workers):
            n_read, n_write = ctx.Pipe(duplex=False)
            c_read, c_write = ctx.Pipe(duplex=False)
            rings.append((n_write, c_read))
            mine, theirs = ctx.Pipe()
            receivers.append((ctx.Process(target=_shm_worker, args=(w, slot_bytes, n_read, c_write, theirs)), mine))
        mine, theirs = ctx.Pipe()
        receivers.append(
            (
                ctx.Process(
                    target=_dispatcher, args=(endpoint, args.workers, slots, slot_bytes, args.blocks, rings, theirs)
                ),
                mine,
            )
        )
    for proc, conn in receivers:
        proc.start()
        assert conn.recv() == "ready"
    go, go_theirs = ctx.Pipe()
    publisher = ctx.Process(
        target=_publish, args=(endpoint, args.channels, args.block, args.blocks, args.rate, go_theirs)
    )
    publisher.start()
    assert go.recv() == "ready"
    t0, router0 = time.monotonic(), _cpu()
    go.send("go")
    results = [conn.recv() for _, conn in receivers]
    elapsed, router_cpu = time.monotonic() - t0, _cpu() - router0
    go.recv()
    go.send("stop")
    for proc, _ in [*receivers, (publisher, None)]:
        proc.join(30)
    for m in shm:
        m.close()
        m.unlink()
    cpu = sum(r["cpu_s"] for r in results)
    kept = sum(r.get("kept", 0) for r in results)
    return {
        "way": way,
        "blocks": args.blocks,
        "delivered": kept,
        "blocks_per_s": kept / elapsed,
        "receiver_cpu_us_per_block": 1e6 * cpu / args.blocks,
        "router_cpu_us_per_block": 1e6 * router_cpu / args.blocks,  # this process: the Zenoh router
        "total_cpu_us_per_block": 1e6 * (cpu + router_cpu) / args.blocks,
        "elapsed_s": elapsed,
    }


def run(args: argparse.Namespace) -> int:
    from sinewatch.clients.session import free_loopback_port, open_session
    from sinewatch.schemas.config import ZenohSection

    console = make_console()
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    console.print(
        f"fan-out of {args.blocks} blocks of {args.block} float32 samples over {args.channels} keys "
        f"to {args.workers} workers at {args.rate:g} blocks/s, both ways ..."
    )
    with open_session(ZenohSection(mode="router", listen=[endpoint], recovery=False)):
        rows = [_run_way(way, args, endpoint) for way in ("zenoh", "shm")]
    table = Table(title="sinewatch bench fanout")
    for col in ("way", "delivered", "blocks/s", "receivers' CPU us/block", "router's", "total", "total vs zenoh"):
        table.add_column(col, justify="right")
    base = rows[0]["total_cpu_us_per_block"]
    for r in rows:
        table.add_row(
            r["way"],
            f"{r['delivered']}/{r['blocks']}",
            f"{r['blocks_per_s']:.0f}",
            f"{r['receiver_cpu_us_per_block']:.1f}",
            f"{r['router_cpu_us_per_block']:.1f}",
            f"{r['total_cpu_us_per_block']:.1f}",
            f"{r['total_cpu_us_per_block'] / base:.2f}",
        )
    print_table(console, table)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0 if all(r["delivered"] == r["blocks"] for r in rows) else 1
