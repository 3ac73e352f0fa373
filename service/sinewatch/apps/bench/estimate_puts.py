"""``sinewatch bench estimate-puts``: how a frame's estimates should leave the daemon.

One input frame of C channels gives C Estimates. Two ways to put them on Zenoh:

* ``per-channel``: one put per channel on ``sinewatch/est/<channel>`` (what the daemon
  does): any subscriber selects channels by key expression and receives only those;
* ``estimate frame``: one put per input frame, the C Estimates as one JSON array on one
  key: one put instead of C, but a subscriber gets every channel of the frame and must
  parse them all to find its own, and a key expression can no longer select a channel.

The publisher is this process (a peer session with declared publishers, as the daemon's
:class:`~sinewatch.outputs.publisher.ZenohPublisherSink`, CongestionControl.BLOCK); the subscriber
is its own process on loopback, reading each message as a client does (``json.loads``).
Two subscribers are measured: one that wants every channel (``sinewatch/est/**``) and one
that wants a single channel. Reported: CPU microseconds per estimate put on the daemon's
side (up to the subscriber's last estimate: Zenoh sends from its own threads after ``put``
returns) and per estimate the subscriber wants on its side (process CPU time, so that other
load on the machine counts less).
The payloads are real Estimates of the ``ges-kalman`` estimator on a 10 kHz frame.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from rich.table import Table

from sinewatch.apps.console import make_console, print_table
from sinewatch.clients import connect
from sinewatch.clients.session import free_loopback_port
from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.schemas.codec import ESTIMATE_JSON_ENCODING
from sinewatch.schemas.config import EstimatorRule, SinewatchConfig
from sinewatch.schemas.frame import Frame, encode_frame_binary

FRAME_KEY = "sinewatch/estf/f0"


def estimates(n_channels: int) -> list[tuple[str, bytes]]:
    """(key, payload) of the C Estimates one 1024-sample frame gives, from the pipeline."""
    from sinewatch.scenarios.demo import KALMAN_10K

    class Keep(NullSink):
        def __init__(self) -> None:
            self.out: list[tuple[str, bytes]] = []

        def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
            self.out.append((key, payload))

    keep = Keep()
    config = SinewatchConfig(
        rules=[EstimatorRule(match="sinewatch/in/**", estimator="ges-kalman", params=KALMAN_10K)],
        recording={"enabled": False},
    )
    names = tuple(f"bench/{c:04d}" for c in range(n_channels))
    t = np.arange(1024) / 10_000.0
    x = np.stack([np.sin(2 * np.pi * 50 * t + c) for c in range(n_channels)], axis=1)
    Pipeline(config, [keep]).process("sinewatch/in/f0", encode_frame_binary(Frame(names, 0, 0, 1e4, x)), "", 0)
    return keep.out


def subscriber_main(argv: list[str]) -> int:
    """The subscriber process: counts and parses what arrives until ``expected`` channel
    estimates are in, then prints its CPU time."""
    endpoint, key, mode, expected = argv[0], argv[1], argv[2], int(argv[3])
    with connect([endpoint]) as session:
        sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(4096))
        print("ready", flush=True)
        cpu0 = time.process_time()
        got = 0
        while got < expected:
            sample = sub.handler.recv()
            msg = json.loads(sample.payload.to_bytes())
            got += len(msg) if mode == "frame" else 1
        print(json.dumps({"cpu_s": time.process_time() - cpu0, "estimates": got}), flush=True)
    return 0


def _subscriber(endpoint: str, key: str, mode: str, expected: int) -> subprocess.Popen[str]:
    code = "import sys; from sinewatch.apps.bench.estimate_puts import subscriber_main; sys.exit(subscriber_main(sys.argv[1:]))"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, endpoint, key, mode, str(expected)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    if proc.stdout.readline().strip() != "ready":
        raise RuntimeError("bench estimate-puts: the subscriber did not start")
    return proc


def measure(n_channels: int, frames: int, mode: str, wanted: str, rate: float = 0.0) -> dict[str, Any]:
    """One run: ``frames`` input frames' estimates put as ``mode``, ``rate`` frames a second
    (0: back to back); the subscriber wants ``wanted`` ("all" or "one" channel). Paced as
    the daemon puts them, frame after frame as they come, Zenoh sends each frame's puts on
    their own instead of packing thousands into one batch: unpaced, a put looks ~10x
    cheaper than it is in the daemon."""
    outs = estimates(n_channels)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    conf = zenoh.Config()
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        if mode == "per-channel":
            key = "sinewatch/est/**" if wanted == "all" else outs[0][0]
            expected = frames * (n_channels if wanted == "all" else 1)
        else:
            key, expected = FRAME_KEY, frames * n_channels
        sub = _subscriber(endpoint, key, "frame" if mode == "frame" else "single", expected)
        enc = zenoh.Encoding(ESTIMATE_JSON_ENCODING)
        block = zenoh.CongestionControl.BLOCK
        if mode == "per-channel":
            pubs = [(session.declare_publisher(k, encoding=enc, congestion_control=block), p) for k, p in outs]
            _wait_matching(pubs[0][0] if wanted == "one" else pubs[-1][0])
        else:
            frame_pub = session.declare_publisher(
                FRAME_KEY, encoding=zenoh.Encoding("application/json"), congestion_control=block
            )
            _wait_matching(frame_pub)
        waiter = threading.Event()
        cpu0 = time.process_time()
        start = time.monotonic()
        for i in range(frames):
            delay = start + i / rate - time.monotonic() if rate > 0 else 0.0
            if delay > 0:  # frames due within a millisecond go out together, as the bench feeder's
                waiter.wait(max(delay, 0.001))
            if mode == "per-channel":
                for pub, payload in pubs:
                    pub.put(payload)
            else:  # the daemon would join its C payloads: that join is counted here too
                frame_pub.put(b"[" + b",".join(p for _, p in outs) + b"]")
        # Zenoh batches and sends on its own threads after put returns: the publisher's CPU
        # is counted until the subscriber has had every estimate, not when the loop ends
        out, _ = sub.communicate(timeout=300)
        pub_cpu = time.process_time() - cpu0
    got = json.loads(out.strip().splitlines()[-1])
    per = frames * n_channels
    return {
        "mode": mode,
        "subscriber_wants": wanted,
        "channels": n_channels,
        "frames": frames,
        "frames_per_s": rate,
        "publisher_us_per_estimate": 1e6 * pub_cpu / per,
        # per estimate the subscriber wants: all C of a frame, or the one channel's
        "subscriber_us_per_estimate": 1e6 * got["cpu_s"] / (per if wanted == "all" else frames),
        "puts_per_frame": n_channels if mode == "per-channel" else 1,
        "bytes_per_frame": sum(len(p) for _, p in outs) + (n_channels + 1 if mode == "frame" else 0),
    }


def _wait_matching(pub: Any, timeout_s: float = 20.0) -> None:
    matched = threading.Event()
    listener = pub.declare_matching_listener(lambda status: matched.set() if status.matching else None)
    try:
        if not (pub.matching_status.matching or matched.wait(timeout_s)):
            raise RuntimeError("bench estimate-puts: no subscriber matched")
    finally:
        listener.undeclare()


def run(args: argparse.Namespace) -> int:
    console = make_console()
    rows = [
        measure(args.channels, args.frames, mode, wanted, args.rate)
        for mode in ("per-channel", "frame")
        for wanted in ("all", "one")
    ]
    paced = f"{args.rate:g} frames/s" if args.rate > 0 else "unpaced"
    table = Table(
        title=f"sinewatch bench estimate-puts --channels {args.channels} (estimates of one input frame, {paced})"
    )
    for col in ("puts", "subscriber wants", "puts/frame", "bytes/frame", "daemon us/est", "subscriber us/wanted est"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            r["mode"],
            r["subscriber_wants"],
            str(r["puts_per_frame"]),
            str(r["bytes_per_frame"]),
            f"{r['publisher_us_per_estimate']:.2f}",
            f"{r['subscriber_us_per_estimate']:.2f}",
        )
    print_table(console, table)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0
