"""A promoted standby's recording directory replays as a whole: its first file, written while
it stood by, holds status messages only; the file it starts at the takeover carries the
state it took over (as :meth:`sinewatch.runtime.cluster.ClusterMember.take_over` does it)."""

from __future__ import annotations

import json

import numpy as np
from conftest import FakeClock, make_config

from sinewatch.apps.cli import main
from sinewatch.core.pipeline import NullSink, Pipeline, ResumePoint
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.runtime.replay import replay
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import RecordingSection

CHANNELS = ["sb/a", "sb/b"]


def block(ch: str, seq: int) -> bytes:
    i = CHANNELS.index(ch)
    t = (seq * 400 + np.arange(400)) / 10_000.0
    return encode_block_binary(Block(ch, seq, seq * 40_000_000, 10_000.0, np.sin(2 * np.pi * 50.0 * t + i)))


def test_a_promoted_standbys_directory_replays(tmp_path):
    config = make_config(
        tmp_path, recording=RecordingSection(directory=tmp_path / "s1", rotate_seconds=None, rotate_bytes=None)
    )
    active = Pipeline(config, [NullSink()])
    for seq in range(20):
        for ch in CHANNELS:
            active.process(f"sinewatch/in/{ch}", block(ch, seq), BLOCK_BINARY_ENCODING, seq)
    snapshot = json.loads(json.dumps(active.snapshot()))  # as it travels on the snapshot key

    # the standby: a file with its status messages only ...
    recorder = McapRecorder(config, snapshot=lambda: standby.snapshot(), clock=FakeClock())
    standby = Pipeline(config, [recorder])
    recorder.open()
    for i in range(3):
        recorder.on_status("sinewatch/status/s1", json.dumps({"standby": i}).encode(), i)
    # ... then the takeover: the snapshot, a resume point per channel, a new file
    standby.restore(snapshot)
    for ch in CHANNELS:
        standby.resume_points[ch] = ResumePoint(19, 20 * 40_000_000)
    recorder.rotate()
    for seq in range(20, 40):
        for ch in CHANNELS:
            standby.process(f"sinewatch/in/{ch}", block(ch, seq), BLOCK_BINARY_ENCODING, 100 + seq)
    recorder.close()

    paths = sorted((tmp_path / "s1").glob("*.mcap"))
    assert len(paths) == 2 and standby.counters.estimates == 40
    r = replay(paths)
    assert r.ok and r.matched == r.recorded_estimates == 40, r
    assert main(["replay", *map(str, paths), "--no-progress"]) == 0
