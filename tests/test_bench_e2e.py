"""``sinewatch bench e2e --sweep`` as a user runs it (functional: the figures are the
bench's business, never asserted as timings): the daemon with its default worker
processes, the feeder and the probe as processes; the JSON carries every point's fields,
the plot is a PNG."""

from __future__ import annotations

import json
import subprocess

import pytest
from conftest import sinewatch


def bench(*args: str) -> str:
    """``sinewatch bench ARGS`` as a process; its stdout, after asserting that it exited 0."""
    r = subprocess.run(sinewatch("bench", *args), capture_output=True, text=True, timeout=300, check=False)
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout


def test_sweep_writes_every_point_the_table_and_the_plot(tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "sweep.json"
    stdout = bench("e2e", "--sweep", "--sweep-channels", "1,4", "--duration", "1", "--json", str(out))
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
        assert row["load_average_start"] >= 0 and row["load_average_end"] >= 0  # what a loaded run is read with
    assert "daemon_rss_mb_per_channel" in rows[1]
    assert "sustained M/s" in stdout and "p99 ms" in stdout and "cores needed" in stdout
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_fanout_delivers_every_block_both_ways(tmp_path):
    """``sinewatch bench fanout``: every block reaches its worker through Zenoh and through
    the shared-memory rings; the JSON has both ways' CPU per block."""
    out = tmp_path / "fanout.json"
    bench("fanout", "--channels", "20", "--blocks", "400", "--json", str(out))
    rows = {row["way"]: row for row in json.loads(out.read_text())}
    assert set(rows) == {"zenoh", "shm"}
    for row in rows.values():
        assert row["delivered"] == row["blocks"] == 400
        # CPU is read in 10 ms ticks: so short a run may read 0
        assert row["total_cpu_us_per_block"] >= row["receiver_cpu_us_per_block"] >= 0


def test_the_latency_probe_reads_what_json_reads_from_the_daemon_s_estimates(tmp_path):
    """The bench's probe reads ``timestamp_ns`` and the gap from the bytes without parsing
    them: on a pipeline's own estimates, with and without a gap, it reads what json does."""
    import numpy as np
    from conftest import make_config

    from sinewatch.apps.bench.e2e_probes import probe_fields
    from sinewatch.core.pipeline import NullSink, Pipeline
    from sinewatch.schemas.codec import Block, encode_block_binary

    class Capture(NullSink):
        def __init__(self) -> None:
            self.payloads: list[bytes] = []

        def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
            self.payloads.append(payload)

    sink = Capture()
    pipeline = Pipeline(make_config(tmp_path), [sink])
    x = np.sin(2 * np.pi * 50 * np.arange(1024 * 8) / 10_000.0).astype(np.float32)
    for seq in (0, 1, 2, 6, 7):  # blocks 3-5 missing: the estimate of block 6 flags 3
        t0 = 1_763_900_000_000_000_000 + seq * 102_400_000
        payload = encode_block_binary(Block("p/a", seq, t0, 10_000.0, x[seq * 1024 : (seq + 1) * 1024]), "float32")
        pipeline.process("sinewatch/in/p/a", payload, "", t0)
    pipeline.release_held(0)  # the input's end: the last estimate, held back for the presence detector
    assert len(sink.payloads) == 5
    for payload in sink.payloads:
        msg = json.loads(payload)
        gap = msg["diagnostics"]["gap_blocks"] if msg["diagnostics"]["gap"] else None
        assert probe_fields(payload) == (msg["timestamp_ns"], gap)
    assert [probe_fields(p)[1] for p in sink.payloads] == [None, None, None, 3, None]


def test_frame_channels_runs_blocks_and_frames_into_one_table_with_the_daemon_s_cpu_per_sample(tmp_path):
    """``--frame-channels 1,4``: the same 8 channels as single blocks, then as frames of 4,
    every estimate back in each, the daemon's CPU per sample in the JSON and the table."""
    out = tmp_path / "frames.json"
    stdout = bench("e2e", "--channels", "8", "--frame-channels", "1,4", "--duration", "1", "--json", str(out))
    runs = json.loads(out.read_text())["runs"]
    assert [(run["frame_channels"], run["messages_sent"]) for run in runs] == [(1, 8 * 9), (4, 2 * 9)]
    for run in runs:
        assert run["estimates_received"] == run["blocks_sent"] == 8 * 9 and run["missing_estimates"] == 0
        assert run["daemon_cpu_ns_per_sample"] == pytest.approx(run["cpu_us_per_block"]["daemon"] * 1e3 / run["block"])
        # the estimator's share, measured in the bench process, and the rest: plumbing
        assert run["kernel_ns_per_sample"] > 0
        assert run["plumbing_ns_per_sample"] == pytest.approx(
            run["daemon_cpu_ns_per_sample"] - run["kernel_ns_per_sample"]
        )
    assert "per msg" in stdout and "daemon ns/sample" in stdout and "of which estimator" in stdout


def test_a_late_feeder_stamps_a_continuous_stream_that_the_daemon_does_not_take_for_time_jumps():
    """The feeder held back by the daemon publishes its blocks seconds late; stamped with
    their publish time, each channel's time would move on by far more than half a block
    between two blocks, and the daemon would start every channel over at every block
    (a time jump). Stamped by :func:`stamp_ns` the stream stays continuous; on time, a
    block carries its publish time."""
    from sinewatch.apps.bench.e2e_feeder import stamp_ns
    from sinewatch.core.continuity import CONTINUES, check_continuity

    fs, block = 10_000.0, 1024
    period_ns = block * 1e9 / fs
    span_ns = round((block - 1) * 1e9 / fs)
    start = 5_000_000_000
    # a backlog: each block of a channel published 0.5 s after the one before (not 0.1024 s),
    # so the feeder falls further behind its schedule with every round
    publish = [start + r * 500_000_000 for r in range(6)]
    due = [start + round(r * period_ns) for r in range(6)]
    stamped = [stamp_ns(d, period_ns, now_ns=p) - span_ns for d, p in zip(due, publish, strict=True)]
    by_publish_time = [p - span_ns for p in publish]

    def verdicts(t0s: list[int]) -> list[object]:
        out = []
        for r in range(1, len(t0s)):
            next_t0 = t0s[r - 1] + round(block * 1e9 / fs)
            out.append(check_continuity(r - 1, next_t0, r, t0s[r], block, fs))
        return out

    assert all(v == CONTINUES for v in verdicts(stamped))
    assert all(v != CONTINUES and v.time_jump_ns > 0 for v in verdicts(by_publish_time))  # the old stamping
    # on time (published 3 ms after due): the publish time; late: at most 10 ms after due
    assert stamp_ns(start, period_ns, now_ns=start + 3_000_000) == start + 3_000_000
    assert stamp_ns(start, period_ns, now_ns=start + 4_000_000_000) == start + 10_000_000
