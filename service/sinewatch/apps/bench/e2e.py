"""``sinewatch bench e2e``: the daemon, fed through real Zenoh on loopback, recording on.

The daemon runs as its own process (``sinewatch serve``) with a peer session on a free
loopback port and recording to a temporary directory. This process publishes
``channels`` channels at ``rate`` Hz in ``block``-sample blocks, paced in real time with
the channels staggered evenly over a block period (as independent sensors would be), and
subscribes to the estimates. Latency is block-to-estimate: the feeder (its own process) stamps
each block so that its last sample's time is its publish time on CLOCK_MONOTONIC, which
is system-wide (or, for a block published more than a quarter period late, its scheduled
time: :func:`sinewatch.apps.bench.e2e_feeder.stamp_ns`), and the estimate's arrival is measured on the same clock. Reported: offered and sustained samples/s, estimates missing, the
daemon's own drop and error counters, latency p50/p99/max, and the daemon's CPU use.

With ``--foxglove`` the daemon also serves its live Foxglove view and a client here
(:class:`sinewatch.apps.bench.e2e_probes.FoxgloveProbe`, the protocol over ``websockets``) subscribes to every topic it
advertises (estimates, input summaries, status, log): the cost of a watched daemon. Run it
with and without the flag at an offer above what the daemon sustains (``--channels``) to
compare throughput.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from sinewatch.apps.bench.e2e_feeder import frame_layout, start_feeder, stop_feeder
from sinewatch.apps.bench.e2e_probes import FoxgloveProbe, LatencyProbe, cpu_seconds, main_thread_times, rss_mb
from sinewatch.apps.console import make_console, print_table
from sinewatch.clients import JsonSubscription, connect
from sinewatch.clients.session import free_loopback_port


def expected_daemons(args: argparse.Namespace) -> int:
    """How many daemons (worker processes) publish Status: ``--workers``, 0 = one per core."""
    workers = getattr(args, "workers", 1)
    return workers if workers > 0 else max(1, len(os.sched_getaffinity(0)))


DAEMON_START_S = 120.0  # how long the daemon may take to listen (start, warm-up) before the run fails
SWEEP_CHANNELS = (1, 10, 100, 1000, 5000)
SWEEP_DURATION_S = 20.0
SINGLE_DURATION_S = 60.0


def frame_channel_counts(args: argparse.Namespace) -> list[int]:
    """``--frame-channels N[,N...]`` as a list (1: one SampleBlock per channel)."""
    text = str(getattr(args, "frame_channels", "1"))
    try:
        counts = [int(v) for v in text.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        from sinewatch.schemas.errors import SinewatchError

        raise SinewatchError(f"--frame-channels: expected N[,N...] with every N >= 1, got {text!r}")
    return counts


def run(args: argparse.Namespace) -> int:
    console = make_console()
    counts = frame_channel_counts(args)
    if getattr(args, "sweep", False):
        code = 0
        for n in counts:
            point = {"frame_channels": n}
            if len(counts) > 1 and args.json:  # one JSON (and plot) per frame size
                point["json"] = args.json.with_name(f"{args.json.stem}-frame{n}{args.json.suffix}")
            if len(counts) > 1 and getattr(args, "plot", None):
                point["plot"] = args.plot.with_name(f"{args.plot.stem}-frame{n}{args.plot.suffix}")
            code |= run_sweep(argparse.Namespace(**{**vars(args), **point}), console)
        return code
    if args.duration is None:
        args.duration = SINGLE_DURATION_S
    results = []
    for n in counts:
        result = measure(argparse.Namespace(**{**vars(args), "frame_channels": n}), console)
        _print(console, result)
        results.append(result)
    if len(results) > 1:
        print_table(console, sweep_table(results, "sinewatch bench e2e --frame-channels (recording on)"))
    if args.json:
        args.json.write_text(json.dumps(results[0] if len(results) == 1 else {"runs": results}, indent=2))
    ok = all(r["missing_estimates"] == 0 and r["daemon_dropped"] == 0 for r in results)
    return 0 if ok else 1


def run_sweep(args: argparse.Namespace, console: Console) -> int:
    """``bench e2e --sweep``: the same measurement at 1, 10, 100, 1,000 and 5,000 channels,
    and on, doubling, while the daemon still sustains the last point (or exactly at
    ``--sweep-channels``), a table, the highest rate sustained, the JSON (``--json``) and a plot of sustained throughput
    and p99 latency against channels (``--plot``; needs matplotlib, the ``plots`` extra)."""
    counts = [int(c) for c in args.sweep_channels.split(",")] if args.sweep_channels else list(SWEEP_CHANNELS)
    extend = not args.sweep_channels  # the default sweep goes on until the daemon saturates
    duration = args.duration if args.duration is not None else SWEEP_DURATION_S
    rows: list[dict[str, Any]] = []
    n = counts[0]
    while n:
        point = argparse.Namespace(**{**vars(args), "channels": n, "duration": duration, "foxglove": False})
        row = measure(point, console)
        if rows:  # memory per channel: the slope from the point before (fixed costs cancel)
            prev = rows[-1]
            row["daemon_rss_mb_per_channel"] = (row["daemon_rss_mb_end"] - prev["daemon_rss_mb_end"]) / (
                n - prev["channels"]
            )
        _print(console, row)
        rows.append(row)
        n = next_sweep_point(counts, rows, extend=extend)
    highest = max((r for r in rows if sustained(r)), key=lambda r: r["offered_samples_per_s"], default=None)
    table = sweep_table(rows, f"sinewatch bench e2e --sweep --frame-channels {frame_channels(args)} (recording on)")
    print_table(console, table)
    console.print(
        "highest rate sustained (>= 99 % of offered, 0 missing): "
        + ("none" if highest is None else f"{highest['offered_samples_per_s'] / 1e6:.3f} M samples/s")
    )
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "sweep": rows,
                    "highest_sustained_samples_per_s": None if highest is None else highest["offered_samples_per_s"],
                },
                indent=2,
            )
        )
    plot = args.plot or (args.json.with_suffix(".png") if args.json else None)
    if plot is not None:
        try:
            plot_sweep(rows, plot, frame_channels(args))
            console.print(f"plot: {plot}")
        except ModuleNotFoundError as exc:
            console.print(f"no plot ({exc.name} is not installed: pip install 'sinewatch[plots]')")
    return 0


SWEEP_MAX_CHANNELS = 64_000  # 640 M samples/s at 10 kHz: past any saturation on a few cores


def sustained(row: dict[str, Any]) -> bool:
    """The daemon kept up: every estimate came, at >= 99 % of the offered rate."""
    return bool(row["missing_estimates"] == 0 and row["sustained_samples_per_s"] >= 0.99 * row["offered_samples_per_s"])


def next_sweep_point(counts: list[int], rows: list[dict[str, Any]], *, extend: bool = True) -> int:
    """The channel count after the last measured one: the next listed, then (``extend``, while
    the daemon still sustains the last point) twice the last, until it saturates; 0 to stop."""
    done = len(rows)
    if done < len(counts):
        return counts[done]
    last = rows[-1]
    if extend and sustained(last) and last["channels"] * 2 <= SWEEP_MAX_CHANNELS:
        return int(last["channels"] * 2)
    return 0


def frame_channels(args: argparse.Namespace) -> int:
    return int(getattr(args, "frame_channels", 1) or 1)


def sweep_table(rows: list[dict[str, Any]], title: str = "sinewatch bench e2e --sweep (recording on)") -> Table:
    table = Table(title=title)
    for col in (
        "channels",
        "per msg",
        "offered M/s",
        "fed M/s",
        "sustained M/s",
        "sustained/offered",
        "missing",
        "p50 ms",
        "p99 ms",
        "CPU (cores)",
        "daemon ns/sample",
        "of which estimator",
        "CPU us/block daemon+feeder+probe",
        "cores needed at offered",
        "RSS MB",
        "RSS/channel kB (slope)",
    ):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            str(r["channels"]),
            str(r.get("frame_channels", 1)),
            f"{r['offered_samples_per_s'] / 1e6:.3f}",
            f"{r['fed_samples_per_s'] / 1e6:.3f}",
            f"{r['sustained_samples_per_s'] / 1e6:.3f}",
            f"{r['sustained_samples_per_s'] / r['offered_samples_per_s']:.3f}",
            str(r["missing_estimates"]),
            _ms(r["latency_ms_p50"]),
            _ms(r["latency_ms_p99"]),
            f"{r['daemon_cpu_fraction_of_one_core']:.2f}",
            f"{r['daemon_cpu_ns_per_sample']:.0f}",
            f"{r['kernel_ns_per_sample']:.0f}" if "kernel_ns_per_sample" in r else "-",
            "+".join(f"{v:.0f}" for v in r["cpu_us_per_block"].values()),
            f"{r['cores_needed_at_offered']:.2f} of {r['machine_cores']}",
            f"{r['daemon_rss_mb_end']:.0f}",
            f"{1e3 * r['daemon_rss_mb_per_channel']:.1f}" if "daemon_rss_mb_per_channel" in r else "-",
        )
    return table


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def plot_sweep(rows: list[dict[str, Any]], path: Path, per_msg: int = 1) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    channels = [r["channels"] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    ax.plot(channels, [r["offered_samples_per_s"] / 1e6 for r in rows], "k--", lw=0.8, label="offered")
    ax.plot(channels, [r["sustained_samples_per_s"] / 1e6 for r in rows], "o-", label="sustained")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("channels (10 kHz each, 1024-sample blocks)")
    ax.set_ylabel("M samples/s")
    lat = ax.twinx()
    lat.plot(channels, [r["latency_ms_p99"] or float("nan") for r in rows], "s-", color="tab:red", label="p99 latency")
    lat.set_yscale("log")
    lat.set_ylabel("p99 block-to-estimate latency, ms", color="tab:red")
    lines = [*ax.get_lines(), *lat.get_lines()]
    ax.legend(lines, [str(line.get_label()) for line in lines], loc="upper left", fontsize=8)
    highest = max((r for r in rows if sustained(r)), key=lambda r: r["offered_samples_per_s"], default=None)
    ax.set_title(
        f"sinewatch bench e2e --sweep --frame-channels {per_msg}: highest sustained with 0 missing "
        + ("none" if highest is None else f"{highest['offered_samples_per_s'] / 1e6:.2f} M samples/s"),
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def measure(args: argparse.Namespace, console: Console) -> dict[str, Any]:
    """Run the daemon as its own process, feed it, and return the figures."""
    kernel_ns = kernel_ns_per_sample(args.estimator, args.rate, args.block, frame_channels(args))
    with running_daemon(args) as (endpoint, daemon, tmp):
        result = _drive(args, endpoint, daemon, console)
    result["recorded_bytes"] = tmp.recorded_bytes
    result["daemon_exit_code"] = daemon.returncode
    # what of the daemon's CPU is the estimator's arithmetic, and what is plumbing around it
    result["kernel_ns_per_sample"] = kernel_ns
    result["plumbing_ns_per_sample"] = result["daemon_cpu_ns_per_sample"] - kernel_ns
    return result


KERNEL_REPEATS = 7


def kernel_ns_per_sample(estimator: str, rate: float, block: int, per_msg: int) -> float:
    """CPU nanoseconds a sample costs the estimator alone, as the daemon calls it: ``update``
    (``last_only``) of one channel's block, or, for frames of ``per_msg`` channels, one
    :func:`~sinewatch.estimators.bank.update_bank` call on the frame's float64 columns.
    Measured here, before the daemon starts (the fastest of a few repeats of about 50 blocks
    a channel, process CPU time), on the bench's own signal."""
    from sinewatch.estimators import get
    from sinewatch.estimators.bank import update_bank

    cls = get(estimator)
    params = _params(argparse.Namespace(estimator=estimator))
    estimators = [cls(rate, params) for _ in range(per_msg)]
    rng = np.random.default_rng(0)
    t = np.arange(block) / rate
    x = np.stack(
        [np.sin(2 * np.pi * 50.0 * t + rng.uniform(0, 6.28)) + 0.01 * rng.standard_normal(block) for _ in estimators],
        axis=1,
    )
    rounds = max(2, 50 // per_msg)
    best = float("inf")
    for repeat in range(KERNEL_REPEATS + 1):  # the first loads the compiled kernels
        t0 = time.process_time()
        for _ in range(rounds if repeat else 1):
            if per_msg == 1:
                estimators[0].update(x[:, 0], last_only=True)
            else:
                update_bank(estimators, x, last_only=True)
        if repeat:
            best = min(best, (time.process_time() - t0) / (rounds * block * per_msg))
    return 1e9 * best


class _Recording:
    recorded_bytes = 0


@contextlib.contextmanager
def running_daemon(
    args: argparse.Namespace, recording: dict[str, Any] | None = None, extra: dict[str, Any] | None = None
) -> Iterator[tuple[str, subprocess.Popen[bytes], _Recording]]:
    """``sinewatch serve`` as its own process on a free loopback port, recording to a
    temporary directory; stopped with SIGINT (drain, finish the file) on exit. ``extra``:
    more config sections (e.g. ``c37118``)."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    rec = _Recording()
    with tempfile.TemporaryDirectory(prefix="sinewatch-bench-") as tmp:
        config = {
            "daemon_id": "bench",
            "zenoh": {"listen": [endpoint]},
            "rules": [{"match": "sinewatch/in/**", "estimator": args.estimator, "params": _params(args)}],
            "recording": {"directory": str(Path(tmp) / "rec"), **(recording or {})},
            "limits": {"queue_policy": args.queue_policy, "queue_capacity": args.queue_capacity},
            "workers": {"count": getattr(args, "workers", 1)},
            "status_interval_s": 1.0,
            # the hold makes every estimate wait a block for its confirmation (docs/benchmarks.md,
            # "The hold and a 5 ms p99"): --no-hold measures the latency without it
            "hold_estimates": not getattr(args, "no_hold", False),
            "report_in_block": getattr(args, "report_in_block", False),
            **(extra or {}),
        }
        if getattr(args, "foxglove", False):
            args.foxglove_port = free_loopback_port()
            config["foxglove"] = {"port": args.foxglove_port}
        cfg_path = Path(tmp) / "bench.json"
        cfg_path.write_text(json.dumps(config))
        # The daemon's log goes to a file: a pipe nobody reads fills up (64 KiB) and then
        # blocks the daemon's first log line after it, which once looked like a daemon stall.
        log_file = open(Path(tmp) / "daemon.log", "wb")
        daemon = subprocess.Popen(
            [sys.executable, "-m", "sinewatch", "serve", "--config", str(cfg_path)],
            stdout=subprocess.DEVNULL,
            stderr=log_file,
        )
        try:
            yield endpoint, daemon, rec
        finally:
            if daemon.poll() is None:
                daemon.send_signal(signal.SIGINT)
                try:
                    daemon.wait(60)
                except subprocess.TimeoutExpired:
                    daemon.kill()
            log_file.close()
            rec.recorded_bytes = sum(f.stat().st_size for f in (Path(tmp) / "rec").glob("*.mcap"))


def _params(args: argparse.Namespace) -> dict[str, Any]:
    if args.estimator == "ges-kalman":
        from sinewatch.scenarios.demo import KALMAN_10K

        return KALMAN_10K
    return {}


def _drive(
    args: argparse.Namespace, endpoint: str, daemon: subprocess.Popen[bytes], console: Console
) -> dict[str, Any]:
    fs, block, n_ch = args.rate, args.block, args.channels
    per_msg = frame_channels(args)
    rounds = max(1, int(args.duration * fs / block))
    # The daemon listens once it has started and warmed up its kernels: on a loaded machine
    # (the benches run beside other work) that took over 30 s, and the run failed to connect.
    with connect([endpoint], timeout_s=DAEMON_START_S) as session:
        status = JsonSubscription(session, "sinewatch/status/**")
        wait_for_daemons(status, expected_daemons(args))
        probe = LatencyProbe(session, "sinewatch/est/**")
        probe.expected = rounds * n_ch
        fox = FoxgloveProbe(args.foxglove_port) if getattr(args, "foxglove", False) else None
        console.print(
            f"offering {n_ch} channels x {fs:g} Hz in {block}-sample blocks"
            + (f", {per_msg} channels a frame" if per_msg > 1 else "")
            + f" ({n_ch * fs / 1e6:.2f} M samples/s) for {rounds * block / fs:.1f} s ..."
        )
        load0 = os.getloadavg()[0]  # the machine's load: what a loaded run's figures must be read with
        cpu0 = cpu_seconds(daemon.pid)
        sched0 = main_thread_times(daemon.pid)
        rss0 = rss_mb(daemon.pid)
        probe_cpu0 = time.process_time()  # this process: the probe's Zenoh threads and parsing
        t0 = time.monotonic()
        feeder, line = start_feeder(endpoint, n_ch, fs, block, rounds, per_msg)
        fed = json.loads(line)
        probe.done.wait(30.0)
        stop_feeder(feeder)  # everything published has had its chance to arrive
        drained_s = time.monotonic() - t0
        cpu = cpu_seconds(daemon.pid) - cpu0
        sched1 = main_thread_times(daemon.pid)
        probe_cpu = time.process_time() - probe_cpu0
        rss1 = rss_mb(daemon.pid)
        # Each daemon (worker) publishes Status every second: drop the backlog, then take a
        # fresh one from each and add them up.
        while status.get(timeout=0) is not None:
            pass
        last_status = latest_statuses(status, expected_daemons(args))
        probe.close()
        status.close()
        if fox is not None:
            fox.close()
    lat = np.array(probe.latencies_ns) / 1e6
    sent = rounds * n_ch
    budget = cpu_budget(
        daemon_cpu_s=cpu, feeder_cpu_s=fed["cpu_s"], probe_cpu_s=probe_cpu, blocks=sent, estimates=probe.received
    )
    return {
        "channels": n_ch,
        "frame_channels": per_msg,
        "messages_sent": rounds * len(frame_layout(n_ch, per_msg)),
        "sample_rate_hz": fs,
        "block": block,
        "duration_s": round(fed["elapsed_s"], 2),
        "offered_samples_per_s": n_ch * fs,
        # n blocks a channel span n block periods (the feeder's clock spans n - 1 of them)
        "sustained_samples_per_s": probe.received * block / max(fed["elapsed_s"], rounds * block / fs),
        "fed_samples_per_s": sent
        * block
        / max(fed["elapsed_s"], rounds * block / fs),  # below offered: the feeder could not keep up
        "blocks_sent": sent,
        "estimates_received": probe.received,
        "missing_estimates": sent - probe.received,
        "feeder_late_blocks": fed["late_blocks"],
        "feeder_cpu_fraction_of_one_core": fed["cpu_s"] / fed["elapsed_s"],
        "daemon_dropped": last_status.get("dropped", -1),
        "daemon_errors": last_status.get("errors", -1),
        "daemon_backpressure_waits": last_status.get("backpressure_waits", -1),
        "latency_ms_p50": float(np.percentile(lat, 50)) if lat.size else None,
        "latency_ms_p99": float(np.percentile(lat, 99)) if lat.size else None,
        "latency_ms_max": float(lat.max()) if lat.size else None,
        "daemon_cpu_fraction_of_one_core": cpu / drained_s,
        # the daemon's event loop over the run: on a CPU, ready but waiting for one (the machine
        # is short of CPU), and the rest asleep (held back by a put, the GIL, or no input)
        "daemon_loop_running_fraction": (sched1[0] - sched0[0]) / 1e9 / drained_s,
        "daemon_loop_runqueue_fraction": (sched1[1] - sched0[1]) / 1e9 / drained_s,
        "daemon_loop_asleep_fraction": 1.0 - (sched1[0] - sched0[0] + sched1[1] - sched0[1]) / 1e9 / drained_s,
        "queue_policy": args.queue_policy,
        "hold_estimates": not getattr(args, "no_hold", False),
        "report_in_block": getattr(args, "report_in_block", False),
        "estimates_flagging_a_gap": probe.gaps,
        "gap_blocks_flagged": probe.gap_blocks,
        "daemon_rss_mb_start": rss0,
        "daemon_rss_mb_end": rss1,
        "daemon_rss_mb_growth_per_channel": (rss1 - rss0) / n_ch,  # fixed costs too: --sweep gives the slope
        "workers": expected_daemons(args),
        "drained_s": drained_s,
        "foxglove_messages": dict(sorted(fox.messages.items())) if fox is not None else None,
        "foxglove_bytes": fox.bytes if fox is not None else None,
        "cpu_us_per_block": budget,
        # the daemon's CPU (every thread) per sample estimated: comparable across frame sizes
        "daemon_cpu_ns_per_sample": 1e9 * cpu / max(probe.received * block, 1),
        # the CPU the three processes need for the offered load at this run's cost per block
        "cores_needed_at_offered": sum(budget.values()) * n_ch * fs / block / 1e6,
        "machine_cores": len(os.sched_getaffinity(0)),
        # the 1-minute load average as the feeding started and as the estimates drained
        "load_average_start": load0,
        "load_average_end": os.getloadavg()[0],
    }


def cpu_budget(
    *, daemon_cpu_s: float, feeder_cpu_s: float, probe_cpu_s: float, blocks: int, estimates: int
) -> dict[str, float]:
    """CPU microseconds a block costs each process of the bench: the daemon (all its
    threads, Zenoh's included, from the first block to the last estimate), the feeder
    (encoding and publishing) and this process's probe (receiving and parsing the estimate).
    Times the offered blocks/s, their sum is the CPU the offered load needs on this machine,
    whatever the daemon sustained: a daemon that cannot keep up is told apart from a machine
    that cannot hold the load."""
    per_estimate = max(estimates, 1)
    return {
        "daemon": 1e6 * daemon_cpu_s / per_estimate,
        "feeder": 1e6 * feeder_cpu_s / max(blocks, 1),
        "probe": 1e6 * probe_cpu_s / per_estimate,
    }


def wait_for_daemons(status: JsonSubscription, count: int, timeout_s: float = 90.0) -> None:
    """Wait until ``count`` daemons (the workers) have published a Status: all are serving."""
    seen: set[str] = set()
    deadline = time.monotonic() + timeout_s
    while len(seen) < count:
        msg = status.get(timeout=max(0.0, deadline - time.monotonic()))
        if msg is None:
            raise RuntimeError(f"expected {count} daemon(s) serving within {timeout_s:g} s, got {len(seen)}")
        seen.add(msg["daemon_id"])


def latest_statuses(status: JsonSubscription, count: int) -> dict[str, int]:
    """The next Status of each of ``count`` daemons, their counters added up (-1: none came)."""
    latest: dict[str, dict[str, Any]] = {}
    deadline = time.monotonic() + 5.0
    while len(latest) < count:
        msg = status.get(timeout=max(0.0, deadline - time.monotonic()))
        if msg is None:
            break
        latest[msg["daemon_id"]] = msg
    if not latest:
        return {}
    return {k: sum(m[k] for m in latest.values()) for k in ("dropped", "errors", "backpressure_waits")}


def _print(console: Console, r: dict[str, Any]) -> None:
    console.print(
        (f"frames of {r['frame_channels']} channels: " if r.get("frame_channels", 1) > 1 else "")
        + f"sustained {r['sustained_samples_per_s'] / 1e6:.3f} M samples/s "
        f"(offered {r['offered_samples_per_s'] / 1e6:.3f} M, ratio {r['sustained_samples_per_s'] / r['offered_samples_per_s']:.3f}) "
        f"over {r['duration_s']} s; estimates {r['estimates_received']}/{r['blocks_sent']} "
        f"(missing {r['missing_estimates']}), daemon drops {r['daemon_dropped']}, errors {r['daemon_errors']}"
    )
    console.print(
        f"block-to-estimate latency: p50 {r['latency_ms_p50']:.2f} ms, p99 {r['latency_ms_p99']:.2f} ms, "
        f"max {r['latency_ms_max']:.2f} ms; daemon CPU {100 * r['daemon_cpu_fraction_of_one_core']:.0f} % of one core; "
        f"recorded {r['recorded_bytes'] / 1e6:.1f} MB"
    )
    if "daemon_loop_running_fraction" in r:
        console.print(
            f"daemon event loop: running {100 * r['daemon_loop_running_fraction']:.0f} %, waiting for a CPU "
            f"{100 * r['daemon_loop_runqueue_fraction']:.0f} %, asleep {100 * r['daemon_loop_asleep_fraction']:.0f} % "
            "(blocked in a put, on the GIL, or without input)"
        )
    if r.get("cpu_us_per_block"):
        b = r["cpu_us_per_block"]
        console.print(
            f"daemon CPU a sample: {r['daemon_cpu_ns_per_sample']:.0f} ns"
            + (
                f" (the estimator {r['kernel_ns_per_sample']:.0f} ns, plumbing {r['plumbing_ns_per_sample']:.0f} ns)"
                if "kernel_ns_per_sample" in r
                else ""
            )
            + "; "
            f"CPU a block: daemon {b['daemon']:.0f} us, feeder {b['feeder']:.0f} us, this bench's probe "
            f"{b['probe']:.0f} us; at the offered {r['offered_samples_per_s'] / r['block']:,.0f} blocks/s the three "
            f"need {r['cores_needed_at_offered']:.2f} cores, of {r['machine_cores']} on this machine"
            + (
                f" (load average {r['load_average_start']:.1f} -> {r['load_average_end']:.1f})"
                if "load_average_start" in r
                else ""
            )
        )
    if r.get("foxglove_messages") is not None:
        kinds = ", ".join(f"{k} {n}" for k, n in r["foxglove_messages"].items())
        console.print(f"foxglove client received {kinds} ({r['foxglove_bytes'] / 1e6:.1f} MB)")
