"""Rewrite one estimator's estimate messages in a recording fixture with this build's bytes, and
nothing else: ``python tests/rewrite_fixture_estimates.py FILE TOPIC``.

For a change that truly alters an estimator's arithmetic (the fixture's docstring in
tests/test_recording_compatibility.py says when it was used and why). It replays FILE, takes
the mismatches on TOPIC (each recorded message must be the one the replay names; mismatches
on other topics are listed and left as recorded), copies every record of FILE in order with those messages' data replaced, then
reads both files back and checks that the header, schemas, channels, metadata, attachments and
every other message (channel, sequence, times, bytes) are identical.
"""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from mcap.records import Attachment, Channel, DataEnd, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from sinewatch.runtime.replay import replay


def replacements(path: Path, topic: str) -> dict[int, tuple[bytes, bytes]]:
    """index among the topic's messages -> (recorded, produced)."""
    result = replay([path])
    out = {}
    for m in result.mismatches:
        if m.topic != topic:
            print(f"left as recorded: {m.describe()[:160]}")
        elif m.recorded is None or m.produced is None:
            raise SystemExit(f"expected a recorded and a produced message, got {m.describe()}")
        else:
            out[m.index] = (m.recorded, m.produced)
    return out


def copy_with(path: Path, dest: Path, topic: str, new: dict[int, tuple[bytes, bytes]]) -> int:
    """Copy every record of path to dest in order, the messages in ``new`` replaced."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunk_size = max(c.uncompressed_size for c in summary.chunk_indexes) + 1
    compression = CompressionType[next(iter({c.compression for c in summary.chunk_indexes})).upper()]
    topics: dict[int, str] = {}
    seen: dict[str, int] = defaultdict(int)
    done = 0
    with open(path, "rb") as f, open(dest, "wb") as g:
        writer = Writer(g, chunk_size=chunk_size, compression=compression)
        for r in StreamReader(f).records:
            if isinstance(r, DataEnd):  # the summary after it repeats schemas and channels
                break
            if isinstance(r, Header):
                writer.start(profile=r.profile, library=r.library)
            elif isinstance(r, Schema):
                assert writer.register_schema(r.name, r.encoding, r.data) == r.id
            elif isinstance(r, Channel):
                assert writer.register_channel(r.topic, r.message_encoding, r.schema_id, r.metadata) == r.id
                topics[r.id] = r.topic
            elif isinstance(r, Message):
                data = r.data
                if topics[r.channel_id] == topic:
                    k = seen[topic]
                    seen[topic] += 1
                    if k in new:
                        assert new[k][0] == data, f"message {k} is not the one the replay named"
                        data = new[k][1]
                        done += 1
                writer.add_message(r.channel_id, r.log_time, data, r.publish_time, r.sequence)
            elif isinstance(r, Metadata):
                writer.add_metadata(r.name, r.metadata)
            elif isinstance(r, Attachment):
                writer.add_attachment(r.create_time, r.log_time, r.name, r.media_type, r.data)
        writer.finish()
    return done


def records(path: Path) -> list[Any]:
    """Every content record of the data section in file order (chunks and indexes left out)."""
    keep = (Header, Schema, Channel, Message, Metadata, Attachment)
    out = []
    with open(path, "rb") as f:
        for r in StreamReader(f).records:
            if isinstance(r, DataEnd):
                break
            if isinstance(r, keep):
                out.append(r)
    return out


def main(path: Path, topic: str) -> None:
    new = replacements(path, topic)
    tmp = path.with_suffix(".new")
    done = copy_with(path, tmp, topic, new)
    assert done == len(new), (done, len(new))
    old_records, new_records = records(path), records(tmp)
    assert len(old_records) == len(new_records)
    changed = [i for i, (a, b) in enumerate(zip(old_records, new_records, strict=True)) if a != b]
    assert len(changed) == done, (len(changed), done)
    for i in changed:
        a, b = old_records[i], new_records[i]
        assert isinstance(a, Message) and isinstance(b, Message)
        assert (a.channel_id, a.sequence, a.log_time, a.publish_time) == (
            b.channel_id,
            b.sequence,
            b.log_time,
            b.publish_time,
        )
    tmp.replace(path)
    print(f"{path}: {done} messages on {topic} rewritten; {len(old_records) - done} records identical")


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2])
