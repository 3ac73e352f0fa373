"""``sinewatch compare`` of two recordings, and ``replay --track``: every sample's estimate."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader
from test_replay_window import T0, messages, record

from sinewatch.apps.cli import main
from sinewatch.apps.compare import compare
from sinewatch.core.window import ChannelFilter, Window
from sinewatch.estimators import get
from sinewatch.runtime.replay import replay
from sinewatch.scenarios.demo import KALMAN_10K
from sinewatch.schemas.codec import decode_block
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.input_record import decode_input_record

OTHER = EstimatorRule(match="sinewatch/in/**", estimator="ges-kalman", params={**KALMAN_10K, "r": 1e-2})


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return record(tmp_path_factory.mktemp("compare"), n_blocks=50)


@pytest.fixture(scope="module")
def rerun(recording, tmp_path_factory):
    out = tmp_path_factory.mktemp("rerun") / "other.mcap"
    replay([recording], rules=[OTHER], out=out)
    return out


def test_a_recording_compared_with_itself_is_zero_everywhere(recording, capsys):
    c = compare(recording, recording)
    assert [ch.channel for ch in c.channels] == ["win/demo-biased", "win/demo-faulty-sensor", "win/demo-ramp"]
    for ch in c.channels:
        assert ch.identical and ch.paired == ch.a.estimates == ch.b.estimates > 0
        assert ch.a.valid == ch.b.valid and ch.a.converged == ch.b.converged
        assert {p.parameter for p in ch.parameters} >= {"frequency_hz[0]", "amplitude[0]", "phase_rad[0]", "offset"}
        for p in ch.parameters:
            assert p.rms == 0.0 and p.worst == 0.0 and p.first_divergence is None and p.one_defined == 0
    assert main(["compare", str(recording), str(recording), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert all(ch["identical"] for ch in out["channels"])


def estimates_by_time(path):
    out = {}
    for _, _, payload in messages(path):
        m = json.loads(payload)
        out[(m["channel"], m["timestamp_ns"])] = m
    return out


def test_a_rerun_with_other_parameters_reports_the_differences_computed_here(recording, rerun, capsys):
    a, b = estimates_by_time(recording), estimates_by_time(rerun)
    assert a.keys() == b.keys()
    channel = "win/demo-ramp"
    pairs = [(a[k], b[k]) for k in sorted(a) if k[0] == channel]
    df = np.array(
        [
            y["frequency_hz"][0] - x["frequency_hz"][0]
            for x, y in pairs
            if x["frequency_hz"][0] is not None and y["frequency_hz"][0] is not None
        ]
    )
    dphi = np.array(
        [
            math.remainder(y["phase_rad"][0] - x["phase_rad"][0], 2 * math.pi)
            for x, y in pairs
            if x["phase_rad"][0] is not None and y["phase_rad"][0] is not None
        ]
    )
    first = next(x["seq"] for x, y in pairs if abs(y["amplitude"][0] - x["amplitude"][0]) > 0.001)
    c = compare(recording, rerun, tolerances={"amplitude": 0.001})
    [ch] = [ch for ch in c.channels if ch.channel == channel]
    got = {p.parameter: p for p in ch.parameters}
    assert got["frequency_hz[0]"].compared == len(df) > 40
    assert (
        got["frequency_hz[0]"].rms == pytest.approx(np.sqrt(np.mean(df**2)), rel=1e-12)
        and got["frequency_hz[0]"].rms > 0
    )
    assert got["frequency_hz[0]"].worst == pytest.approx(np.max(np.abs(df)), rel=1e-12)
    assert got["phase_rad[0]"].rms == pytest.approx(np.sqrt(np.mean(dphi**2)), rel=1e-12)
    assert got["amplitude[0]"].first_divergence.seq == first
    assert ch.a.converged == sum(x["diagnostics"]["converged"] for x, _ in pairs)
    assert ch.b.valid == sum(y["diagnostics"]["valid"] for _, y in pairs)
    assert not ch.identical
    # the text report names the channel, the parameter and the numbers
    assert main(["compare", str(recording), str(rerun), "--channels", "*ramp", "--tolerance", "amplitude=0.001"]) == 0
    text = capsys.readouterr().out
    assert "win/demo-ramp" in text and "win/demo-biased" not in text
    assert f"{np.sqrt(np.mean(df**2)):.3g}" in text


def test_compare_of_a_window_counts_only_its_estimates(recording, rerun):
    c = compare(recording, rerun, window=Window.parse("+1s", "+1.4s"), channels=ChannelFilter.of("*biased"))
    [ch] = c.channels
    assert ch.paired == ch.a.estimates == 10 and c.window == "from +1.000 s to +1.400 s"


def test_track_rows_are_the_estimators_own_track(recording, tmp_path, capsys):
    out = tmp_path / "track.parquet"
    window = ["--start", "+1.2s", "--end", "+1.4s", "--channels", "*faulty*"]
    assert main(["replay", str(recording), "--no-progress", *window, "--track", str(out)]) == 0
    text = capsys.readouterr().out
    assert "OK" in text and "track: 1600 rows" in text  # blocks 30-34 of 400 samples, 30 rejected (NaN)
    table = pq.read_table(out).to_pandas()
    # the estimator run directly over the recorded blocks of the channel, as the pipeline
    # accepts them (in order; the duplicate and the NaN block rejected)
    est = get("ges-kalman")(10_000.0, KALMAN_10K)
    rows = {}
    last_seq = -1
    with open(recording, "rb") as f:
        for _, c, m in make_reader(f).iter_messages(log_time_order=False):
            if c.metadata["role"] != "input" or "faulty" not in c.topic:
                continue
            blk = decode_block(*decode_input_record(m.data))  # an InputBlock: the bytes as received
            if blk.seq <= last_seq or not np.isfinite(blk.samples).all():
                continue
            last_seq = blk.seq
            rows[blk.seq] = (est.update(blk.samples), blk, m.log_time)
    origin = T0 + 40_000_000
    in_window = [s for s, (_, _, t) in rows.items() if origin + 1_200_000_000 <= t < origin + 1_400_000_000]
    assert in_window == [31, 32, 33, 34]
    assert list(dict.fromkeys(table["seq"])) == in_window
    for seq in in_window:
        track, blk, _ = rows[seq]
        part = table[table["seq"] == seq]
        np.testing.assert_array_equal(part["frequency_hz_0"], track.frequency_hz[:, 0])
        np.testing.assert_array_equal(part["amplitude_0"], track.amplitude[:, 0])
        np.testing.assert_array_equal(part["phase_rad_0"], track.phase_rad[:, 0])
        np.testing.assert_array_equal(part["offset"], track.offset)
        np.testing.assert_array_equal(part["converged"], track.converged)
        np.testing.assert_array_equal(part["std_frequency_hz_0"], track.std.frequency_hz[:, 0])
        np.testing.assert_array_equal(part["input_0"], blk.samples)
        assert list(part["timestamp_ns"]) == [blk.t0_ns + round(i * 1e5) for i in range(400)]


def test_track_goes_into_the_output_recording_for_foxglove(recording, tmp_path):
    out = tmp_path / "win.mcap"
    r = replay(
        [recording], window=Window.parse("+0.4s", "+0.48s"), channels=ChannelFilter.of("*ramp"), out=out, track=True
    )
    assert r.ok and r.track_rows == 800
    with open(out, "rb") as f:
        reader = make_reader(f)
        rows = [
            (s, c, json.loads(m.data))
            for s, c, m in reader.iter_messages(log_time_order=False)
            if c.metadata["role"] == "track"
        ]
    assert len(rows) == 800 and rows[0][1].topic == "sinewatch/track/win/demo-ramp"
    schema, _, first = rows[0]
    assert schema.encoding == "jsonschema" and json.loads(schema.data)["title"] == "TrackRow"
    last = rows[399][2]
    estimate = json.loads(next(p for t, topic, p in messages(out) if json.loads(p)["seq"] == last["seq"]))
    assert last["frequency_hz"] == estimate["frequency_hz"] and last["offset"] == estimate["offset"]
    assert first["timestamp"] == {"sec": first["timestamp_ns"] // 10**9, "nsec": first["timestamp_ns"] % 10**9}
    assert replay([out]).ok  # track rows are not outputs a replay compares


def test_relative_windows_are_the_first_recordings_for_both(recording, tmp_path):
    # a re-run of a window starts 1 s later: "+1s" still means 1 s after A's start in B
    later = tmp_path / "later.mcap"
    assert replay([recording], window=Window.parse("+1s", None), out=later).ok
    c = compare(recording, later, window=Window.parse("+1s", "+1.4s"))
    assert [(ch.paired, ch.a.estimates, ch.b.estimates) for ch in c.channels] == [(10, 10, 10), (9, 9, 9), (10, 10, 10)]
    assert all(ch.identical for ch in c.channels)


def test_a_window_of_a_frame_recording_replays_and_tracks_its_channels(tmp_path):
    """Multi-channel frames (recorded whole): a window replays bit for bit, and ``--track``
    gives each selected channel's rows, as its estimator computes them."""
    from conftest import make_config

    from sinewatch.core.pipeline import Pipeline
    from sinewatch.outputs.recorder import McapRecorder
    from sinewatch.schemas.config import RecordingSection
    from sinewatch.schemas.frame import FRAME_BINARY_ENCODING, Frame, encode_frame_binary

    config = make_config(tmp_path, recording=RecordingSection(directory=tmp_path / "rec", snapshot_interval_s=0.5))
    recorder = McapRecorder(config, snapshot=lambda: pipeline.snapshot())
    pipeline = Pipeline(config, [recorder])
    names = ("daq/a", "daq/b")
    rng = np.random.default_rng(3)
    frames = []
    for seq in range(50):  # 400 samples at 10 kHz: 40 ms each, 2 s
        t = (seq * 400 + np.arange(400)) / 1e4
        x = np.stack([np.sin(2 * np.pi * 50 * t), 0.5 * np.sin(2 * np.pi * 60 * t)], axis=1)
        x = x + 0.01 * rng.standard_normal(x.shape)
        frames.append(x)
        payload = encode_frame_binary(Frame(names, seq, seq * 40_000_000, 1e4, x))
        pipeline.process("sinewatch/in/daq", payload, FRAME_BINARY_ENCODING, T0 + (seq + 1) * 40_000_000)
    recorder.close()
    [path] = recorder.paths
    out = tmp_path / "track.parquet"
    r = replay([path], window=Window.parse("+1.2s", "+1.6s"), channels=ChannelFilter.of("*/b"), track=out)
    # the frames run whole; the estimates of daq/b alone are compared
    assert r.ok and r.started_from == "snapshot at +1.040 s" and r.matched == r.produced_estimates == 10
    table = pq.read_table(out).to_pandas()
    assert set(table["channel"]) == {"daq/b"} and sorted(set(table["seq"])) == list(range(30, 40))
    est = get("ges-kalman")(1e4, KALMAN_10K)
    tracks = [est.update(np.ascontiguousarray(x[:, 1])) for x in frames]
    for seq in range(30, 40):
        part = table[table["seq"] == seq]
        np.testing.assert_array_equal(part["frequency_hz_0"], tracks[seq].frequency_hz[:, 0])
        np.testing.assert_array_equal(part["input_0"], frames[seq][:, 1])
