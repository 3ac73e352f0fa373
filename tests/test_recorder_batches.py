"""A frame's Estimates reach the recorder's FastWriter in one call (``add_messages``): the file is
byte for byte what mcap's own Writer writes for the same messages one by one, chunk boundaries
falling inside a batch included, and McapRecorder.on_estimates writes what on_estimate writes."""

from __future__ import annotations

import io

import numpy as np
import pytest
from conftest import make_config
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from sinewatch.outputs.recorder import FastWriter, McapRecorder
from sinewatch.schemas.config import RecordingSection


def _batches(seed: int) -> list[tuple[int, int, list[tuple[int, int, bytes]]]]:
    """Seeded batches: (log time, publish time, [(channel index, sequence, data), ...]), 1-9
    messages each (a frame's estimates), log times not monotonic either."""
    rng = np.random.default_rng(seed)
    t, out = 1_763_900_000_000_000_000, []
    for i in range(600):
        t += int(rng.integers(-2_000, 10_000))
        batch = []
        for _ in range(int(rng.integers(1, 10))):
            size = int(rng.choice([0, 37, 600, 2500]))
            data = rng.bytes(size) if rng.random() < 0.5 else (b'{"seq":%d,"x":[0.5,1.25]}' % i * size)[:size]
            batch.append((int(rng.integers(0, 3)), int(rng.integers(0, 2**32)), data))
        out.append((t, int(rng.integers(0, 2**63)), batch))
    return out


def _file(batched: bool, compression: CompressionType, chunk_size: int) -> bytes:
    out = io.BytesIO()
    w = (FastWriter if batched else Writer)(out, chunk_size=chunk_size, compression=compression)
    w.start(profile="", library="test")
    sid = w.register_schema("s", "jsonschema", b"{}")
    cids = [w.register_channel(f"t/{c}", "json", sid, {}) for c in range(3)]
    for log_time, publish_time, batch in _batches(seed=11):
        messages = [(cids[c], seq, data) for c, seq, data in batch]
        if batched:
            w.add_messages(messages, log_time, publish_time)  # type: ignore[attr-defined]
        else:
            for cid, seq, data in messages:
                w.add_message(cid, log_time, data, publish_time, seq)
    w.finish()
    return out.getvalue()


@pytest.mark.parametrize("compression", [CompressionType.NONE, CompressionType.ZSTD])
@pytest.mark.parametrize("chunk_size", [1024, 1 << 20])
def test_a_batch_of_messages_is_mcaps_writer_one_message_at_a_time(compression, chunk_size):
    batched = _file(True, compression, chunk_size)
    assert batched == _file(False, compression, chunk_size)
    summary = make_reader(io.BytesIO(batched), validate_crcs=True).get_summary()
    assert summary.statistics.message_count == sum(len(b) for _, _, b in _batches(seed=11))
    if chunk_size == 1024:  # chunks were finished inside batches
        assert summary.statistics.chunk_count > 300


def test_on_estimates_writes_what_on_estimate_writes(tmp_path):
    """The same estimates through on_estimates (a batch a frame) and on_estimate (one by one):
    the same messages on the same channels with the same sequences, in the same order."""
    got = {}
    for way in ("batch", "each"):
        section = RecordingSection(directory=tmp_path / way, chunk_size_bytes=2048)
        recorder = McapRecorder(make_config(tmp_path, recording=section))
        recorder.open()
        for frame in range(40):
            estimates = [(f"sinewatch/est/c{c}", b'{"seq":%d,"c":%d}' % (frame, c)) for c in range(frame % 7 + 1)]
            if way == "batch":
                recorder.on_estimates(estimates, 1_000 + frame)
            else:
                for key, payload in estimates:
                    recorder.on_estimate(key, payload, 1_000 + frame)
        recorder.close()
        (path,) = recorder.paths
        with open(path, "rb") as f:
            got[way] = [
                (c.topic, m.sequence, m.log_time, m.data)
                for _, c, m in make_reader(f, validate_crcs=True).iter_messages(log_time_order=False)
            ]
    assert got["batch"] == got["each"] and len(got["batch"]) == sum(f % 7 + 1 for f in range(40))
