"""``sinewatch bench soak`` (``make soak``): hours of load, with recording rotation, watched.

The daemon runs as its own process (as in ``bench e2e``), fed in real time through Zenoh on
loopback by the bench feeder, recording with a new file every ``--rotate-seconds``. Every
``--interval`` seconds a line reports the daemon's RSS and open file descriptors and the
block-to-estimate latency percentiles of that interval. At the end: RSS growth after
warm-up, which must stay under 5 %, and, with matplotlib installed, the RSS curve as a PNG.

Warm-up is the first recording file: besides numba's caches and the buffers filling, an
MCAP writer keeps its file's chunk index in memory until the file is finished, so RSS
rises through each file and falls back at each rotation (a sawtooth whose height is set by
``recording.rotate_seconds``/``rotate_bytes``). Growth is the highest RSS after the first
rotation relative to the first sample after it: a leak shows as a rising floor.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from sinewatch.apps.bench.e2e import running_daemon
from sinewatch.apps.bench.e2e_feeder import feeder_command
from sinewatch.apps.bench.e2e_probes import LatencyProbe, rss_mb
from sinewatch.apps.console import make_console
from sinewatch.clients import JsonSubscription, connect
from sinewatch.schemas.errors import ConfigError

GROWTH_LIMIT = 0.05


def run(args: argparse.Namespace) -> int:
    if args.duration < args.interval:  # no RSS line at all: nothing to report
        raise ConfigError(f"--duration: expected at least --interval ({args.interval:g} s), got {args.duration:g} s")
    console = make_console()
    rounds = max(1, int(args.duration * args.rate / args.block))
    samples: list[dict[str, Any]] = []
    recording = {"rotate_seconds": args.rotate_seconds, "rotate_bytes": None}
    with running_daemon(args, recording) as (endpoint, daemon, rec), connect([endpoint], timeout_s=30.0) as session:
        with JsonSubscription(session, "sinewatch/status/**") as status:
            if status.get(timeout=60.0) is None:
                raise RuntimeError("the daemon did not come up within 60 s")
        probe = LatencyProbe(session, "sinewatch/est/**")
        console.print(
            f"soak: {args.channels} ch x {args.rate:g} Hz ({args.channels * args.rate / 1e6:.2f} M samples/s) "
            f"for {args.duration:g} s, a new recording every {args.rotate_seconds:g} s, a line every {args.interval:g} s"
        )
        feeder = subprocess.Popen(
            feeder_command(endpoint, args.channels, args.rate, args.block, rounds),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert feeder.stdin is not None and feeder.stdout is not None
        fed = threading.Event()  # set once the feeder says it has published everything
        out = feeder.stdout

        def wait_for_feeder() -> None:
            out.readline()
            fed.set()

        threading.Thread(target=wait_for_feeder, daemon=True).start()
        start, seen = time.monotonic(), 0
        while not fed.is_set():
            if fed.wait(args.interval):
                break
            window = np.array(probe.latencies_ns[seen:]) / 1e6
            seen += window.size
            sample = {
                "t_s": round(time.monotonic() - start, 1),
                "rss_mb": rss_mb(daemon.pid),
                "open_fds": len(os.listdir(f"/proc/{daemon.pid}/fd")),
                "estimates": int(window.size),
                "latency_ms_p50": float(np.percentile(window, 50)) if window.size else None,
                "latency_ms_p99": float(np.percentile(window, 99)) if window.size else None,
                "latency_ms_max": float(window.max()) if window.size else None,
            }
            samples.append(sample)
            console.print(
                f"t={sample['t_s']:7.1f} s  RSS {sample['rss_mb']:7.1f} MB  fds {sample['open_fds']:4d}  "
                f"estimates {sample['estimates']:7d}  latency p50 {sample['latency_ms_p50'] or 0:.2f} "
                f"p99 {sample['latency_ms_p99'] or 0:.2f} max {sample['latency_ms_max'] or 0:.2f} ms"
            )
        feeder.stdin.close()
        feeder.wait()
        probe.close()
    growth = _growth(samples, args.rotate_seconds)
    result = {"samples": samples, "rss_growth_after_warmup": growth, "recorded_bytes": rec.recorded_bytes}
    console.print(
        f"RSS growth after warm-up: {100 * growth:.1f} % (limit {100 * GROWTH_LIMIT:.0f} %); "
        f"recorded {rec.recorded_bytes / 1e9:.2f} GB"
    )
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    if args.plot:
        _plot(samples, args.plot, args.rotate_seconds)
        console.print(f"RSS curve: {args.plot}")
    return 0 if growth < GROWTH_LIMIT else 1


def _growth(samples: list[dict[str, Any]], warm_up_s: float) -> float:
    """Highest RSS after warm-up relative to the first sample after it."""
    after = [s["rss_mb"] for s in samples if s["t_s"] >= warm_up_s] or [s["rss_mb"] for s in samples]
    return float((max(after) - after[0]) / after[0])


def _plot(samples: list[dict[str, Any]], path: Path, warm_up_s: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [s["t_s"] / 60 for s in samples]
    rss = [s["rss_mb"] for s in samples]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.plot(t, rss, marker="o", ms=3, label="RSS")
    after = [r for s, r in zip(samples, rss, strict=True) if s["t_s"] >= warm_up_s]
    if after:  # the pass band: within 5 % of the first sample after warm-up
        ax.axhspan(after[0], after[0] * (1 + GROWTH_LIMIT), color="tab:green", alpha=0.12, label="+5 % after warm-up")
        ax.axvline(warm_up_s / 60, color="grey", lw=0.8, ls="--")
    ax.set_ylim(0, max(rss) * 1.15)
    ax.legend(loc="lower right")
    ax.set_xlabel("minutes")
    ax.set_ylabel("daemon RSS, MB")
    ax.set_title("sinewatch bench soak: RSS under constant load")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
