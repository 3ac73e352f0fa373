"""``sinewatch export``: a recording's estimates (and, on request, its input samples) as
tidy tables, CSV or Parquet.

One pass over the MCAP file (the streaming reader replay uses, so an unfinished file
exports its complete chunks), writing as it reads: memory stays flat on long files.

Tables (one row per observation, one column per variable, the same columns in CSV and
Parquet):

* ``STEM.estimates.{csv,parquet}``: one row per estimate and component ``k``; the
  Estimate's fields flattened (``std_*`` for its standard deviations, the diagnostics by
  name, ``extras`` as JSON text; the ``{sec, nsec}`` twin of ``timestamp_ns`` left out).
  A field a recording's format does not have (``valid`` before format 3, ``std`` before
  2) and an undefined value (JSON null) are an empty CSV cell and a Parquet null.
* ``STEM.samples.{csv,parquet}`` (``--samples``): one row per recorded input sample and
  column (``column`` 0 is the measurement, others known inputs), at
  ``timestamp_ns = t0_ns + round(i * 1e9 / sample_rate_hz)``.

Floats are written so that they read back to the same float64 (``repr``, the shortest
string that round-trips); Parquet columns are typed (int64, float64, bool, string).
Parquet needs pyarrow: ``pip install 'sinewatch[export]'``.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from sinewatch.core.window import ChannelFilter, Window
from sinewatch.runtime.replay import check_recording, read_window
from sinewatch.schemas.codec import Block
from sinewatch.schemas.errors import DecodeError, SinewatchError
from sinewatch.schemas.frame import Frame, decode_input

FORMATS = ("csv", "parquet")
BATCH_ROWS = 65_536  # rows per Parquet row group / CSV flush

# (column, type) in order; types: "int", "float", "bool", "str"
ESTIMATE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("channel", "str"),
    ("seq", "int"),
    ("timestamp_ns", "int"),
    ("estimator", "str"),
    ("n_samples", "int"),
    ("component", "int"),
    ("frequency_hz", "float"),
    ("amplitude", "float"),
    ("phase_rad", "float"),
    ("offset", "float"),
    ("rocof_hz_per_s", "float"),
    ("std_frequency_hz", "float"),
    ("std_amplitude", "float"),
    ("std_phase_rad", "float"),
    ("std_offset", "float"),
    ("converged", "bool"),
    ("valid", "bool"),
    ("residual_rms", "float"),
    ("gap", "bool"),
    ("gap_blocks", "int"),
    ("restart", "bool"),
    ("reset", "bool"),
    ("extras", "str"),
    ("format_version", "int"),
)
SAMPLE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("channel", "str"),
    ("seq", "int"),
    ("sample", "int"),
    ("timestamp_ns", "int"),
    ("sample_rate_hz", "float"),
    ("column", "int"),
    ("value", "float"),
)


class ExportError(SinewatchError, ValueError):
    """The export cannot be done as asked (a missing extra, a recording without estimates)."""


@dataclass
class ExportResult:
    paths: list[Path] = field(default_factory=list)
    estimates: int = 0  # Estimate messages exported
    estimate_rows: int = 0
    inputs: int = 0  # input blocks exported
    sample_rows: int = 0
    skipped_inputs: int = 0  # inputs that do not decode (recorded as they came, rejected by the daemon)
    incomplete: bool = False


def estimate_rows(msg: dict[str, Any]) -> Iterable[tuple[Any, ...]]:
    """The rows of one Estimate message, one per component."""
    d = msg["diagnostics"]
    std = msg.get("std") or {}
    rocof = msg.get("rocof_hz_per_s") or []
    extras = json.dumps(d.get("extras") or {}, sort_keys=True)
    for k in range(len(msg["frequency_hz"])):
        yield (
            msg["channel"],
            msg["seq"],
            msg["timestamp_ns"],
            msg["estimator"],
            msg["n_samples"],
            k,
            msg["frequency_hz"][k],
            msg["amplitude"][k],
            msg["phase_rad"][k],
            msg["offset"],
            rocof[k] if k < len(rocof) else None,
            _at(std.get("frequency_hz"), k),
            _at(std.get("amplitude"), k),
            _at(std.get("phase_rad"), k),
            std.get("offset"),
            d["converged"],
            d.get("valid"),  # format version 3; null in earlier recordings
            d.get("residual_rms"),
            d.get("gap", False),
            d.get("gap_blocks", 0),
            d.get("restart", False),
            d.get("reset", False),
            extras,
            msg.get("format_version", 1),
        )


def _at(values: list[Any] | None, k: int) -> Any:
    return values[k] if values is not None and k < len(values) else None


def sample_rows(payload: bytes, encoding: str) -> list[tuple[Any, ...]]:
    """The rows of one recorded input block, or of each channel of a multi-channel frame
    in turn (DecodeError if it is neither)."""
    decoded = decode_input(payload, encoding)
    if isinstance(decoded, Frame):
        return [row for c in range(decoded.n_channels) for row in _block_rows(decoded.block(c))]
    return _block_rows(decoded)


def _block_rows(block: Block) -> list[tuple[Any, ...]]:
    samples = block.samples.reshape(block.n_samples, -1).astype(np.float64)
    n, columns = samples.shape
    offsets = np.round(np.arange(n) * (1e9 / block.sample_rate_hz)).astype(np.int64)
    rows = []
    for i in range(n):
        t = block.t0_ns + int(offsets[i])
        for c in range(columns):
            rows.append((block.channel, block.seq, i, t, block.sample_rate_hz, c, float(samples[i, c])))
    return rows


# ---- writers ---------------------------------------------------------------------------------
class _CsvTable:
    def __init__(self, path: Path, columns: tuple[tuple[str, str], ...]) -> None:
        self.path = path
        self._file: TextIO = open(path, "w", newline="", encoding="utf-8")
        self._csv = csv.writer(self._file, lineterminator="\n")
        self._csv.writerow([name for name, _ in columns])

    def write(self, rows: list[tuple[Any, ...]]) -> None:
        self._csv.writerows([tuple(_csv_cell(v) for v in row) for row in rows])

    def close(self) -> None:
        self._file.close()


def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)  # the shortest text that reads back to the same float64 ('nan', 'inf' included)
    return v


class _ParquetTable:
    def __init__(self, path: Path, columns: tuple[tuple[str, str], ...]) -> None:
        pa, pq = _pyarrow()
        self.path = path
        self._pa = pa
        types = {"int": pa.int64(), "float": pa.float64(), "bool": pa.bool_(), "str": pa.string()}
        self.schema = pa.schema([pa.field(name, types[kind]) for name, kind in columns])
        self._writer = pq.ParquetWriter(path, self.schema, compression="zstd")

    def write(self, rows: list[tuple[Any, ...]]) -> None:
        if rows:
            columns = list(zip(*rows, strict=True))
            self._writer.write_table(self._pa.Table.from_arrays(columns, schema=self.schema))

    def close(self) -> None:
        self._writer.close()


def _pyarrow() -> tuple[Any, Any]:
    try:
        import pyarrow as pa  # type: ignore[import-untyped,import-not-found,unused-ignore]
        import pyarrow.parquet as pq  # type: ignore[import-untyped,import-not-found,unused-ignore]
    except ImportError:
        raise ExportError(
            "--format parquet: expected pyarrow to be installed, got no pyarrow "
            "(install the extra: pip install 'sinewatch[export]')"
        ) from None
    return pa, pq


class _Buffered:
    """A table that writes in batches of BATCH_ROWS."""

    def __init__(self, table: _CsvTable | _ParquetTable) -> None:
        self.table = table
        self.rows: list[tuple[Any, ...]] = []
        self.count = 0

    def add(self, rows: Iterable[tuple[Any, ...]]) -> None:
        for row in rows:
            self.rows.append(row)
            self.count += 1
        if len(self.rows) >= BATCH_ROWS:
            self.table.write(self.rows)
            self.rows = []

    def close(self) -> None:
        self.table.write(self.rows)
        self.rows = []
        self.table.close()


# ---- export ----------------------------------------------------------------------------------
def export(
    path: Path,
    out_dir: Path,
    *,
    fmt: str = "csv",
    channels: str | list[str] = "*",
    samples: bool = False,
    on_progress: Callable[[int], None] | None = None,
    window: Window | None = None,
) -> ExportResult:
    """Export the recording at ``path`` into ``out_dir``; see the module docstring.
    ``channels``: globs of channel names (:mod:`sinewatch.core.window`); ``window``: only the
    messages logged in it (reading stops at its end)."""
    selected = ChannelFilter.of(channels)
    window = window or Window()
    if fmt not in FORMATS:
        raise ExportError(f"--format: expected one of {list(FORMATS)}, got {fmt!r}")
    check_recording(path)
    if fmt == "parquet":
        _pyarrow()  # the missing extra is told before any file is written
    make = _CsvTable if fmt == "csv" else _ParquetTable
    stem = path.name.removesuffix(".mcap")
    result = ExportResult()
    seen: set[str] = set()
    tables = {"estimates": _Buffered(make(out_dir / f"{stem}.estimates.{fmt}", ESTIMATE_COLUMNS))}
    if samples:
        tables["samples"] = _Buffered(make(out_dir / f"{stem}.samples.{fmt}", SAMPLE_COLUMNS))
    try:
        for kind, item in read_window(path, window, on_progress):
            if kind == "incomplete":
                result.incomplete = True
            if kind != "message":
                continue
            if item.role == "estimate":
                msg = json.loads(item.payload)
                seen.add(msg["channel"])
                if selected.matches(msg["channel"]):
                    tables["estimates"].add(estimate_rows(msg))
                    result.estimates += 1
            elif item.role == "input" and samples:
                try:
                    rows = sample_rows(item.payload, item.zenoh_encoding)
                except DecodeError:
                    result.skipped_inputs += 1
                    continue
                if not selected.everything:  # a frame's rows are of several channels
                    rows = [row for row in rows if selected.matches(row[0])]
                if rows:
                    tables["samples"].add(rows)
                    result.inputs += 1
    finally:
        for table in tables.values():
            table.close()
    result.paths = [t.table.path for t in tables.values()]
    if result.estimates == 0 and not selected.everything and seen:
        for p in result.paths:
            p.unlink()
        listed = ", ".join(sorted(seen)[:8]) + (", ..." if len(seen) > 8 else "")
        got = channels if isinstance(channels, str) else ", ".join(channels)
        raise ExportError(f"--channels: expected a pattern matching some of {listed}; got {got!r}")
    result.estimate_rows = tables["estimates"].count
    result.sample_rows = tables["samples"].count if samples else 0
    return result


# ---- the command -----------------------------------------------------------------------------
def run_export(args: Any) -> int:
    """``sinewatch export FILE.mcap --format csv|parquet [--channels GLOB ...] [--start T] [--end T]
    [--out DIR] [--samples]``."""
    from sinewatch.apps.console import byte_progress, check_output_dir, make_console

    path = Path(args.path)
    check_recording(path)
    out_dir = check_output_dir(Path(args.out) if args.out else path.parent, "--out")
    console = make_console(stderr=True)
    with byte_progress(console, "exporting", disable=args.no_progress or not console.is_terminal) as progress:
        task = progress.add_task("export", total=path.stat().st_size)
        result = export(
            path,
            out_dir,
            fmt=args.format,
            channels=args.channels or "*",
            samples=args.samples,
            on_progress=lambda pos: progress.update(task, completed=pos),
            window=Window.parse(args.start, args.end),
        )
    if result.incomplete:
        print(f"{path} was not finished (writer killed?): its complete chunks were exported")
    print(
        f"{result.estimates} estimates ({result.estimate_rows} rows)"
        + (f", {result.inputs} input blocks ({result.sample_rows} rows)" if args.samples else "")
        + (f", {result.skipped_inputs} undecodable inputs skipped" if result.skipped_inputs else "")
    )
    for p in result.paths:
        print(p)
    return 0
