"""The recorder's FastWriter writes MCAP files byte for byte as mcap's own Writer does for the
same calls (chunk boundaries, compression, message indexes, statistics, CRCs), and the files
read back with mcap's reader, CRCs checked, and replay bit for bit."""

from __future__ import annotations

import io

import numpy as np
import pytest
import zstandard
from conftest import make_config
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import CompressionType, Writer

from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.outputs.recorder import RECORDING_ZSTD_LEVEL, FastWriter, McapRecorder
from sinewatch.runtime.replay import replay
from sinewatch.schemas.codec import Block, encode_block_binary
from sinewatch.schemas.config import RecordingSection
from sinewatch.schemas.input_record import decode_input_record


def _write(cls, compression: CompressionType, chunk_size: int, seed: int) -> tuple[bytes, list[tuple]]:
    """The same seeded sequence of calls on a Writer of class ``cls``: its bytes and messages."""
    rng = np.random.default_rng(seed)
    out = io.BytesIO()
    w = cls(out, chunk_size=chunk_size, compression=compression)
    w.start(profile="", library="test")
    w.add_metadata("m", {"a": "1"})
    sid = w.register_schema("s", "jsonschema", b"{}")
    channels = [w.register_channel("t/0", "json", sid, {"role": "x"})]
    messages = []
    t = 1_763_900_000_000_000_000
    for i in range(3000):
        if i in (700, 1900):  # channels registered mid-file land in the open chunk
            channels.append(w.register_channel(f"t/{len(channels)}", "json", sid, {}))
        if i == 1200:
            w.flush()  # the recorder's timed flush: closes the open chunk
        if i == 2500:
            w.add_attachment(t, t, "a", "application/json", b"{}")
        t += int(rng.integers(-2_000, 10_000))  # log times not monotonic either
        cid = int(rng.choice(channels))
        size = int(rng.choice([0, 1, 37, 600, 5000]))
        # noise, or JSON-like text the compressors do shrink
        data = rng.bytes(size) if rng.random() < 0.5 else (b'{"seq":%d,"x":[0.5,1.25]}' % i * size)[:size]
        seq, pub = int(rng.integers(0, 2**32)), int(rng.integers(0, 2**63))
        w.add_message(cid, t, data, pub, seq)
        messages.append((cid, seq, t, pub, data))
    w.finish()
    return out.getvalue(), messages


def test_the_recorders_zstd_level_changes_the_chunks_bytes_not_the_messages():
    """The recorder compresses at RECORDING_ZSTD_LEVEL (1), mcap's Writer at 3: other chunk
    bytes, the same messages read back, CRCs checked; level 1 is the one in the file."""
    ref, messages = _write(Writer, CompressionType.ZSTD, 1 << 16, seed=9)

    class Level1(FastWriter):
        def __init__(self, out, *, chunk_size, compression):
            super().__init__(out, chunk_size=chunk_size, compression=compression, zstd_level=RECORDING_ZSTD_LEVEL)

    fast, _ = _write(Level1, CompressionType.ZSTD, 1 << 16, seed=9)
    assert RECORDING_ZSTD_LEVEL == 1 and fast != ref
    reader = make_reader(io.BytesIO(fast), validate_crcs=True)
    got = [(m.channel_id, m.sequence, m.log_time, m.publish_time, m.data) for _, _, m in reader.iter_messages()]
    assert sorted(got, key=lambda m: m[2]) == sorted(messages, key=lambda m: m[2])
    chunks = list(reader.get_summary().chunk_indexes)
    assert chunks and all(c.compression == "zstd" for c in chunks)
    # the frame header of each chunk's data says nothing of the level; compressing a chunk's
    # records again at level 1 gives its bytes exactly (zstd is deterministic per level)
    c = chunks[0]
    stored = fast[c.chunk_start_offset + 9 :][: c.chunk_length - 9]
    data = stored[-c.compressed_size :]
    raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=c.uncompressed_size)
    assert zstandard.ZstdCompressor(level=1).compress(raw) == data
    assert zstandard.ZstdCompressor(level=3).compress(raw) != data


@pytest.mark.parametrize("compression", [CompressionType.NONE, CompressionType.LZ4, CompressionType.ZSTD])
@pytest.mark.parametrize("chunk_size", [1024, 1 << 20])
def test_fast_writer_bytes_are_mcap_writers_bytes(compression, chunk_size):
    ref, messages = _write(Writer, compression, chunk_size, seed=5)
    fast, _ = _write(FastWriter, compression, chunk_size, seed=5)
    assert fast == ref
    # and mcap reads them back: every message, in order, chunk CRCs checked
    reader = make_reader(io.BytesIO(fast), validate_crcs=True)
    got = [
        (m.channel_id, m.sequence, m.log_time, m.publish_time, m.data)
        for _, _, m in reader.iter_messages(log_time_order=False)
    ]
    assert got == messages
    summary = reader.get_summary()
    assert summary.statistics.message_count == len(messages)
    assert summary.statistics.message_start_time == min(m[2] for m in messages)
    assert summary.statistics.message_end_time == max(m[2] for m in messages)
    if chunk_size == 1024:
        assert summary.statistics.chunk_count > 100
    streamed = [
        m.data for _, _, m in NonSeekingReader(io.BytesIO(fast), validate_crcs=True).iter_messages(log_time_order=False)
    ]
    assert streamed == [m[4] for m in messages]


def test_a_pipeline_recording_reads_back_with_crcs_and_replays_bit_for_bit(tmp_path):
    config = make_config(tmp_path, recording=RecordingSection(directory=tmp_path / "rec", chunk_size_bytes=4096))
    recorder = McapRecorder(config)
    pipeline = Pipeline(config, [NullSink(), recorder])
    fs, n = 10_000.0, 1024
    x = np.sin(2 * np.pi * 50 * np.arange(n * 30) / fs).astype(np.float32)
    payloads = []
    for i in range(30):
        for ch in ("a", "b"):
            t0 = 1_763_900_000_000_000_000 + round(i * n * 1e9 / fs)
            payload = encode_block_binary(Block(ch, i, t0, fs, x[i * n : (i + 1) * n]), "float32")
            payloads.append(payload)
            pipeline.process(f"sinewatch/in/{ch}", payload, "", t0)
    assert type(recorder._writer) is FastWriter  # this mcap's internals are the ones FastWriter knows
    pipeline.release_held(t0 + 1)  # the input's end, as the daemon's drain: every held estimate out
    pipeline.close_sinks()
    (path,) = recorder.paths
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        inputs = [m.data for _, c, m in reader.iter_messages(log_time_order=False) if c.metadata["role"] == "input"]
        assert [decode_input_record(data) for data in inputs] == [(p, "") for p in payloads]
        assert reader.get_summary().statistics.chunk_count > 10
    result = replay([path])
    assert result.ok and result.matched == 60 == result.recorded_estimates


class _RefusingFile(io.BytesIO):
    """A file whose writes fail with ENOSPC once ``room`` bytes are in it."""

    def __init__(self, room: int) -> None:
        super().__init__()
        self.room = room

    def write(self, data) -> int:  # type: ignore[override]
        if self.tell() + len(data) > self.room:
            raise OSError(28, "No space left on device")
        return super().write(data)


def test_a_chunk_write_that_fails_in_the_background_raises_in_the_writer_s_next_call():
    """Chunks are compressed and written on another thread: a write that fails there (a full
    disk) is raised by the writer's next call that needs the file, so the recorder's guard
    sees it and reports it, as it did when the write was synchronous."""
    w = FastWriter(_RefusingFile(room=20_000), chunk_size=4096, compression=CompressionType.NONE)
    w.start(profile="", library="test")
    sid = w.register_schema("s", "jsonschema", b"{}")
    cid = w.register_channel("t", "json", sid, {})
    with pytest.raises(OSError, match="No space left"):
        for i in range(100):  # 100 x 1 KB: the fifth chunk does not fit
            w.add_message(cid, i, b"x" * 1000, i, i)
        w.flush()


def _rotating_recording(tmp_path, name: str) -> list[int]:
    """Messages per file of a recording rotated by size (64 KiB chunks, 150 kB files)."""
    section = RecordingSection(directory=tmp_path / name, chunk_size_bytes=1 << 16, rotate_bytes=150_000)
    config = make_config(tmp_path, recording=section)
    recorder = McapRecorder(config, snapshot=lambda: {})
    pipeline = Pipeline(config, [NullSink(), recorder])
    x = np.random.default_rng(3).standard_normal(1024 * 100).astype(np.float32)
    for i in range(100):
        t0 = 1_763_900_000_000_000_000 + round(i * 1024 * 1e5)
        payload = encode_block_binary(Block("a", i, t0, 10_000.0, x[i * 1024 : (i + 1) * 1024]), "float32")
        pipeline.process("sinewatch/in/a", payload, "", t0)
    pipeline.release_held(t0 + 1)  # the input's end, as the daemon's drain
    pipeline.close_sinks()
    counts = []
    for path in recorder.paths:
        with open(path, "rb") as f:
            counts.append(make_reader(f, validate_crcs=True).get_summary().statistics.message_count)
    return counts


def test_rotation_by_size_falls_on_the_same_block_at_every_run(tmp_path):
    """The file's size that rotation reads is taken where the writer waits for its chunk in
    flight, not from a file position another thread moves: the same files at every run."""
    first = _rotating_recording(tmp_path, "one")
    assert len(first) >= 2 and sum(first) == 200  # 100 inputs and 100 estimates
    assert [_rotating_recording(tmp_path, f"again{i}") for i in range(3)] == [first] * 3


def test_a_writer_finished_after_its_chunk_thread_is_gone_writes_the_chunks_itself(monkeypatch):
    """At interpreter exit the chunk thread takes no more work: a file finished then (an
    atexit handler's) is written on the calling thread, the same bytes."""
    from concurrent.futures import ThreadPoolExecutor

    import sinewatch.outputs.recorder as recorder_module

    gone = ThreadPoolExecutor(max_workers=1)
    gone.shutdown()
    monkeypatch.setattr(recorder_module, "_CHUNK_THREAD", gone)
    ref, _ = _write(Writer, CompressionType.ZSTD, 1024, seed=7)
    fast, _ = _write(FastWriter, CompressionType.ZSTD, 1024, seed=7)
    assert fast == ref


def test_bench_recorder_compression_compresses_one_chunk_every_way():
    from sinewatch.apps.bench.recorder_compression import measure

    rows = {r["compression"]: r for r in measure(1 << 16, 2, 1)}
    assert list(rows) == ["none", "lz4", "zstd level 1 (the recorder's)", "zstd level 3 (mcap's)"]
    assert rows["none"]["bytes_fraction"] == 1.0
    # float32 samples of a noisy sine: each compressor saves something, zstd more than lz4
    assert rows["zstd level 1 (the recorder's)"]["bytes_fraction"] < rows["lz4"]["bytes_fraction"] < 0.95
    assert rows["zstd level 3 (mcap's)"]["cpu_vs_zstd3"] == 1.0
