"""``sinewatch bench startup``: how long short CLI commands take, against the bare
interpreter measured in the same run.

Each command runs ``--runs`` times as a fresh process of this interpreter
(``python -m sinewatch ...``, what the ``sinewatch`` script runs), the commands taking
turns so that a load change on the machine touches them alike, after one warm-up run each
(bytecode caches, page cache). Reported per command: the median and the fastest wall
time, and the median against the baseline ``python -c pass``, as a ratio and as the
milliseconds the command adds. The target is ``sinewatch config show`` under 0.3 s (it imports no estimator).
What a command imports, and what each import costs, shows with
``python -X importtime -m sinewatch config show``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass

from rich.table import Table

from sinewatch.apps.console import make_console, print_table
from sinewatch.schemas.errors import SinewatchError

BASELINE = "python -c pass"
TARGET_S = {"sinewatch config show": 0.3}  # fast enough to feel instant in a shell


@dataclass
class Timing:
    command: str
    argv: list[str]
    runs_s: list[float]
    median_s: float = 0.0
    fastest_s: float = 0.0
    ratio: float = 0.0  # median / the baseline's median
    added_ms: float = 0.0  # median - the baseline's median


def commands(config: str | None = None) -> dict[str, list[str]]:
    """The commands measured, baseline first: name -> argv (this interpreter)."""
    py = sys.executable
    show = [py, "-m", "sinewatch", "config", "show"] + (["--config", config] if config else [])
    return {
        BASELINE: [py, "-c", "pass"],
        "sinewatch --help": [py, "-m", "sinewatch", "--help"],
        "sinewatch config show": show,
    }


def _wall_time(argv: list[str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, check=False)
    dt = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SinewatchError(
            f"{' '.join(argv)}: expected exit code 0, got {proc.returncode}: {proc.stderr.decode()[-500:]}"
        )
    return dt


def measure(cmds: dict[str, list[str]], runs: int) -> list[Timing]:
    """Median wall times of ``cmds`` (the first is the baseline), ``runs`` each, in turns."""
    timings = [Timing(name, argv, []) for name, argv in cmds.items()]
    for tm in timings:  # warm-up
        _wall_time(tm.argv)
    for _ in range(runs):
        for tm in timings:
            tm.runs_s.append(_wall_time(tm.argv))
    base = statistics.median(timings[0].runs_s)
    for tm in timings:
        tm.median_s = statistics.median(tm.runs_s)
        tm.fastest_s = min(tm.runs_s)
        tm.ratio = tm.median_s / base
        tm.added_ms = (tm.median_s - base) * 1e3
    return timings


def run(args: argparse.Namespace) -> int:
    """``sinewatch bench startup [--runs N] [--config FILE] [--json FILE]``."""
    if args.runs < 1:
        print(f"error: --runs: expected >= 1, got {args.runs}", file=sys.stderr)
        return 2
    console = make_console()
    timings = measure(commands(str(args.config) if args.config else None), args.runs)
    table = Table(title=f"CLI start-up: median of {args.runs} runs each ({sys.executable})")
    for col in ("command", "median ms", "fastest ms", "vs python -c pass", "added ms", "target"):
        table.add_column(col, justify="left" if col == "command" else "right")
    for tm in timings:
        target = TARGET_S.get(tm.command)
        verdict = (
            "" if target is None else f"< {target * 1e3:.0f} ms: " + ("met" if tm.median_s < target else "NOT met")
        )
        table.add_row(
            tm.command,
            f"{tm.median_s * 1e3:.0f}",
            f"{tm.fastest_s * 1e3:.0f}",
            f"{tm.ratio:.2f}x",
            f"{tm.added_ms:+.0f}",
            verdict,
        )
    print_table(console, table)
    if os.environ.get("PYTHONDONTWRITEBYTECODE"):
        console.print("PYTHONDONTWRITEBYTECODE is set: sinewatch's own modules are compiled on every start")
    if args.json:
        args.json.write_text(json.dumps({"runs": args.runs, "results": [asdict(tm) for tm in timings]}, indent=2))
    return 0
