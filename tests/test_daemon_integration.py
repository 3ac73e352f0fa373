"""The daemon end to end: real Zenoh sessions on 127.0.0.1, real MCAP files, replay."""

from __future__ import annotations

import asyncio
import json
import signal
import struct
import threading

import numpy as np
import pytest
from conftest import TIMEOUT, clean_estimates, make_config, publishing, run_daemon, take
from mcap.reader import make_reader

from sinewatch.apps.feed import Feed, make_channels
from sinewatch.clients import BlockPublisher, connect, subscribe_errors, subscribe_estimates
from sinewatch.runtime.daemon import Daemon
from sinewatch.runtime.replay import replay
from sinewatch.schemas.codec import Block, encode_block_binary, encode_block_json
from sinewatch.schemas.config import LimitsSection
from sinewatch.schemas.messages import ErrorReport, Estimate


def test_blocks_in_estimates_out_recorded_and_replayed_bit_for_bit(tmp_path):
    config = make_config(tmp_path)
    names = ["demo-biased", "demo-ramp", "demo-faulty-sensor"]

    def client(_daemon, ep):
        with connect([ep]) as s:
            est, err = subscribe_estimates(s), subscribe_errors(s)
            pub = BlockPublisher(s, dtype="float64")
            channels = make_channels(names, prefix="it", duration_s=3.0)
            assert all(pub.wait_for_subscriber(c.channel, TIMEOUT) for c in channels)
            sent = Feed(pub, channels, block_size=500, realtime=False).run(3.0)
            faults = {k: sum(c.faults_injected.get(k, 0) for c in channels) for k in ("drop", "nan", "duplicate")}
            n_errors = faults["nan"] + faults["duplicate"]
            return take(est, sent - n_errors), take(err, n_errors), sent, faults, channels

    (estimates, errors, sent, faults, _channels), daemon, code = run_daemon(config, client)
    assert code == 0
    assert faults["drop"] > 0 and faults["nan"] > 0 and faults["duplicate"] > 0  # the faulty channel did its job
    # one estimate per accepted block, in order per channel, valid against the schema
    assert len(estimates) == sent - faults["nan"] - faults["duplicate"]
    per_channel = {}
    for e in estimates:
        Estimate.model_validate({k: v for k, v in e.items() if k != "_key"})
        per_channel.setdefault(e["channel"], []).append(e["seq"])
    for seqs in per_channel.values():
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert sorted(e["kind"] for e in errors) == sorted(
        ["non_finite"] * faults["nan"] + ["duplicate"] * faults["duplicate"]
    )
    for e in errors:
        ErrorReport.model_validate({k: v for k, v in e.items() if k != "_key"})
    gaps = [e for e in estimates if e["diagnostics"]["gap"]]
    assert gaps and all(e["channel"] == "it/demo-faulty-sensor" for e in gaps)
    # converged to the truth (biased: 120 Hz, A = 2, offset 0.5)
    last = [e for e in estimates if e["channel"] == "it/demo-biased"][-1]
    assert abs(last["frequency_hz"][0] - 120.0) < 0.1 and abs(last["offset"] - 0.5) < 0.02

    # the MCAP file: finished (has a summary), inputs and estimates on their own channels
    [path] = daemon.recording_paths
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        roles = {}
        for ch in summary.channels.values():
            count = summary.statistics.channel_message_counts.get(ch.id, 0)
            roles.setdefault(ch.metadata["role"], 0)
            roles[ch.metadata["role"]] += count
        schemas = {s.name: s.encoding for s in summary.schemas.values()}
    assert roles["input"] == sent and roles["estimate"] == len(estimates) and roles["error"] == len(errors)
    assert schemas["sinewatch.Estimate"] == "jsonschema"
    assert schemas["sinewatch.InputBlock"] == "protobuf"  # with its FileDescriptorSet: any reader decodes it

    result = replay([path])
    assert result.ok and result.matched == len(estimates) and result.inputs == sent


def _good_blocks(n, block=500, fs=10_000.0):
    sc = make_channels(["demo-biased"], prefix="h")[0]
    return [Block("h/a", i, 1_000_000_000 + i * 50_000_000, fs, sc.stream.read(block)[0]) for i in range(n)]


def test_hostile_inputs_are_reported_and_never_reach_the_estimator(tmp_path):
    limits = LimitsSection(max_block_samples=2000)
    config = make_config(tmp_path, limits=limits)
    good = _good_blocks(12)
    b = encode_block_binary
    bad_version_bin = bytearray(b(good[4]))
    bad_version_bin[4] = 9
    nan_block = Block("h/a", 5, 0, 10_000.0, np.array([0.1, np.nan, 0.2]))
    json_enc = "application/json;sinewatch/SampleBlock@1"
    hostile = [  # (key suffix, payload, expected kind); JSON ones go out with the JSON encoding
        ("h/a", b"\x00\x01garbage", "decode_error"),
        ("h/a", json.dumps({"format_version": 2, "channel": "h/a"}).encode(), "unsupported_version"),
        ("h/a", bytes(bad_version_bin), "unsupported_version"),
        ("h/a", b(good[5])[:-7], "decode_error"),
        ("h/a", b(nan_block), "non_finite"),
        ("h/a", encode_block_json(Block("h/a", 5, 0, 10_000.0, np.array([0.1, float("inf")]))), "non_finite"),
        ("h/a", b(Block("h/a", 5, 0, 10_000.0, np.zeros(0))), "empty_block"),
        ("h/a", b(Block("h/a", 5, 0, 10_000.0, np.zeros(3000))), "oversized_block"),
        ("h/a", b(Block("h/a", 5, 0, 20_000.0, np.zeros(100))), "sample_rate_change"),
        ("h/a", b(good[4]), "duplicate"),
        ("h/a", b(good[2]), "out_of_order"),
        ("other", b(good[5]), "channel_key_mismatch"),
        ("h/a", b(Block("h/a", 5, 0, 10_000.0, np.zeros((10, 3)))), "shape_mismatch"),
    ]
    accepted = good[:5] + good[5:10] + [good[11]]  # seq 10 never sent: a gap before 11

    def client(_daemon, ep):
        with connect([ep]) as s:
            est, err = subscribe_estimates(s), subscribe_errors(s)
            pub = BlockPublisher(s)
            for key in ("h/a", "other"):
                assert pub.wait_for_subscriber(key, TIMEOUT)
            for blk in good[:5]:
                pub.publish_raw("h/a", b(blk))
            for key, payload, _ in hostile:
                pub.publish_raw(key, payload, json_enc if payload[:1] == b"{" else None)
            for blk in [*good[5:10], good[11]]:
                pub.publish_raw("h/a", b(blk))
            return take(est, len(accepted)), take(err, len(hostile))

    (estimates, errors), daemon, code = run_daemon(config, client)
    assert code == 0
    assert [e["kind"] for e in errors] == [kind for _, _, kind in hostile]
    assert all(e["message"] for e in errors)
    assert errors[0]["_key"] == "sinewatch/err/_unknown" and errors[4]["_key"] == "sinewatch/err/h/a"
    assert [e["seq"] for e in estimates] == [blk.seq for blk in accepted]
    assert estimates[-1]["diagnostics"]["gap"] and estimates[-1]["diagnostics"]["gap_blocks"] == 1
    assert not any(e["diagnostics"]["gap"] for e in estimates[:-1])

    # The estimator saw exactly the good blocks: a clean pipeline fed only those agrees bit for bit
    # (the last estimate, held back for the presence detector, came from the daemon's idle
    # release, not valid: the samples that would have confirmed its window never came)
    clean = clean_estimates(config, "sinewatch/in/h/a", accepted)
    assert [{k: v for k, v in e.items() if k != "_key"} for e in estimates] == clean
    assert not estimates[-1]["diagnostics"]["valid"]
    assert daemon.pipeline.counters.errors == len(hostile)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_intake_drains_and_finishes_the_recording(tmp_path, sig):
    config = make_config(tmp_path)
    blocks = _good_blocks(40)
    done = threading.Event()

    def client(_daemon, ep):
        with publishing(ep, "h/a", subscribe_estimates) as (pub, [est]):
            for blk in blocks[:20]:
                pub.publish_raw("h/a", encode_block_binary(blk))
            got = take(est, 20)
            signal.raise_signal(sig)  # handled by the daemon's event loop
            done.set()
            return got

    got, daemon, code = run_daemon(config, client, signals=True)  # the signal, not the runner, stops it
    assert done.is_set() and code == 0 and len(got) == 20
    assert daemon.should_exit.is_set() and not daemon.force_exit.is_set()
    [path] = daemon.recording_paths
    with open(path, "rb") as f:
        assert make_reader(f).get_summary() is not None  # finished: summary and footer written
    assert replay([path]).ok


def test_second_sigint_forces_exit_and_still_finishes_the_file(tmp_path):
    config = make_config(tmp_path)

    async def main():
        daemon = Daemon(config, install_signal_handlers=True)
        task = asyncio.create_task(daemon.run())
        await daemon.ready.wait()
        signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGINT)
        return daemon, await asyncio.wait_for(task, TIMEOUT)

    daemon, code = asyncio.run(main())
    assert code == 130 and daemon.force_exit.is_set()
    [path] = daemon.recording_paths
    with open(path, "rb") as f:
        assert make_reader(f).get_summary() is not None
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handlers removed


def test_binary_header_layout_is_as_documented():
    blk = Block("a/b", 7, -5, 1000.0, np.array([1.0, -2.0], dtype=np.float32), "V")
    raw = encode_block_binary(blk, "float32")
    assert raw[:40] == struct.pack("<4sBBBBQqdIHH", b"SWSB", 1, 1, 1, 0, 7, -5, 1000.0, 2, 3, 1)
    assert raw[40:44] == b"a/bV"
    np.testing.assert_array_equal(np.frombuffer(raw, "<f4", offset=44), [1.0, -2.0])


def test_status_reports_counters_and_validates(tmp_path):
    config = make_config(tmp_path)
    blocks = _good_blocks(10)

    def client(_daemon, ep):
        from sinewatch.clients import subscribe_status

        with publishing(ep, "h/a", subscribe_estimates, subscribe_status) as (pub, [est, status]):
            for blk in blocks:
                pub.publish_raw("h/a", encode_block_binary(blk))
            pub.publish_raw("h/a", b"junk")
            assert len(take(est, 10)) == 10
            while (msg := status.get(timeout=TIMEOUT)) is not None:  # the next status after the inputs
                if msg["blocks_processed"] == 11:
                    return msg
            return None

    (msg, _daemon, _code) = run_daemon(config, client)
    from sinewatch.schemas.messages import Status

    st = Status.model_validate({k: v for k, v in msg.items() if k != "_key"})
    assert st.errors == 1 and st.dropped == 0 and st.recording.endswith(".mcap")
    [ch] = st.channels
    assert (ch.channel, ch.blocks, ch.samples, ch.last_seq, ch.estimator) == ("h/a", 10, 5000, 9, "ges-kalman")
    assert ch.last_latency_us is not None and ch.last_latency_us > 0


def test_drop_policy_counts_every_dropped_input(tmp_path):
    # A tiny queue with the drop policy: whatever is dropped is reported, nothing vanishes.
    config = make_config(tmp_path, limits=LimitsSection(queue_capacity=1, queue_policy="drop", intake_batch=1))
    blocks = [Block("d/a", i, 0, 10_000.0, np.sin(np.arange(2000) * 0.03)) for i in range(300)]

    def client(_daemon, ep):
        from sinewatch.clients import JsonSubscription

        with connect([ep]) as s, JsonSubscription(s, "sinewatch/**") as everything:
            pub = BlockPublisher(s)
            assert pub.wait_for_subscriber("d/a", TIMEOUT)
            for blk in blocks:
                pub.publish_raw("d/a", encode_block_binary(blk))
            out_est, out_err = [], []

            def accounted():  # estimates, plus the dropped inputs the reports count so far
                return len(out_est) + (out_err[-1]["count"] if out_err else 0)

            while accounted() < len(blocks) and (m := everything.get(timeout=TIMEOUT)):
                if m["_key"].startswith("sinewatch/est/"):
                    out_est.append(m)
                elif m["_key"].startswith("sinewatch/err/"):
                    out_err.append(m)
            return out_est, out_err

    (estimates, errors), daemon, _code = run_daemon(config, client)
    dropped = daemon.intake.counters.dropped
    assert len(estimates) + dropped == len(blocks)
    # drops are reported per intake batch: each report's running count says how many so far
    assert {e["kind"] for e in errors} == {"queue_overflow"} and errors[-1]["count"] == dropped
    counts = [e["count"] for e in errors]
    assert counts == sorted(counts) and len(set(counts)) == len(counts)
    assert sum(e["diagnostics"]["gap_blocks"] for e in estimates) == dropped - _tail_drops(estimates, len(blocks))


def _tail_drops(estimates, n):
    """Dropped blocks after the last estimate are not gaps (nothing came after them)."""
    return n - 1 - max(e["seq"] for e in estimates)
