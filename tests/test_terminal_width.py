"""Tables fit the terminal they are shown in, and are plain lines when output is not a terminal.

The demo runs as a real process on a pseudo-terminal of a fixed size (the width rich reads
with TIOCGWINSZ, as on a user's terminal), and piped; the renderers are also called with a
width directly.
"""

from __future__ import annotations

import fcntl
import itertools
import os
import pty
import re
import struct
import subprocess
import termios
from pathlib import Path

import pytest
from conftest import sinewatch
from rich.cells import cell_len
from rich.table import Table

from sinewatch.apps.console import fit_table, natural_width, table_lines

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


def _row_pairs(lines: list[str]) -> dict[str, tuple[list[str], list[str]]]:
    """channel -> (its estimate line's cells, its truth line's cells), from drawn table lines
    (the last drawing of the live table: its finished state)."""
    cells = [[c.strip() for c in line.strip("│").split("│")] for line in lines if line.startswith("│")]
    pairs = {}
    for est, true in itertools.pairwise(cells):
        if len(est) > 1 and est[1] == "est" and true[1] == "true":
            pairs[est[0]] = (est, true)
    return pairs


@pytest.mark.parametrize("columns", [80, 100])
def test_demo_table_fits_80_and_100_columns_with_truth_estimate_and_error(columns, tmp_path):
    args = [*DEMO[:-1], DEMO[-1]]
    args.remove("--no-record")
    output = run_on_pty(sinewatch(*args, "--record-dir", str(tmp_path / "runs")), columns)
    lines = screen_lines(output)
    drawn = [line for line in lines if any(ch in line for ch in "│┃━─")]
    assert drawn and max(cell_len(line) for line in drawn) <= columns, max(drawn, key=cell_len)
    header = [c.strip() for c in next(line for line in lines if "f err" in line).strip("┃").split("┃")]
    # the estimate, the truth (the line below it) and the error of frequency and amplitude, always
    assert header[:7] == ["channel", "", "f Hz", "f err", "A", "A err", "offset"] and "conv" in header
    if columns >= 100:  # and the phase error (the first of the three that go at 80, after bad in and est.)
        assert "phase err°" in header
    est, true = _row_pairs(lines)["biased"]
    assert true[0] == "ges-kalman" and float(true[2]) == 120.0 and float(true[4]) == 2.0 and float(true[6]) == 0.5
    assert float(est[3]) == pytest.approx(float(est[2]) - float(true[2]), abs=2e-3)  # f err = est - true
    assert float(est[5]) == pytest.approx(float(est[4]) - float(true[4]), abs=2e-3)
    assert abs(float(est[3])) < 0.5
    # the replay command on one line however narrow the terminal (it wraps it on screen, softly)
    [path] = (tmp_path / "runs").glob("*.mcap")
    raw_lines = STYLE.sub("", output).replace("\r", "").split("\n")
    assert any(line.endswith(f"replay {path}") and " " not in line.split(" replay ")[0] for line in raw_lines), [
        line for line in raw_lines if "replay" in line
    ]


def test_demo_on_a_wide_terminal_shows_every_column():
    lines = screen_lines(run_on_pty(sinewatch(*DEMO), 200))
    header = next(line for line in lines if "f err" in line)
    for col in ("channel", "f Hz", "f err", "A", "A err", "offset", "phase err°", "conv", "est.", "bad in"):
        assert col in header


def test_demo_piped_prints_plain_lines_unpadded():
    args = [*DEMO]
    args[args.index("--duration") + 1] = "3"  # the faulty sensor's (seeded) drop comes at block 23
    r = subprocess.run(sinewatch(*args), capture_output=True, text=True, timeout=120, check=True)
    lines = r.stdout.split("\n")
    assert not any(ch in r.stdout for ch in "│┃━─\x1b")  # no box drawing, no escapes
    i = next(i for i, line in enumerate(lines) if line.startswith("channel"))
    assert lines[i].split()[:4] == ["channel", "f", "Hz", "f"]
    rows = [line.split() for line in lines[i + 1 : i + 5]]
    assert [r[:2] for r in rows] == [["biased", "est"], ["ges-kalman", "true"], ["faulty-sensor", "est"],
                                     [rows[3][0], "true"]]  # fmt: skip
    assert abs(float(rows[0][2]) - float(rows[1][2])) < 0.5
    # the faulty sensor's gap is logged: one plain line, as long as it is (not padded to a width)
    logged = [line for line in (r.stdout + r.stderr).split("\n") if line.startswith("WARNING sinewatch")]
    assert (
        "WARNING sinewatch.core.pipeline: channel demo/demo-faulty-sensor: 1 block(s) missing before seq 23" in logged
    )
    assert all(line == line.rstrip() for line in logged)
    assert all(line == line.rstrip() for line in lines)


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
