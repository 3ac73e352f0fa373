"""Debugging a recording: a time window and channel globs for ``replay`` and ``export``,
replayed from the state snapshot before the window, bit for bit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import make_config
from mcap.reader import make_reader

from sinewatch.apps.cli import main
from sinewatch.apps.feed import make_channels
from sinewatch.core.pipeline import Pipeline
from sinewatch.core.window import ChannelFilter, Window, WindowError, parse_time
from sinewatch.outputs.recorder import SNAPSHOT_NAME, McapRecorder
from sinewatch.runtime.replay import replay, seek_point
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import RecordingSection

T0 = 1_764_000_000_000_000_000  # log time of the first block, ns since the epoch
BLOCK = 400  # samples at 10 kHz: 40 ms
CHANNELS = ["demo-biased", "demo-ramp", "demo-faulty-sensor"]


def record(tmp_path: Path, n_blocks: int = 100, snapshot_interval_s: float | None = 1.0, name: str = "rec") -> Path:
    """4 s of three channels through the real pipeline and recorder, log time = each
    block's end (as a daemon receiving it in real time), a state snapshot every second;
    the faulty sensor drops, duplicates and corrupts blocks."""
    config = make_config(
        tmp_path,
        recording=RecordingSection(
            directory=tmp_path / name, rotate_seconds=None, rotate_bytes=None, snapshot_interval_s=snapshot_interval_s
        ),
    )
    recorder = McapRecorder(config, snapshot=lambda: pipeline.snapshot())
    pipeline = Pipeline(config, [recorder])
    streams = make_channels(CHANNELS, prefix="win")
    for i in range(n_blocks):
        for j, ch in enumerate(streams):
            x, _ = ch.stream.read(BLOCK)
            if ch.channel.endswith("faulty-sensor") and i % 23 == 22:
                continue  # dropped: a gap
            if ch.channel.endswith("faulty-sensor") and i % 31 == 30:
                x = x.copy()
                x[5] = np.nan  # rejected
            blk = Block(ch.channel, i, i * 40_000_000, 10_000.0, x)
            payload = encode_block_binary(blk)
            log_time = T0 + (i + 1) * 40_000_000 + j
            pipeline.process(f"sinewatch/in/{ch.channel}", payload, BLOCK_BINARY_ENCODING, log_time)
            if ch.channel.endswith("faulty-sensor") and i % 37 == 36:  # duplicated: rejected
                pipeline.process(f"sinewatch/in/{ch.channel}", payload, BLOCK_BINARY_ENCODING, log_time + 5)
    pipeline.release_held(T0 + (n_blocks + 1) * 40_000_000)  # the input's end, as a daemon's drain
    recorder.close()
    [path] = recorder.paths
    return path


def messages(path: Path, role: str = "estimate") -> list[tuple[int, str, bytes]]:
    """(log time, topic, payload) of every message of ``role``, in file order."""
    with open(path, "rb") as f:
        return [
            (m.log_time, c.topic, bytes(m.data))
            for _, c, m in make_reader(f).iter_messages(log_time_order=False)
            if c.metadata.get("role") == role
        ]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return record(tmp_path_factory.mktemp("window"))


def test_time_syntax():
    assert parse_time("+2.5s").relative_ns == 2_500_000_000
    assert parse_time("+2500ms").relative_ns == 2_500_000_000
    assert parse_time("+2.5").relative_ns == 2_500_000_000
    assert parse_time("+7ns").relative_ns == 7
    assert parse_time("+1.5min").relative_ns == 90_000_000_000
    assert parse_time("1764000000123456789").absolute_ns == 1_764_000_000_123_456_789
    assert parse_time("2025-11-24T16:00:00.25Z").absolute_ns == 1_764_000_000_250_000_000
    assert parse_time("2025-11-24T17:00:00.25+01:00").absolute_ns == 1_764_000_000_250_000_000
    with pytest.raises(WindowError, match=r"expected \+SECONDS.*got 'yesterday'"):
        parse_time("yesterday")
    with pytest.raises(WindowError, match="--end: expected a time after --start"):
        Window.parse("+3s", "+2s")


def test_snapshots_are_written_every_interval_of_log_time(recording):
    with open(recording, "rb") as f:
        snaps = [a.log_time for a in make_reader(f).iter_attachments() if a.name == SNAPSHOT_NAME]
    # the first input (T0 + 40 ms) is the reference; then one at the first input >= 1 s after
    assert [round((t - T0) / 1e6) for t in snaps] == [1040, 2040, 3040]


def test_a_window_replays_bit_for_bit_from_the_snapshot_before_it(recording, tmp_path):
    full = replay([recording], out=tmp_path / "full.mcap")  # the same estimator: a check and a copy
    assert full.ok
    window = Window.parse("+2.2s", "+3.1s")
    positions = []
    part = replay(
        [recording], window=window, out=tmp_path / "win.mcap", on_progress=lambda _, pos: positions.append(pos)
    )
    assert part.ok and part.matched == part.recorded_estimates > 0
    # the file was read from the snapshot on (the summary's index), not from its start
    offset, _, _ = seek_point(recording, T0 + 40_000_000 + 2_200_000_000)
    assert min(positions) > offset > recording.stat().st_size / 3
    # it ran from the snapshot 2 s after the start, not from the start: 3 channels x 5 blocks of warm-up
    assert part.started_from == "snapshot at +2.000 s" and part.warmup_inputs == 15
    start, end = T0 + 40_000_000 + 2_200_000_000, T0 + 40_000_000 + 3_100_000_000
    expected = [m for m in messages(tmp_path / "full.mcap") if start <= m[0] < end]
    got = messages(tmp_path / "win.mcap")
    assert len(got) == part.matched and got == expected  # the same bytes, at the same log times
    # the window's recording starts with the state at its start: it replays on its own
    again = replay([tmp_path / "win.mcap"])
    assert again.ok and again.matched == len(got)


def test_a_window_and_channel_glob_select_exactly_their_estimates(recording, tmp_path):
    r = replay([recording], window=Window.parse("+1.5s", None), channels=ChannelFilter.of(["*faulty*"]))
    assert r.ok and r.started_from == "snapshot at +1.000 s"
    recorded = [m for m in messages(recording) if m[0] >= T0 + 40_000_000 + 1_500_000_000 and "faulty" in m[1]]
    assert r.matched == len(recorded) > 0
    # rejected inputs of the window: the NaN blocks 61 and 92 and the duplicate of block 73
    assert r.recorded_errors == r.produced_errors == 3
    assert r.window == "from +1.500 s"


def test_a_recording_without_periodic_snapshots_replays_its_window_from_the_start(tmp_path):
    path = record(tmp_path, n_blocks=40, snapshot_interval_s=None)
    r = replay([path], window=Window.parse("+1s", "+1.2s"))
    assert r.ok and r.started_from == "run start" and r.matched == 3 * 5
    assert r.warmup_inputs == 3 * 25 - 1  # every block before the window (blocks 0-24), less the one dropped


def test_export_takes_the_window_and_channel_globs(recording, tmp_path):
    assert (
        main(
            [
                "export",
                str(recording),
                "--out",
                str(tmp_path),
                "--no-progress",
                "--samples",
                "--start",
                "+1s",
                "--end",
                "+2s",
                "--channels",
                "*ramp",
                "--channels",
                "*biased",
            ]
        )
        == 0
    )
    stem = recording.name.removesuffix(".mcap")
    est = pd.read_csv(tmp_path / f"{stem}.estimates.csv")
    origin = T0 + 40_000_000
    expected = [
        json.loads(p)
        for t, topic, p in messages(recording)
        if origin + 1_000_000_000 <= t < origin + 2_000_000_000 and "faulty" not in topic
    ]
    assert len(expected) == 2 * 25
    assert sorted(zip(est["channel"], est["seq"], strict=True)) == sorted((m["channel"], m["seq"]) for m in expected)
    samples = pd.read_csv(tmp_path / f"{stem}.samples.csv")
    assert set(samples["seq"]) == set(range(25, 50)) and len(samples) == 2 * 25 * BLOCK


def test_a_window_in_a_later_file_starts_from_that_files_snapshot(tmp_path):
    from conftest import record_run

    paths, _ = record_run(tmp_path, n_blocks=60, rotate_seconds=1.0)  # 3 files, log times 1001, 1002, ...
    assert len(paths) == 3
    assert replay(paths, out=tmp_path / "whole.mcap").ok
    part = replay(paths, window=Window.parse("+70ns", "+100ns"), out=tmp_path / "part.mcap")
    # file 2 starts at block 25, the 51st input (block 30 of the ramp is missing): +50 ns
    assert part.ok and part.started_from == "snapshot at +0.000 s" and part.warmup_inputs == 70 - 50
    expected = [m for m in messages(tmp_path / "whole.mcap") if 1001 + 70 <= m[0] < 1001 + 100]
    assert messages(tmp_path / "part.mcap") == expected and len(expected) == part.matched == 30


def test_a_rerun_of_a_window_is_that_window_of_the_whole_rerun(recording, tmp_path):
    from sinewatch.schemas.config import EstimatorRule

    rules = [EstimatorRule(match="sinewatch/in/**", estimator="ipdft", params={"nominal_frequency_hz": 50.0})]
    replay([recording], rules=rules, out=tmp_path / "full.mcap")
    part = replay(
        [recording],
        rules=rules,
        window=Window.parse("+2.2s", "+3.1s"),
        channels=ChannelFilter.of("*faulty*"),
        out=tmp_path / "win.mcap",
    )
    # another estimator cannot start from the recorded one's snapshot: the run's start, as warm-up
    assert part.started_from == "run start" and part.warmup_inputs > 50
    start, end = T0 + 40_000_000 + 2_200_000_000, T0 + 40_000_000 + 3_100_000_000
    expected = [m for m in messages(tmp_path / "full.mcap") if start <= m[0] < end and "faulty" in m[1]]
    got = messages(tmp_path / "win.mcap")
    assert got == expected and len(got) == part.produced_estimates > 15
    assert json.loads(got[0][2])["estimator"] == "ipdft"


def test_a_window_of_a_recording_made_under_earlier_validity_rules_replays_under_them(tmp_path, monkeypatch):
    """A file recorded under validity rules version 1 (as an earlier build wrote it: the
    recorder states version 1, the pipeline coasts across a sender's restart) replays bit for
    bit whole and in a window: both loops rebuild the pipeline with the file's rules (under
    today's, the restart would reset the estimator and every estimate after it differ)."""
    import sinewatch.outputs.recorder as recorder_module

    monkeypatch.setattr(recorder_module, "VALIDITY_RULES_VERSION", 1)
    config = make_config(tmp_path, recording=RecordingSection(directory=tmp_path / "v1", rotate_seconds=None))
    recorder = McapRecorder(config, snapshot=lambda: pipeline.snapshot())
    pipeline = Pipeline(config, [recorder], validity_version=1)
    [stream] = make_channels(["demo-biased"], prefix="v1")
    for i in range(60):
        x, _ = stream.stream.read(BLOCK)
        seq = i if i < 30 else i - 30  # the sender restarts its count; its time goes on
        payload = encode_block_binary(Block(stream.channel, seq, i * 40_000_000, 10_000.0, x))
        pipeline.process(f"sinewatch/in/{stream.channel}", payload, BLOCK_BINARY_ENCODING, T0 + (i + 1) * 40_000_000)
    recorder.close()
    [path] = recorder.paths
    whole = replay([path])
    assert whole.ok and whole.matched == 60
    windowed = replay([path], window=Window.parse("+0.4s", None))
    assert windowed.ok, [m.describe() for m in windowed.mismatches[:3]]
    assert windowed.matched > 40
