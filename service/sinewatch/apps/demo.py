"""``sinewatch demo``: the whole path on one machine, nothing else to start.

The daemon runs on an embedded Zenoh peer listening on a free loopback port; a simulated
feed (eight 10 kHz channels by default) publishes to it through a second Zenoh session in
real time; a third session subscribes to the estimates and shows them beside the truth.
At the end the daemon drains, finishes its MCAP file, and the demo prints the file's path,
a per-channel summary and the command that replays it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import shutil
import sys
import threading
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live
from rich.logging import RichHandler
from rich.table import Table

from sinewatch.apps.console import fit_table, make_console, print_table
from sinewatch.apps.feed import Feed, FeedChannel, make_channels, rules_for
from sinewatch.clients import BlockPublisher, connect, subscribe_estimates
from sinewatch.clients.session import free_loopback_port
from sinewatch.runtime.daemon import Daemon
from sinewatch.scenarios.demo import DEMO_CHANNELS
from sinewatch.schemas.config import RecordingSection, SinewatchConfig, ZenohSection

PREFIX = "demo"
TRUTHS_KEPT = 512  # per channel: the truth of the last blocks sent, for the estimates still in flight


@dataclass
class ChannelView:
    feed: FeedChannel
    truth_by_seq: dict[int, Any] = field(default_factory=dict)
    order: deque[int] = field(default_factory=lambda: deque(maxlen=TRUTHS_KEPT))
    last: dict[str, Any] | None = None  # the newest valid estimate (the newest of any while none is valid)
    truth: Any = None
    estimates: int = 0


def demo_config(channels: list[FeedChannel], port: int, record_dir: Path, record: bool) -> SinewatchConfig:
    """The daemon's config: a loopback listener, and each channel served by the estimator
    its scenario suggests."""
    return SinewatchConfig(
        daemon_id="sinewatch-demo",
        zenoh=ZenohSection(listen=[f"tcp/127.0.0.1:{port}"]),
        rules=rules_for(channels),
        recording=RecordingSection(enabled=record, directory=record_dir),
    )


def _fmt(x: float | None, spec: str = ".3f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def _phase_err_deg(est: float | None, true: float) -> float | None:
    if est is None:
        return None
    return math.degrees(math.remainder(est - true, 2 * math.pi))


def _short(channel: str) -> str:
    return channel.removeprefix(f"{PREFIX}/").removeprefix("demo-")


# The columns a narrow terminal loses first, in order: at 100 columns the table is whole, at
# 80 the channel, the estimate beside its truth, and the errors stay.
DROP_ORDER = ("bad in", "est.", "phase err°")
HEADERS = ("channel", "", "f Hz", "f err", "A", "A err", "offset", "phase err°", "conv", "est.", "bad in")


def render(views: list[ChannelView], title: str, width: int | None = None) -> Table:
    """The live table, two lines per channel: its name and the estimate, then its estimator
    and the truth; the errors (estimate - truth) beside them. With ``width``, fitted to it
    (:data:`DROP_ORDER`)."""
    t = Table(title=title, title_justify="left")
    for col in HEADERS:
        t.add_column(col, justify="left" if col in ("channel", "") else "right", no_wrap=True)
    for v in views:
        e = v.last
        tr = v.truth
        name, bad = _short(v.feed.channel), str(sum(v.feed.faults_injected.get(k, 0) for k in ("nan", "duplicate")))
        if e is None or tr is None:
            t.add_row(name, "est", *(["-"] * 6), "no", "0", bad)
            t.add_row("", "true", *([""] * 9), style="dim")
            continue
        f_est, a_est, off = e["frequency_hz"][0], e["amplitude"][0], e["offset"]
        f_true, a_true, off_true = float(tr.frequency_hz[0, 0]), float(tr.amplitude[0, 0]), float(tr.offset[0])
        t.add_row(
            name,
            "est",
            _fmt(f_est),
            _fmt(None if f_est is None else f_est - f_true, "+.3f"),
            _fmt(a_est),
            _fmt(None if a_est is None else a_est - a_true, "+.3f"),
            _fmt(off),
            _fmt(_phase_err_deg(e["phase_rad"][0], float(tr.phase_rad[0, 0])), "+.2f"),
            "yes" if e["diagnostics"]["converged"] else "no",
            str(v.estimates),
            bad,
        )
        t.add_row(
            e["estimator"], "true", _fmt(f_true), "", _fmt(a_true), "", _fmt(off_true), "", "", "", "", style="dim"
        )
    return t if width is None else fit_table(t, width, DROP_ORDER)


async def run_demo(
    names: list[str] | None = None,
    duration_s: float = 10.0,
    record_dir: Path = Path("sinewatch-runs"),
    record: bool = True,
    console: Console | None = None,
    block_s: float = 0.1,
) -> int:
    console = console or Console()
    channels = make_channels(names or DEMO_CHANNELS, prefix=PREFIX)
    port = free_loopback_port()
    daemon = Daemon(demo_config(channels, port, record_dir, record))
    daemon_task = asyncio.create_task(daemon.run())
    await daemon.ready.wait()

    session = connect([f"tcp/127.0.0.1:{port}"])
    estimates = subscribe_estimates(session)
    publisher = BlockPublisher(session)
    views = {c.channel: ChannelView(c) for c in channels}
    for c in channels:
        publisher.wait_for_subscriber(c.channel, 10.0)

    def remember_truth(ch: FeedChannel) -> None:
        v = views[ch.channel]
        v.truth_by_seq[ch.last_seq] = ch.last_truth
        v.order.append(ch.last_seq)
        if len(v.truth_by_seq) > TRUTHS_KEPT - 1:
            v.truth_by_seq.pop(v.order[0], None)

    # Blocks of 0.1 s: 1000 samples at 10 kHz, 10 at the 100 Hz of paper 002's example.
    block_size = max(1, round(block_s * channels[0].scenario.sample_rate_hz))
    feed = Feed(publisher, channels, block_size=block_size, realtime=True)
    feed_done = threading.Event()

    def feed_thread() -> None:
        try:
            feed.run(duration_s, on_block=remember_truth)
        finally:
            feed_done.set()

    threading.Thread(target=feed_thread, name="sinewatch-demo-feed", daemon=True).start()
    ordered = [views[c.channel] for c in channels]

    def absorb() -> None:
        while (msg := estimates.get(timeout=0)) is not None:
            v = views.get(msg["channel"])
            if v is None:
                continue
            v.estimates += 1
            # The table shows the newest estimate that is a measurement: at the drain the daemon
            # publishes what it still held back, not valid (nothing confirmed those windows), and
            # showing those would turn every channel's last row to "not converged".
            if msg["diagnostics"]["valid"] or v.last is None or not v.last["diagnostics"]["valid"]:
                v.last = msg
                v.truth = v.truth_by_seq.get(msg["seq"], v.truth)

    title = f"sinewatch demo: {len(channels)} channels, {duration_s:g} s (Ctrl-C stops early)"
    # On a terminal a live table fitted to its width; elsewhere (a pipe, a log) plain lines at the end.
    live = None
    if console.is_terminal:
        live = Live(render(ordered, title, console.width), console=console, refresh_per_second=4, transient=False)
    with live or contextlib.nullcontext(), _logs_through(console):
        while not feed_done.is_set() and not daemon.should_exit.is_set():
            await asyncio.sleep(0.25)  # the display's refresh period
            absorb()
            if live is not None:
                live.update(render(ordered, title, console.width))
        feed.stop.set()
        await asyncio.to_thread(feed_done.wait)
        daemon.should_exit.set()
        code = await daemon_task
        absorb()
        if live is not None:
            live.update(render(ordered, title + " (finished)", console.width))
    if live is None:
        print_table(console, render(ordered, title + " (finished)"))
    estimates.close()
    publisher.close()
    session.close()  # type: ignore[no-untyped-call]  # zenoh's stub leaves it untyped
    _summary(console, daemon, ordered)
    return code


@contextlib.contextmanager
def _logs_through(console: Console) -> Iterator[None]:
    """Route sinewatch's log lines (rejected inputs, gaps) through the live display's
    console, so they print above the table instead of tearing it."""
    logger = logging.getLogger("sinewatch")
    handler: logging.Handler
    if console.is_terminal:
        handler = RichHandler(console=console, show_path=False, show_time=False, markup=False)
    else:  # a pipe or a file: plain lines, as long as they are (RichHandler pads them to the width)
        handler = logging.StreamHandler(console.file)
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    handler.setLevel(logging.WARNING)
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _summary(console: Console, daemon: Daemon, views: list[ChannelView]) -> None:
    assert daemon.pipeline is not None  # the daemon ran
    c = daemon.pipeline.counters
    console.print(
        f"\n[bold]Summary[/bold]: {c.inputs} blocks in, {c.estimates} estimates out, {c.errors} rejected "
        f"({', '.join(f'{k} {n}' for k, n in sorted(c.by_kind.items())) or 'none'})"
    )
    for v in views:
        e, tr = v.last, v.truth
        if e is None or tr is None or e["frequency_hz"][0] is None:
            console.print(f"  {v.feed.channel}: no converged estimate", soft_wrap=True)
            continue
        console.print(
            f"  {_short(v.feed.channel):18s} |f err| {abs(e['frequency_hz'][0] - tr.frequency_hz[0, 0]):.4f} Hz"
            f"   |A err| {abs(e['amplitude'][0] - tr.amplitude[0, 0]):.4f}"
            + (f"   faults injected: {v.feed.faults_injected}" if v.feed.faults_injected else ""),
            soft_wrap=True,
        )
    for path in daemon.recording_paths:
        # soft_wrap: one line however narrow the terminal (it wraps it on screen), so it pastes
        console.print(f"\nMCAP recording: [bold]{path}[/bold]", soft_wrap=True)
        console.print("Replay it bit for bit:")
        console.print(f"{_cli_name()} replay {path}", soft_wrap=True, highlight=False, markup=False)


def _cli_name() -> str:
    """How the user can call the CLI from here: `sinewatch` if it is on PATH, else the
    path of the script that is running (e.g. .venv/bin/sinewatch after `make demo`)."""
    if shutil.which("sinewatch") or not sys.argv[0].endswith("sinewatch"):
        return "sinewatch"
    return os.path.relpath(sys.argv[0])


def main(names: list[str] | None, duration_s: float, record_dir: Path, record: bool) -> int:
    console = make_console()
    return asyncio.run(run_demo(names, duration_s, record_dir, record, console))
