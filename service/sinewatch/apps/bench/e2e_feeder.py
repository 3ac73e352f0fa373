"""The publisher of ``sinewatch bench e2e`` and the benches built on it, run as its own
process (:func:`feeder_main`) so that publishing and measuring do not share a GIL:
real-time pacing, channels (or frames of channels) staggered over a block period, each
block stamped so that its last sample's time is its publish time (:func:`stamp_ns`)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from sinewatch.clients import BlockPublisher, connect

FEEDER_TICK_S = 0.001


def feeder_main(argv: list[str] | None = None) -> int:
    """The feeder's process: ``--channels`` channels ``bench/0000``... at ``--rate`` Hz in
    ``--block``-sample blocks for ``--rounds`` block periods, as single blocks or, with
    ``--frame-channels`` over 1, as SampleFrames of that many channels (:func:`frame_layout`).
    Prints what it did as one JSON line, then keeps its session until its stdin closes:
    blocks still in the session's send queue would be lost with it, and counted against
    the daemon."""
    p = argparse.ArgumentParser()
    p.add_argument("endpoint")
    p.add_argument("--channels", type=int)
    p.add_argument("--rate", type=float)
    p.add_argument("--block", type=int)
    p.add_argument("--rounds", type=int)
    p.add_argument("--frame-channels", type=int, default=1)
    a = p.parse_args(argv)
    fs = a.rate
    signals = _signals(a.channels, fs)
    with connect([a.endpoint]) as session:
        pub = BlockPublisher(session, prefix="sinewatch/in", dtype="float32")
        send = _frame_sender(pub, a, signals) if a.frame_channels > 1 else _block_sender(pub, a, signals)
        if send is None:
            return 2
        print(json.dumps(_pace(send, a.rounds, a.block, fs)), flush=True)
        sys.stdin.read()
        pub.close()
    return 0


# The units a round publishes (channels, or frames of channels) and how one goes out, from
# its index, the block's sample indices into the one-second signals and its first sample's time.
Send = tuple[int, Callable[[int, np.ndarray, int], None]]


def _signals(n_channels: int, fs: float) -> list[np.ndarray]:
    """One second of each channel's signal (50 Hz at a random phase, 1 % noise; seeded), as
    float64: blocks are cut from it cyclically."""
    t = np.arange(int(fs)) / fs
    rng = np.random.default_rng(0)
    return [
        np.sin(2 * np.pi * 50.0 * t + rng.uniform(0, 6.28)) + 0.01 * rng.standard_normal(t.size)
        for _ in range(n_channels)
    ]


def _block_sender(pub: BlockPublisher, a: argparse.Namespace, signals: list[np.ndarray]) -> Send | None:
    """Each channel's block alone; None when the daemon does not subscribe within 30 s."""
    base = [s.astype(np.float32) for s in signals]  # float32, as sent: no conversion per block
    channels = [f"bench/{i:04d}" for i in range(a.channels)]
    if not pub.wait_for_subscriber(channels[0], 30.0):
        return None

    def send(c: int, idx: np.ndarray, t0_ns: int) -> None:
        pub.publish_raw(channels[c], pub.encode(pub.block(channels[c], base[c][idx], a.rate, t0_ns=t0_ns)))

    return len(channels), send


def _frame_sender(pub: BlockPublisher, a: argparse.Namespace, signals: list[np.ndarray]) -> Send | None:
    """The channels as frames of ``--frame-channels``; None when the daemon does not subscribe."""
    layout = frame_layout(a.channels, a.frame_channels)
    per = a.frame_channels  # frame k holds channels k * per ... (frame_layout)
    base = [np.stack(signals[i : i + per], axis=1).astype(np.float32) for i in range(0, a.channels, per)]  # as sent
    frames = [f"f{k:04d}" for k in range(len(layout))]
    if not pub.wait_for_frame_subscriber(frames[0], 30.0):
        return None

    def send(k: int, idx: np.ndarray, t0_ns: int) -> None:
        fr = pub.frame(frames[k], layout[k], base[k][idx], a.rate, t0_ns=t0_ns)
        pub.publish_frame_raw(frames[k], pub.encode_frame(fr))

    return len(frames), send


def _pace(send: Send, rounds: int, block: int, fs: float) -> dict[str, float]:
    """Publish ``rounds`` block periods in real time, the units staggered evenly over each
    period (as independent sensors would be); each stamped by :func:`stamp_ns`."""
    n_units, publish = send
    period = block / fs
    period_ns = block * 1e9 / fs
    span_ns = round((block - 1) * 1e9 / fs)
    waiter = threading.Event()
    late = 0
    start_ns = time.monotonic_ns()
    start = start_ns / 1e9
    cpu0 = time.process_time()
    for r in range(rounds):
        idx = ((r * block) % int(fs) + np.arange(block)) % int(fs)
        for k in range(n_units):
            delay = start + (r + k / n_units) * period - time.monotonic()
            if delay > 0:  # units due within a tick go out together: a wake-up per block costs more CPU than the block
                waiter.wait(max(delay, FEEDER_TICK_S))
            elif delay < -period:
                late += 1
            due_ns = start_ns + round((r + k / n_units) * period_ns)
            publish(k, idx, stamp_ns(due_ns, period_ns) - span_ns)
    return {"elapsed_s": time.monotonic() - start, "late_blocks": late, "cpu_s": time.process_time() - cpu0}


def stamp_ns(due_ns: int, period_ns: float, now_ns: int | None = None) -> int:
    """The time a block's last sample is stamped with: its publish time (now), but never
    more than a quarter of a block period (at most 10 ms) after it was due. A sensor's
    clock does not wait for a backed-up network: a feeder held back by the daemon
    (CongestionControl.BLOCK) that stamped its publish time would move each channel's
    time on by more than half a block between two blocks, which the daemon rightly takes
    for a time jump and starts the channel over for, every block. On time, the
    latency is measured from the publish; late, from the schedule, delay included."""
    now = time.monotonic_ns() if now_ns is None else now_ns
    return min(now, due_ns + round(min(0.25 * period_ns, 10e6)))


def frame_layout(n_channels: int, per_frame: int) -> list[list[str]]:
    """The bench's channels ``bench/0000``... cut into frames of ``per_frame`` (the last may
    hold fewer): frame k is published on ``sinewatch/in/f<k>``, so its channels' keys are
    ``sinewatch/in/bench/<i>``, the keys they have as single blocks."""
    names = [f"bench/{i:04d}" for i in range(n_channels)]
    return [names[i : i + per_frame] for i in range(0, n_channels, per_frame)]


def start_feeder(
    endpoint: str, channels: int, rate: float, block: int, rounds: int, frame_channels: int = 1
) -> tuple[subprocess.Popen[str], str]:
    """Start the bench feeder process and wait for its first line (what it published);
    the feeder keeps its session until its stdin is closed."""
    feeder = subprocess.Popen(
        [*feeder_command(endpoint, channels, rate, block, rounds), "--frame-channels", str(frame_channels)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert feeder.stdin is not None and feeder.stdout is not None
    line = feeder.stdout.readline()
    if not line:
        raise RuntimeError(f"bench feeder failed: {feeder.communicate()[1][-2000:]}")
    return feeder, line


def stop_feeder(feeder: subprocess.Popen[str]) -> None:
    """Let the feeder close its session (it waits on its stdin) and end."""
    assert feeder.stdin is not None
    feeder.stdin.close()
    feeder.wait()


def feeder_command(endpoint: str, channels: int, rate: float, block: int, rounds: int) -> list[str]:
    """The bench feeder (:func:`feeder_main`) as its own process."""
    return [
        sys.executable,
        "-c",
        "import sys; from sinewatch.apps.bench.e2e_feeder import feeder_main; sys.exit(feeder_main(sys.argv[1:]))",
        endpoint,
        "--channels",
        str(channels),
        "--rate",
        str(rate),
        "--block",
        str(block),
        "--rounds",
        str(rounds),
    ]
