"""Nothing one input, one estimator or one sink does stops the daemon (reliability item 0).

Each test runs a live daemon on loopback Zenoh, injects one fault and checks that every
other channel goes on, that the fault is reported (ErrorReport kind, Status count) and
that no estimator state was touched (a clean pipeline fed only the good blocks agrees
bit for bit).
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import TIMEOUT, clean_estimates, make_config, run_daemon, take
from mcap.reader import make_reader

from sinewatch.apps.feed import make_channels
from sinewatch.clients import BlockPublisher, JsonSubscription, connect, subscribe_errors, subscribe_estimates
from sinewatch.runtime.replay import replay
from sinewatch.schemas.codec import Block, encode_block_binary
from sinewatch.schemas.config import RecordingSection
from sinewatch.schemas.messages import ErrorReport, SinkStatus, Status

JSON_ENC = "application/json;sinewatch/SampleBlock@1"


def _blocks(channel: str, n: int, start_seq: int = 0, block: int = 500, fs: float = 10_000.0) -> list[Block]:
    stream = make_channels(["demo-biased"], prefix="f")[0].stream
    samples = [stream.read(block)[0] for _ in range(start_seq + n)][start_seq:]
    dt_ns = int(block * 1e9 / fs)
    return [
        Block(channel, start_seq + i, 1_000_000_000 + (start_seq + i) * dt_ns, fs, s) for i, s in enumerate(samples)
    ]


def _json_block(**fields) -> bytes:
    msg = {"format_version": 1, "channel": "f/a", "seq": 99, "t0_ns": 0, "sample_rate_hz": 10_000.0}
    msg.update(fields)
    return json.dumps(msg).encode()


def _malformed_payloads() -> list[bytes]:
    """The payloads that used to end the consumer task, plus seeded random bytes."""
    rng = random.Random(16)
    payloads = [
        _json_block(columns=1, samples=[[1.0, 2.0], [3.0]]),  # ragged rows, one column announced
        _json_block(columns=2, samples=[[1.0, 2.0], [3.0]]),  # ragged rows, two columns
        b"{" + b'"samples":' + b"[" * 100_000,  # nesting deep enough to exhaust the JSON parser
        b"SWSB" + bytes(rng.randrange(256) for _ in range(60)),  # binary magic, random header
    ]
    payloads += [bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200))) for _ in range(40)]
    return payloads


def _publish_pairs(pub, a_blocks, b_blocks, indices):
    """Blocks of channels f/a and f/b, alternately."""
    for i in indices:
        pub.publish_raw("f/a", encode_block_binary(a_blocks[i]))
        pub.publish_raw("f/b", encode_block_binary(b_blocks[i]))


def _strip(msg):
    return {k: v for k, v in msg.items() if k != "_key"}


def _status_where(status_sub, predicate) -> dict | None:
    while (msg := status_sub.get(timeout=TIMEOUT)) is not None:
        if predicate(msg):
            return msg
    return None


def test_malformed_blocks_are_rejected_and_every_channel_goes_on(tmp_path):
    config = make_config(tmp_path)
    bad = _malformed_payloads()
    a_blocks, b_blocks = _blocks("f/a", 8), _blocks("f/b", 8)

    def client(daemon, ep):
        with connect([ep]) as s, JsonSubscription(s, "sinewatch/status/**") as status:
            est, err = subscribe_estimates(s), subscribe_errors(s)
            pub = BlockPublisher(s)
            assert pub.wait_for_subscriber("f/a", TIMEOUT)
            _publish_pairs(pub, a_blocks, b_blocks, range(4))
            for payload in bad:
                pub.publish_raw("f/a", payload, JSON_ENC if payload[:1] == b"{" else None)
            _publish_pairs(pub, a_blocks, b_blocks, range(4, 8))
            estimates, errors = take(est, 16), take(err, len(bad))
            st = _status_where(status, lambda m: m["blocks_processed"] == 16 + len(bad))
            return estimates, errors, st

    (estimates, errors, st), _daemon, code = run_daemon(config, client)
    assert code == 0
    assert len(errors) == len(bad)
    for e in errors:
        report = ErrorReport.model_validate(_strip(e))
        assert report.kind.value in {"decode_error", "unsupported_version"}, report
    assert "expected rows of equal length" in errors[0]["message"]
    by_channel = {"f/a": [], "f/b": []}
    for e in estimates:
        by_channel[e["channel"]].append(_strip(e))
    assert by_channel["f/a"] == clean_estimates(config, "sinewatch/in/f/a", a_blocks)
    assert by_channel["f/b"] == clean_estimates(config, "sinewatch/in/f/b", b_blocks)
    status = Status.model_validate(_strip(st))
    assert status.errors == len(bad)
    assert sum(status.errors_by_kind.values()) == len(bad)
    assert all(s.ok and s.failures == 0 for s in status.sinks)


def test_an_estimator_that_raises_is_isolated_to_its_channel_and_keeps_its_state(tmp_path):
    config = make_config(tmp_path)
    a_blocks, b_blocks = _blocks("f/a", 6), _blocks("f/b", 6)
    poison = Block("f/a", 3, a_blocks[3].t0_ns, 10_000.0, np.full(500, 12345.0))

    def client(daemon, ep):
        with connect([ep]) as s:
            est, err = subscribe_estimates(s), subscribe_errors(s)
            pub = BlockPublisher(s)
            assert pub.wait_for_subscriber("f/a", TIMEOUT)
            _publish_pairs(pub, a_blocks, b_blocks, range(3))
            first = take(est, 6)
            # A fault inside f/a's estimator (a kernel bug, say) on one particular block.
            estimator = daemon.pipeline.channels["f/a"].estimator
            run = estimator._run

            def faulty_run(samples, state, last_only):
                if samples[0] == 12345.0:
                    raise ZeroDivisionError("injected kernel fault")
                return run(samples, state, last_only)

            estimator._run = faulty_run
            pub.publish_raw("f/a", encode_block_binary(poison))
            _publish_pairs(pub, a_blocks, b_blocks, range(3, 6))
            return first + take(est, 6), take(err, 1)

    (estimates, errors), daemon, code = run_daemon(config, client)
    assert code == 0
    [fault] = errors
    assert fault["kind"] == "estimator_fault" and fault["channel"] == "f/a" and fault["seq"] == 3
    assert "ZeroDivisionError: injected kernel fault" in fault["message"]
    a = [_strip(e) for e in estimates if e["channel"] == "f/a"]
    b = [_strip(e) for e in estimates if e["channel"] == "f/b"]
    # seq 3 was consumed by the fault, so the next good block (also seq 3) is accepted,
    # and the estimator continues from exactly the state it had before the fault
    assert a == clean_estimates(config, "sinewatch/in/f/a", a_blocks)
    assert b == clean_estimates(config, "sinewatch/in/f/b", b_blocks)
    assert daemon.pipeline.counters.by_kind["estimator_fault"] == 1


# ---- a full disk ------------------------------------------------------------------------------
@contextlib.contextmanager
def _small_disk(path: Path, size_kib: int):
    """A tmpfs of ``size_kib`` mounted at ``path`` for the test (needs root, as CI has)."""
    path.mkdir(parents=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(path)], check=True)
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def _fill(directory: Path) -> Path:
    """Write until the filesystem refuses (ENOSPC); return the filler file."""
    filler = directory / "filler"
    with open(filler, "wb", buffering=0) as f:
        chunk = b"\0" * 4096
        with contextlib.suppress(OSError):
            while True:
                f.write(chunk)
    return filler


def test_a_full_disk_keeps_estimating_reports_it_and_resumes_recording(tmp_path):
    with _small_disk(tmp_path / "disk", 2048) as disk:
        config = make_config(
            tmp_path,
            recording=RecordingSection(directory=disk, flush_interval_s=0.05, chunk_size_bytes=4096),
            sink_retry_s=0.05,
        )
        blocks = _blocks("f/a", 200)

        def client(daemon, ep):
            with connect([ep]) as s, JsonSubscription(s, "sinewatch/status/**") as status:
                est, err = subscribe_estimates(s), subscribe_errors(s)
                pub = BlockPublisher(s)
                assert pub.wait_for_subscriber("f/a", TIMEOUT)
                sent = 0

                def send(n):
                    nonlocal sent
                    for blk in blocks[sent : sent + n]:
                        pub.publish_raw("f/a", encode_block_binary(blk))
                    sent += n
                    return take(est, n)

                def send_until(predicate):
                    """Blocks in fives, each followed by the next Status, until it says so."""
                    got = []
                    for _ in range(30):
                        got += send(5)
                        st = _status_where(status, lambda m: True)
                        if predicate(_mcap(st)):
                            return got, st
                    raise AssertionError("the recorder's state never changed")

                out = send(10)
                filler = _fill(disk)
                more, failed = send_until(lambda sink: not sink["ok"])
                out += more
                report = take(err, 1)
                out += send(20)  # estimation and publishing do not need the disk
                filler.unlink()  # space comes back
                more, recovered = send_until(lambda sink: sink["recoveries"] == 1 and sink["ok"])
                out += more + send(10)
                return out, report, failed, recovered, sent

        (estimates, report, failed, recovered, sent), daemon, code = run_daemon(config, client)
        assert code == 0
        assert [e["seq"] for e in estimates] == list(range(sent))  # not one estimate lost
        [rep] = report
        assert rep["kind"] == "sink_error" and "mcap failed" in rep["message"] and "No space left" in rep["message"]
        mcap_failed = SinkStatus.model_validate(_mcap(failed))
        assert not mcap_failed.ok and "No space left" in mcap_failed.last_error
        mcap_back = SinkStatus.model_validate(_mcap(recovered))
        assert mcap_back.ok and mcap_back.skipped > 0
        # The file written after the outage is finished and replays on its own, bit for bit.
        _first, resumed = daemon.recording_paths
        with open(resumed, "rb") as f:
            assert make_reader(f).get_summary() is not None
        result = replay([resumed])
        assert result.ok and result.matched > 0 and result.inputs == result.matched


def _mcap(status_msg: dict) -> dict:
    return next(s for s in status_msg["sinks"] if s["name"] == "mcap")
