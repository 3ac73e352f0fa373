"""``sinewatch bench overload``: the daemon offered twice what it sustains, once with each
queue policy (reliability item 4).

Runs :mod:`sinewatch.apps.bench.e2e` twice with the same offer (``--channels``, by default twice
``--sustainable-channels``): with ``queue_policy = "drop"`` the daemon must drop whole
blocks, flag every one as a gap on the channel's next estimate and keep its latency
bounded; with ``"block"`` it must push back on the publishers and lose nothing (the feeder
then takes longer than the signal lasts). In neither case may it stall, or its memory grow
beyond its bounded queue.
"""

from __future__ import annotations

import argparse
import copy
import json
from collections.abc import Callable
from typing import Any

from rich.table import Table

from sinewatch.apps.bench.e2e import measure
from sinewatch.apps.console import make_console, print_table


def run(args: argparse.Namespace) -> int:
    console = make_console()
    results: dict[str, dict[str, Any]] = {}
    for policy in ("drop", "block"):
        a = copy.copy(args)
        a.queue_policy = policy
        console.print(f"[bold]queue_policy = {policy!r}[/bold]")
        results[policy] = measure(a, console)
    print_table(console, _table(results, args))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0 if _verdict(results) else 1


def _verdict(r: dict[str, dict[str, Any]]) -> bool:
    drop, block = r["drop"], r["block"]
    dropped_all_flagged = drop["daemon_dropped"] == drop["missing_estimates"]
    return bool(dropped_all_flagged and block["missing_estimates"] == 0 and block["daemon_dropped"] == 0)


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


ROWS: tuple[tuple[str, Callable[[dict[str, Any]], str]], ...] = (
    ("blocks sent", lambda r: str(r["blocks_sent"])),
    ("estimates", lambda r: str(r["estimates_received"])),
    ("dropped by the daemon", lambda r: str(r["daemon_dropped"])),
    ("gap blocks flagged on estimates", lambda r: str(r["gap_blocks_flagged"])),
    ("backpressure waits", lambda r: str(r["daemon_backpressure_waits"])),
    ("sustained M samples/s", lambda r: f"{r['sustained_samples_per_s'] / 1e6:.2f}"),
    (
        "feeder time / signal time",
        lambda r: f"{r['duration_s'] * r['sample_rate_hz'] * r['channels'] / (r['blocks_sent'] * r['block']):.2f}",
    ),
    ("latency p50 ms", lambda r: _ms(r["latency_ms_p50"])),
    ("latency p99 ms", lambda r: _ms(r["latency_ms_p99"])),
    ("latency max ms", lambda r: _ms(r["latency_ms_max"])),
    ("daemon RSS start -> end MB", lambda r: f"{r['daemon_rss_mb_start']:.0f} -> {r['daemon_rss_mb_end']:.0f}"),
)


def _table(results: dict[str, dict[str, Any]], args: argparse.Namespace) -> Table:
    offered = args.channels * args.rate / 1e6
    t = Table(
        title=f"offered {args.channels} ch x {args.rate:g} Hz ({offered:.1f} M samples/s); "
        f"{args.sustainable_channels} ch sustainable"
    )
    t.add_column("")
    for policy in results:
        t.add_column(policy, justify="right")
    for label, cell in ROWS:
        t.add_row(label, *(cell(r) for r in results.values()))
    return t
