"""``sinewatch export`` of a demo recording: the CSV read by pandas holds the MCAP's values
exactly, the Parquet file is typed and holds the same table; samples too."""

from __future__ import annotations

import asyncio
import io
import json
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from conftest import cli_without, sinewatch
from mcap.reader import make_reader
from rich.console import Console

from sinewatch.apps.demo import run_demo
from sinewatch.apps.export import ESTIMATE_COLUMNS, SAMPLE_COLUMNS
from sinewatch.schemas.codec import decode_block
from sinewatch.schemas.input_record import decode_input_record

CHANNELS = ["demo-ramp", "demo-faulty-sensor", "multisine-demo"]  # a NaN block; a multi-component estimator


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    console = Console(file=io.StringIO(), width=160)
    # 3.2 s: 32 blocks per channel; the faulty sensor drops block 22 and sends NaN in block 30
    assert asyncio.run(run_demo(CHANNELS, duration_s=3.2, record_dir=d, console=console)) == 0
    [path] = d.glob("*.mcap")
    return path


def recorded(path):
    """(estimates, input blocks) straight from the MCAP file."""
    estimates, blocks = [], []
    with open(path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages(log_time_order=False):  # file order
            role = channel.metadata.get("role")
            if role == "estimate":
                estimates.append(json.loads(message.data))
            elif role == "input":
                if channel.message_encoding == "protobuf":  # an InputBlock record
                    blocks.append(decode_block(*decode_input_record(message.data)))
                else:  # a recording of an earlier build: the payload as received
                    blocks.append(decode_block(message.data, channel.metadata.get("zenoh_encoding", "")))
    return estimates, blocks


def run_export(*args):
    r = subprocess.run(sinewatch("export", *args, "--no-progress"), capture_output=True, text=True, check=True)
    return r.stdout.splitlines()


def expected_estimate_rows(estimates):
    rows = []
    for m in estimates:
        std = m.get("std") or {}
        for k in range(len(m["frequency_hz"])):
            rows.append(
                {
                    "channel": m["channel"],
                    "seq": m["seq"],
                    "timestamp_ns": m["timestamp_ns"],
                    "component": k,
                    "frequency_hz": m["frequency_hz"][k],
                    "amplitude": m["amplitude"][k],
                    "phase_rad": m["phase_rad"][k],
                    "offset": m["offset"],
                    "std_frequency_hz": (std.get("frequency_hz") or [None] * 9)[k],
                    "converged": m["diagnostics"]["converged"],
                    "valid": m["diagnostics"]["valid"],
                    "residual_rms": m["diagnostics"]["residual_rms"],
                    "extras": m["diagnostics"]["extras"],
                }
            )
    return rows


def assert_same(frame: pd.DataFrame, rows: list[dict]) -> None:
    assert len(frame) == len(rows)
    for col in rows[0]:
        want = [r[col] for r in rows]
        got = frame[col].tolist()
        if col == "extras":
            assert [json.loads(g) for g in got] == want
        elif dict(ESTIMATE_COLUMNS)[col] == "float":
            a = np.array([np.nan if w is None else w for w in want], dtype=float)
            np.testing.assert_array_equal(np.asarray(got, dtype=float), a)  # exact, NaN where null
        else:
            assert got == want, col


def test_csv_holds_the_recorded_estimates_exactly(recording, tmp_path):
    lines = run_export(str(recording), "--out", str(tmp_path))
    estimates, _ = recorded(recording)
    assert len(estimates) == 32 + 30 + 32  # the faulty sensor's dropped and NaN blocks have none
    frame = pd.read_csv(tmp_path / f"{recording.stem}.estimates.csv")
    assert list(frame.columns) == [c for c, _ in ESTIMATE_COLUMNS]
    rows = expected_estimate_rows(estimates)
    assert len(rows) > len(estimates)  # multisine-demo reports several components
    assert_same(frame, rows)
    assert lines[0] == f"94 estimates ({len(rows)} rows)"
    assert lines[1] == str(tmp_path / f"{recording.stem}.estimates.csv")


def test_parquet_is_typed_and_holds_the_same_table(recording, tmp_path):
    run_export(str(recording), "--format", "parquet", "--out", str(tmp_path), "--samples")
    table = pq.read_table(tmp_path / f"{recording.stem}.estimates.parquet")
    types = {"int": pa.int64(), "float": pa.float64(), "bool": pa.bool_(), "str": pa.string()}
    assert table.schema == pa.schema([pa.field(c, types[t]) for c, t in ESTIMATE_COLUMNS])
    estimates, blocks = recorded(recording)
    assert_same(table.to_pandas(), expected_estimate_rows(estimates))
    samples = pq.read_table(tmp_path / f"{recording.stem}.samples.parquet")
    assert samples.schema == pa.schema([pa.field(c, types[t]) for c, t in SAMPLE_COLUMNS])
    # 0.1 s blocks: 1000 samples at 10 kHz (demo-ramp, faulty sensor), 100 at 1 kHz (multisine-demo)
    assert samples.num_rows == sum(b.n_samples for b in blocks) == 32 * 1000 + 31 * 1000 + 32 * 100


def test_samples_csv_holds_every_recorded_sample_at_its_time(recording, tmp_path):
    run_export(str(recording), "--samples", "--out", str(tmp_path))
    _, blocks = recorded(recording)
    frame = pd.read_csv(tmp_path / f"{recording.stem}.samples.csv")
    assert list(frame.columns) == [c for c, _ in SAMPLE_COLUMNS]
    values = np.concatenate([b.samples.astype(np.float64) for b in blocks])
    assert np.isnan(values).sum() >= 1  # the faulty sensor's NaN block is recorded as it came
    np.testing.assert_array_equal(frame["value"].to_numpy(), values)
    first = blocks[0]
    rows = frame[(frame["channel"] == first.channel) & (frame["seq"] == first.seq)]
    assert rows["timestamp_ns"].iloc[0] == first.t0_ns
    assert rows["timestamp_ns"].iloc[10] - first.t0_ns == round(10 * 1e9 / first.sample_rate_hz)  # 1 ms at 10 kHz
    assert (rows["column"] == 0).all() and rows["sample"].tolist() == list(range(first.n_samples))


def test_channels_glob_selects_channels(recording, tmp_path):
    lines = run_export(str(recording), "--channels", "demo/demo-*", "--out", str(tmp_path))
    assert lines[0] == "62 estimates (62 rows)"
    frame = pd.read_csv(tmp_path / f"{recording.stem}.estimates.csv")
    assert set(frame["channel"]) == {"demo/demo-ramp", "demo/demo-faulty-sensor"}


def test_a_glob_matching_nothing_is_a_mistake_and_leaves_no_file(recording, tmp_path):
    r = subprocess.run(
        sinewatch("export", str(recording), "--channels", "nope*", "--out", str(tmp_path)),
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 2 and len(r.stderr.splitlines()) == 1
    assert "demo/demo-ramp" in r.stderr and "got 'nope*'" in r.stderr
    assert list(tmp_path.iterdir()) == []


def test_parquet_without_pyarrow_names_the_extra(recording, tmp_path):
    r = cli_without("pyarrow", ["export", str(recording), "--format", "parquet", "--out", str(tmp_path)])
    assert r.returncode == 2
    assert r.stderr.splitlines() == [
        "sinewatch: error: --format parquet: expected pyarrow to be installed, got no pyarrow "
        "(install the extra: pip install 'sinewatch[export]')"
    ]
    assert list(tmp_path.iterdir()) == []


def test_a_recording_of_an_earlier_format_exports_with_its_missing_fields_null(tmp_path):
    old = Path(__file__).parent / "data" / "recorded-before-layering.mcap"  # Estimate format 1
    lines = run_export(str(old), "--format", "parquet", "--out", str(tmp_path))
    table = pq.read_table(tmp_path / f"{old.stem}.estimates.parquet").to_pandas()
    estimates, _ = recorded(old)
    rows = expected_estimate_rows([{**e, "diagnostics": {**e["diagnostics"], "valid": None}} for e in estimates])
    assert lines[0] == f"96 estimates ({len(rows)} rows)" and len(estimates) == 96
    assert set(table["format_version"]) == {1}
    assert (
        table["valid"].isna().all() and table["std_frequency_hz"].isna().all() and table["rocof_hz_per_s"].isna().all()
    )
    assert_same(table.drop(columns=["valid"]), [{k: v for k, v in r.items() if k != "valid"} for r in rows])
