"""Consoles and tables that fit where they are shown.

On a terminal a table is fitted to the terminal's width: columns the caller marks as
optional are dropped (least important first) until the table's natural width fits, so
cells do not wrap; rich folds whatever still does not fit. When the output is not a
terminal (a pipe, a file, a CI log) a table degrades to plain lines: its title, a header
line and one line per row, cells separated by two spaces, nothing wrapped or drawn.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console
from rich.measure import Measurement
from rich.table import Table
from rich.text import Text

if TYPE_CHECKING:
    from rich.progress import Progress

from sinewatch.schemas.errors import OutputError

PIPE_WIDTH = 140  # what rich wraps free text at when the output is not a terminal


def make_console(stderr: bool = False) -> Console:
    stream = sys.stderr if stderr else sys.stdout
    console = Console(file=stream)
    if not console.is_terminal:
        console = Console(file=stream, width=PIPE_WIDTH)
    return console


class Waiting:
    """``with Waiting("tail", "a Zenoh router or daemon at tcp/...", 60):`` around a call that
    blocks until a daemon or a peer answers: says at once on stderr what the command waits
    for, for how long and how to stop it, then every ``every`` seconds how long it has
    waited, until the block ends (a command that seems to hang is one a user kills)."""

    def __init__(self, command: str, what: str, limit_s: float | None, *, every: float = 5.0) -> None:
        self.command, self.what, self.limit_s, self.every = command, what, limit_s, every
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._started = 0.0

    def _say(self, text: str) -> None:
        print(f"{self.command}: {text}", file=sys.stderr, flush=True)

    def __enter__(self) -> Waiting:
        limit = f"up to {self.limit_s:g} s; " if self.limit_s is not None else ""
        self._say(f"waiting for {self.what} ({limit}Ctrl-C to stop)")
        self._started = time.monotonic()
        self._thread = threading.Thread(target=self._progress, name="sinewatch-waiting", daemon=True)
        self._thread.start()
        return self

    def _progress(self) -> None:
        while not self._done.wait(self.every):
            waited = time.monotonic() - self._started
            of = f" of {self.limit_s:g} s" if self.limit_s is not None else ""
            self._say(f"still waiting for {self.what} ({waited:.0f} s{of})")

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join()


def natural_width(table: Table) -> int:
    """The width the table takes when nothing in it wraps."""
    wide = Console(width=10_000, file=sys.stdout)
    return Measurement.get(wide, wide.options, table).maximum


def fit_table(table: Table, width: int, drop: Sequence[str] = ()) -> Table:
    """Drop the columns named in ``drop`` (in that order, first dropped first) until the
    table's natural width is at most ``width``; the table is changed in place and returned."""
    for header in drop:
        if natural_width(table) <= width:
            break
        table.columns[:] = [c for c in table.columns if _plain(c.header) != header]
    return table


def table_lines(table: Table) -> list[str]:
    """The table as plain lines: its title, a header line, one line per row."""
    columns = table.columns
    cells = [[_plain(c) for c in col.cells] for col in columns]
    headers = [_plain(col.header) for col in columns]
    n_rows = max((len(c) for c in cells), default=0)
    rows = [[c[i] if i < len(c) else "" for c in cells] for i in range(n_rows)]
    widths = [max([len(h)] + [len(r[j]) for r in rows]) for j, h in enumerate(headers)]
    lines = [_plain(table.title)] if table.title else []
    for row in [headers, *rows]:
        lines.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())
    return lines


def print_table(console: Console, table: Table, drop: Sequence[str] = ()) -> None:
    """Fitted to the terminal, or plain lines when the console is not a terminal."""
    if console.is_terminal:
        console.print(fit_table(table, console.width, drop))
    else:
        print_lines(console, table_lines(table))


def print_lines(console: Console, lines: Iterable[str]) -> None:
    for line in lines:
        console.print(line, markup=False, highlight=False, soft_wrap=True)


def _plain(cell: object) -> str:
    if isinstance(cell, Text):
        return cell.plain
    return Text.from_markup(cell).plain if isinstance(cell, str) else str(cell)


def check_output_dir(directory: Path, what: str) -> Path:
    """Create ``directory`` (and its parents) if needed; raise OutputError saying why it
    cannot be written to (a file in the way, no permission) before any work starts."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{what} {directory}: expected a writable directory, got {_reason(exc)}") from None
    if not os.access(directory, os.W_OK | os.X_OK):
        raise OutputError(f"{what} {directory}: expected a writable directory, got one without write permission")
    return directory


def _reason(exc: OSError) -> str:
    if isinstance(exc, FileExistsError | NotADirectoryError):
        return "a file in the way"
    return (exc.strerror or type(exc).__name__).lower()


def byte_progress(console: Console, label: str, *, disable: bool) -> Progress:
    """A progress bar over the bytes of the files being read (replay, export), gone when done."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(
        TextColumn(label),
        BarColumn(),
        DownloadColumn(),
        TimeRemainingColumn(),
        console=console,
        disable=disable,
        transient=True,
    )
