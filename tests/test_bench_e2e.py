"""``sinewatch bench e2e --sweep`` as a user runs it (functional: the figures are the
bench's business, never asserted as timings): the daemon with its default worker
processes, the feeder and the probe as processes; the JSON carries every point's fields,
the plot is a PNG."""

from __future__ import annotations

import json
import subprocess

import pytest
from conftest import sinewatch


def test_sweep_writes_every_point_the_table_and_the_plot(tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "sweep.json"
    r = subprocess.run(
        sinewatch("bench", "e2e", "--sweep", "--sweep-channels", "1,4", "--duration", "2", "--json", str(out)),
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    rows = json.loads(out.read_text())["sweep"]
    assert [row["channels"] for row in rows] == [1, 4]
    for row in rows:
        assert row["offered_samples_per_s"] == row["channels"] * 10_000.0
        assert row["missing_estimates"] == 0 and row["daemon_dropped"] == 0
        assert row["estimates_received"] == row["blocks_sent"] > 0
        assert row["sustained_samples_per_s"] == pytest.approx(row["offered_samples_per_s"], rel=0.05)
        assert 0 < row["latency_ms_p50"] <= row["latency_ms_p99"] <= row["latency_ms_max"]
        assert row["workers"] >= 1 and row["daemon_rss_mb_end"] > 0
        # the CPU budget: per block, per process; times the offered blocks/s, the cores needed
        budget = row["cpu_us_per_block"]
        assert set(budget) == {"daemon", "feeder", "probe"} and budget["daemon"] > 0  # CPU ticks are 10 ms
        blocks_per_s = row["offered_samples_per_s"] / row["block"]
        assert row["cores_needed_at_offered"] == pytest.approx(sum(budget.values()) * blocks_per_s / 1e6)
        assert row["machine_cores"] >= 1
    assert "daemon_rss_mb_per_channel" in rows[1]
    assert "sustained M/s" in r.stdout and "p99 ms" in r.stdout and "cores needed" in r.stdout
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_fanout_delivers_every_block_both_ways(tmp_path):
    """``sinewatch bench fanout``: every block reaches its worker through Zenoh and through
    the shared-memory rings; the JSON has both ways' CPU per block."""
    out = tmp_path / "fanout.json"
    r = subprocess.run(
        sinewatch("bench", "fanout", "--channels", "20", "--blocks", "400", "--json", str(out)),
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    rows = {row["way"]: row for row in json.loads(out.read_text())}
    assert set(rows) == {"zenoh", "shm"}
    for row in rows.values():
        assert row["delivered"] == row["blocks"] == 400
        # CPU is read in 10 ms ticks: so short a run may read 0
        assert row["total_cpu_us_per_block"] >= row["receiver_cpu_us_per_block"] >= 0
