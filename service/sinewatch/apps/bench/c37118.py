"""``sinewatch bench c37118``: the daemon as a C37.118.2 PMU, and what its clients cost it.

Three runs of the same load (``sinewatch serve`` as its own process, ``--channels`` channels
of the ``pmu`` estimator fed in real time by the e2e bench's feeder, a station of the first
``--station-channels`` (default all) served on a free loopback port): no C37.118.2 client
(the baseline), one client reading every frame, and one client that turns data on and never
reads again; its frames fill its socket and write buffers (``client_buffer_bytes``) and its
queue, then are dropped and counted. Reported per run: block-to-estimate latency on Zenoh
(p50, p99, max; see :mod:`sinewatch.apps.bench.e2e`), estimates, data frames built, read and
dropped; and the latency ratios against the baseline measured in the same invocation. The
daemon must drop no input in any run: a client, reading or not, costs the estimation
nothing. (Estimate counts differ a little between runs: the feeder stamps each block with
its publish time, so the blocks' times, and the reporting grid's fill, follow its pacing.)
"""

from __future__ import annotations

import argparse
import json
import socket
import threading
import time
from typing import Any

import numpy as np
from rich.table import Table

from sinewatch.apps.bench.e2e import running_daemon
from sinewatch.apps.bench.e2e_feeder import start_feeder, stop_feeder
from sinewatch.apps.bench.e2e_probes import LatencyProbe
from sinewatch.apps.console import make_console
from sinewatch.clients import JsonSubscription, connect
from sinewatch.clients.c37118 import C37118Reader
from sinewatch.clients.session import free_loopback_port
from sinewatch.schemas.c37118 import Command, encode_command

ID_CODE = 1
MODES = ("no client", "reading client", "stalled client")


def run(args: argparse.Namespace) -> int:
    console = make_console()
    args.station_channels = args.station_channels or args.channels
    results = {mode: _measure(args, mode, console) for mode in MODES}
    base = results["no client"]
    for r in results.values():
        r["latency_p50_ratio"] = r["latency_ms_p50"] / base["latency_ms_p50"]
        r["latency_p99_ratio"] = r["latency_ms_p99"] / base["latency_ms_p99"]
    table = Table(title=f"C37.118.2 server: {args.channels} channels of pmu, a station of {args.station_channels}")
    table.add_column("")
    for mode in MODES:
        table.add_column(mode, justify="right")
    rows = (
        ("estimates on Zenoh", "estimates"),
        ("daemon drops (intake)", "daemon_dropped"),
        ("latency p50, ms", "latency_ms_p50"),
        ("latency p99, ms", "latency_ms_p99"),
        ("latency max, ms", "latency_ms_max"),
        ("p50 / no client", "latency_p50_ratio"),
        ("p99 / no client", "latency_p99_ratio"),
        ("data frames built", "frames_built"),
        ("frames read by the client", "frames_read"),
        ("frames dropped for the client", "frames_dropped"),
    )
    for label, key in rows:
        table.add_row(label, *(_fmt(results[m][key]) for m in MODES))
    console.print(table)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0 if all(r["daemon_dropped"] == 0 for r in results.values()) else 1


def _fmt(v: Any) -> str:
    return f"{v:.2f}" if isinstance(v, float) else str(v)


def _measure(args: argparse.Namespace, mode: str, console: Any) -> dict[str, Any]:
    fs, block, n_ch = args.rate, args.block, args.channels
    rounds = max(1, int(args.duration * fs / block))
    port = free_loopback_port()
    station = {
        "id_code": ID_CODE,
        "name": "BENCH",
        "channels": [f"bench/{i:04d}" for i in range(args.station_channels)],
        "time_synchronised": True,
    }
    extra = {"c37118": {"enabled": True, "port": port, "stations": [station]}}
    console.print(f"[bold]{mode}[/bold]: {n_ch} channels x {fs:g} Hz, {rounds * block / fs:.0f} s")
    with running_daemon(args, recording={"enabled": False}, extra=extra) as (endpoint, _daemon, _):
        with connect([endpoint], timeout_s=30.0) as session:
            status = JsonSubscription(session, "sinewatch/status/**")
            if status.get(timeout=60.0) is None:
                raise RuntimeError("the daemon did not come up within 60 s")
            probe = LatencyProbe(session, "sinewatch/est/**")
            reader, stalled, read = None, None, [0]
            if mode == "reading client":
                reader = C37118Reader("127.0.0.1", port, id_code=ID_CODE, timeout_s=60.0)
                reader.config()
                reader.start()

                def consume(r: C37118Reader = reader) -> None:
                    try:
                        for _ in r.data_frames():
                            read[0] += 1
                    except OSError:  # closed at the end of the run
                        return

                thread = threading.Thread(target=consume, daemon=True)
                thread.start()
            elif mode == "stalled client":
                stalled = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
                stalled.connect(("127.0.0.1", port))
                stalled.sendall(encode_command(ID_CODE, Command.DATA_ON))  # and never reads
            feeder, _ = start_feeder(endpoint, n_ch, fs, block, rounds)
            # drained: the daemon's Status says every block sent has been processed
            last: dict[str, Any] = {}
            deadline = time.monotonic() + 60.0
            while time.monotonic() < deadline and (msg := status.get(timeout=10.0)) is not None:
                last = msg
                if msg["blocks_processed"] >= rounds * n_ch:
                    break
            last = status.get(timeout=10.0) or last  # one more: the counters after the last frame
            stop_feeder(feeder)
            if reader is not None:
                reader.close()
            if stalled is not None:
                stalled.close()
            probe.close()
            status.close()
    lat = np.array(probe.latencies_ns) / 1e6
    c37 = last.get("c37118") or {}
    return {
        "estimates": probe.received,
        "daemon_dropped": last.get("dropped", -1),
        "latency_ms_p50": float(np.percentile(lat, 50)),
        "latency_ms_p99": float(np.percentile(lat, 99)),
        "latency_ms_max": float(lat.max()),
        "frames_built": c37.get("frames_built", 0),
        "frames_read": read[0] if mode == "reading client" else 0,
        "frames_dropped": c37.get("frames_dropped", 0),
    }
