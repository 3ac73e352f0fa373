"""Tables fit the terminal they are shown in, and are plain lines when output is not a terminal.

The demo runs as a real process on a pseudo-terminal of a fixed size (the width rich reads
with TIOCGWINSZ, as on a user's terminal), and piped; the renderers are also called with a
width directly.
"""

from __future__ import annotations

import fcntl
import os
import pty
import re
import struct
import subprocess
import termios
from pathlib import Path

from conftest import sinewatch
from rich.cells import cell_len
from rich.table import Table

from sinewatch.console import fit_table, natural_width, table_lines

STYLE = re.compile(r"\x1b\[[0-9;]*m")  # colours and bold: nothing on screen
CURSOR = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07|\r")  # moves: a live redraw


def screen_lines(output: str) -> list[str]:
    """What a terminal shows, line by line: a cursor move ends a line as a newline does."""
    return CURSOR.sub("\n", STYLE.sub("", output)).split("\n")


DEMO = ["demo", "--duration", "1", "--no-record", "--scenarios", "demo-biased,demo-faulty-sensor"]


def run_on_pty(args: list[str], columns: int, rows: int = 50) -> str:
    """Run a command with its stdout and stderr on a pseudo-terminal of ``columns``; its output."""
    main, child = pty.openpty()
    fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", rows, columns, 0, 0))
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "NO_COLOR")}
    env["TERM"] = "xterm-256color"
    proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=child, stderr=child, env=env)
    os.close(child)
    chunks = []
    while True:
        try:
            data = os.read(main, 65536)
        except OSError:  # EIO: the child closed its side
            break
        if not data:
            break
        chunks.append(data)
    os.close(main)
    assert proc.wait(timeout=120) == 0
    return b"".join(chunks).decode("utf-8", "replace")


def test_demo_table_fits_a_narrow_terminal():
    columns = 80
    # live redraws move the cursor instead of starting new lines: an escape ends a line too
    lines = screen_lines(run_on_pty(sinewatch(*DEMO), columns))
    assert max(cell_len(line) for line in lines) <= columns, max(lines, key=cell_len)
    header = next(line for line in lines if "f est Hz" in line)
    assert "channel" in header and "A est" in header  # the columns that always stay
    assert "off true" not in header  # the first to go: the full table needs about 128 columns
    assert any("biased" in line and "│" in line for line in lines)  # a drawn table, one row per channel


def test_demo_on_a_wide_terminal_shows_every_column():
    lines = screen_lines(run_on_pty(sinewatch(*DEMO), 200))
    header = next(line for line in lines if "f est Hz" in line)
    for col in ("estimator", "f true", "A true", "offset", "off true", "phase err°", "conv", "est.", "bad in"):
        assert col in header


def test_demo_piped_prints_plain_lines():
    r = subprocess.run(sinewatch(*DEMO), capture_output=True, text=True, timeout=120, check=True)
    lines = r.stdout.split("\n")
    assert not any(ch in r.stdout for ch in "│┃━─\x1b")  # no box drawing, no escapes
    i = next(i for i, line in enumerate(lines) if line.startswith("channel"))
    assert lines[i].split()[:3] == ["channel", "estimator", "f"]
    rows = {line.split()[0]: line.split() for line in lines[i + 1 : i + 3]}
    assert set(rows) == {"biased", "faulty-sensor"}
    assert rows["biased"][1] == "ges-kalman" and abs(float(rows["biased"][2]) - float(rows["biased"][3])) < 0.5


def _wide_table() -> Table:
    t = Table(title="t")
    for col in ("name", "a", "b", "c"):
        t.add_column(col)
    t.add_row("x" * 10, "1" * 20, "2" * 20, "3" * 20)
    return t


def test_fit_table_drops_named_columns_until_it_fits():
    full = natural_width(_wide_table())
    assert full == 1 + 4 * 3 + 10 + 60  # borders and padding: 3 per column, one closing border
    assert [c.header for c in fit_table(_wide_table(), full, ("c", "b")).columns] == ["name", "a", "b", "c"]
    assert [c.header for c in fit_table(_wide_table(), full - 1, ("c", "b")).columns] == ["name", "a", "b"]
    assert [c.header for c in fit_table(_wide_table(), 40, ("c", "b")).columns] == ["name", "a"]
    narrow = fit_table(_wide_table(), 40, ("c", "b"))
    assert natural_width(narrow) == 1 + 2 * 3 + 10 + 20 <= 40


def test_table_lines_are_aligned_plain_text():
    assert table_lines(_wide_table()) == [
        "t",
        "name        a                     b                     c",
        "xxxxxxxxxx  11111111111111111111  22222222222222222222  33333333333333333333",
    ]


def test_export_shows_a_progress_bar_on_a_terminal_only(tmp_path):
    recording = Path(__file__).parent / "data" / "recorded-before-layering.mcap"
    args = sinewatch("export", str(recording), "--out", str(tmp_path))
    on_terminal = run_on_pty(args, 100)
    assert "exporting" in on_terminal and "\x1b[" in on_terminal  # drawn, then erased (transient)
    assert "96 estimates" in on_terminal
    piped = subprocess.run(args, capture_output=True, text=True, check=True)
    assert "exporting" not in piped.stdout + piped.stderr and "\x1b" not in piped.stdout + piped.stderr
