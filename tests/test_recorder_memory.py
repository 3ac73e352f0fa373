"""A finished recording file's writer is freed at once, not at the next full garbage
collection: its chunk and message indexes (hundreds of entries a chunk at 200 channels) and
its compressor would otherwise pile up across rotations, which is what made the daemon's
RSS climb file after file with recording on (``tests/test_soak_rotation.py``)."""

from __future__ import annotations

import gc
import weakref

import numpy as np
from conftest import make_config

from sinewatch.core.pipeline import Pipeline
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.runtime.replay import replay
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import RecordingSection


def test_a_finished_files_writer_is_freed_without_a_full_collection(tmp_path):
    config = make_config(
        tmp_path,
        recording=RecordingSection(
            directory=tmp_path / "rec", rotate_seconds=None, rotate_bytes=None, chunk_size_bytes=4096
        ),
    )
    recorder = McapRecorder(config, snapshot=lambda: pipeline.snapshot())
    pipeline = Pipeline(config, [recorder])
    t = np.arange(400) / 10_000.0
    writers = []
    gc.disable()  # only reference counting frees what follows
    try:
        for f in range(3):
            for seq in range(f * 10, f * 10 + 10):
                for ch in ("m/a", "m/b"):
                    blk = Block(ch, seq, seq * 40_000_000, 10_000.0, np.sin(2 * np.pi * 50 * (t + seq * 0.04)))
                    pipeline.process(f"sinewatch/in/{ch}", encode_block_binary(blk), BLOCK_BINARY_ENCODING, seq)
            writers.append(weakref.ref(recorder._writer))
            recorder.rotate()
        recorder.close()
        alive = [w() is not None for w in writers]
    finally:
        gc.enable()
    assert alive == [False, False, False]
    assert replay(recorder.paths).ok  # the files are what they were
