"""``report_in_block`` (validity rules version 6): each block's estimate at the sample its presence
detector has read its onset latency L past, confirmed by the block itself and published with it.

What is checked: the estimate's time and values are the single track's row n - 1 - L (L the
detector's latency after the block); it leaves with its own block, not the next; the hold's
guarantee is unchanged (no estimate whose window holds the start of an interruption is published
valid, wherever in a block the interruption starts, the last L samples included); a frame's banks
give each channel what its own path gives, bytes and order, with channels at different L in one
bank; a recording made so replays bit for bit under its own rules version.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import make_config
from mcap.reader import make_reader
from test_pipeline_hot_path import Batches as Keep  # every estimate (key, payload) in order, errors (key, kind)

from sinewatch.core.continuity import REPORT_IN_BLOCK_RULES_VERSION, VALIDITY_RULES_VERSION
from sinewatch.core.pipeline import Pipeline
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.runtime.replay import replay
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, encode_block_binary
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.frame import FRAME_BINARY_ENCODING, Frame, encode_frame_binary

FS, N, F0 = 10_000.0, 1024, 50.0
STEP_NS = round(N * 1e9 / FS)
SOGI = [EstimatorRule(match="sinewatch/in/**", estimator="sogi-fll", params={"nominal_frequency_hz": 50.0})]


def _sine(n_blocks: int, seed: int, phase: float = 0.0) -> np.ndarray:
    t = np.arange(n_blocks * N) / FS
    rng = np.random.default_rng(seed)
    return np.sin(2 * np.pi * F0 * t + phase) + 0.01 * rng.standard_normal(t.size)


def _pipeline(tmp_path, sinks, **overrides) -> Pipeline:
    return Pipeline(make_config(tmp_path, rules=SOGI, report_in_block=True, **overrides), sinks)


def test_the_estimate_is_row_n_minus_l_of_the_track_and_leaves_with_its_own_block(tmp_path):
    from sinewatch.estimators import get

    x = _sine(12, seed=1)
    keep = Keep()
    pipe = _pipeline(tmp_path, [keep])
    assert pipe.validity_version == REPORT_IN_BLOCK_RULES_VERSION
    alone = get("sogi-fll")(FS, {"nominal_frequency_hz": 50.0})  # the single track, every row
    lags = []
    for seq in range(12):
        block = x[seq * N : (seq + 1) * N]
        payload = encode_block_binary(Block("s/a", seq, seq * STEP_NS, FS, block))
        pipe.process("sinewatch/in/s/a", payload, BLOCK_BINARY_ENCODING, seq + 1)
        assert len(keep.estimates) == seq + 1, "each block's estimate leaves with its own block"
        latency = pipe.channels["s/a"].presence.onset_latency_samples
        row = N - 1 - latency
        est = json.loads(keep.estimates[-1][1])
        assert est["seq"] == seq and est["n_samples"] == N
        assert est["timestamp_ns"] == seq * STEP_NS + round(row * 1e9 / FS)
        track = alone.update(block)
        assert est["frequency_hz"] == [float(track.frequency_hz[row, 0])]  # bit for bit (repr round-trips)
        assert est["amplitude"] == [float(track.amplitude[row, 0])]
        lags.append(latency)
    assert lags[-1] == 61  # the quadrature test armed: Q + m - 1 at 50 Hz, 10 kHz
    assert not pipe.channels["s/a"].held
    assert json.loads(keep.estimates[-1][1])["diagnostics"]["valid"] is True


@pytest.mark.parametrize("offset", [-200, -62, -61, -60, -30, -1])
def test_no_estimate_whose_window_holds_an_interruption_is_published_valid(tmp_path, offset):
    """An interruption starting ``offset`` samples before a block's end (inside the window of
    that block's estimate, at its row, or in the last L samples after it): no estimate whose
    window (its valid memory up to its time) holds an interrupted sample is published valid,
    the first estimate after the onset is not valid, and each block's estimate still leaves
    with its block."""
    x = _sine(24, seed=2)
    onset, end = 10 * N + offset, 10 * N + offset + 3000
    x[onset:end] = 0.0
    keep = Keep()
    pipe = _pipeline(tmp_path, [keep])
    for seq in range(24):
        payload = encode_block_binary(Block("s/a", seq, seq * STEP_NS, FS, x[seq * N : (seq + 1) * N]))
        pipe.process("sinewatch/in/s/a", payload, BLOCK_BINARY_ENCODING, seq + 1)
        assert len(keep.estimates) == seq + 1
    memory = pipe.channels["s/a"].valid_memory_samples
    ests = [json.loads(p) for _, p in keep.estimates]
    rows = [(round(e["timestamp_ns"] * FS / 1e9), e["diagnostics"]["valid"]) for e in ests]  # (sample, valid)
    assert not [r for r, valid in rows if valid and r >= onset and r - memory < end]
    assert any(valid for r, valid in rows if r < onset) and any(valid for r, valid in rows if r - memory >= end)
    assert not next(valid for r, valid in rows if r >= onset)


def test_the_same_check_fails_without_the_hold(tmp_path):
    """The check above is not vacuous: estimates published at once at their block's end (the
    hold off) publish one valid whose window holds an onset 30 samples before the end."""
    x = _sine(16, seed=2)
    onset = 10 * N - 30
    x[onset : onset + 3000] = 0.0
    keep = Keep()
    pipe = _pipeline(tmp_path, [keep], hold_estimates=False)
    for seq in range(16):
        payload = encode_block_binary(Block("s/a", seq, seq * STEP_NS, FS, x[seq * N : (seq + 1) * N]))
        pipe.process("sinewatch/in/s/a", payload, BLOCK_BINARY_ENCODING, seq + 1)
    rows = [
        (round(json.loads(p)["timestamp_ns"] * FS / 1e9), json.loads(p)["diagnostics"]["valid"])
        for _, p in keep.estimates
    ]
    assert [r for r, valid in rows if valid and onset <= r < onset + 3000]


class ChannelByChannel(Pipeline):
    """The frame path without the usual frame's banks: each channel on its own path."""

    def _usual_frame(self, *args, **kwargs):
        return None


def _frames(n_frames: int) -> list[bytes]:
    """Six channels; c5 silent for the first ten frames (its detector's latency the level test's
    while the others' is the quadrature test's: two rows in one bank), a NaN in c1 at frame 9,
    frame 17 lost, c3 away for frames 25-27."""
    names = [f"daq/c{c}" for c in range(6)]
    signals = np.stack([_sine(n_frames, seed=10 + c, phase=c) for c in range(6)], axis=1)
    signals[: 10 * N, 5] = 0.0
    frames = []
    for seq in range(n_frames):
        if seq == 17:
            continue
        cols = list(range(6)) if not 25 <= seq < 28 else [0, 1, 2, 4, 5]
        x = signals[seq * N : (seq + 1) * N, cols].copy()
        if seq == 9:
            x[100, 1] = np.nan
        frames.append(encode_frame_binary(Frame(tuple(names[c] for c in cols), seq, seq * STEP_NS, FS, x), "float64"))
    return frames


def test_a_frames_banks_give_each_channel_what_its_own_path_gives(tmp_path):
    frames = _frames(36)
    got = {}
    for cls in (Pipeline, ChannelByChannel):
        keep = Keep()
        pipe = cls(make_config(tmp_path, rules=SOGI, report_in_block=True), [keep])
        for i, payload in enumerate(frames):
            pipe.process("sinewatch/in/daq", payload, FRAME_BINARY_ENCODING, i + 1)
        pipe.release_held(10**12)
        got[cls.__name__] = (keep, pipe.channel_status())
    (banks, banks_status), (alone, alone_status) = got["Pipeline"], got["ChannelByChannel"]
    assert banks.estimates == alone.estimates and banks_status == alone_status
    assert banks.errors == alone.errors == [("sinewatch/err/daq/c1", "non_finite")]
    assert len(banks.estimates) == 35 * 6 - 3 - 1
    # two rows in one frame's bank were exercised: c5's time differs from c0's in early frames
    times = {(k, json.loads(p)["seq"]): json.loads(p)["timestamp_ns"] for k, p in banks.estimates}
    assert any(times[("sinewatch/est/daq/c5", s)] != times[("sinewatch/est/daq/c0", s)] for s in range(2, 9))
    assert all(times[("sinewatch/est/daq/c5", s)] == times[("sinewatch/est/daq/c0", s)] for s in range(30, 36))


def test_a_recording_made_reporting_in_block_replays_bit_for_bit(tmp_path):
    config = make_config(tmp_path, rules=SOGI, report_in_block=True)
    recorder = McapRecorder(config)
    pipe = Pipeline(config, [recorder])
    for i, payload in enumerate(_frames(20)):
        pipe.process("sinewatch/in/daq", payload, FRAME_BINARY_ENCODING, 1_000 + i)
    x = _sine(20, seed=4)
    for seq in range(20):
        blk = Block("s/alone", seq, seq * STEP_NS, FS, x[seq * N : (seq + 1) * N])
        pipe.process("sinewatch/in/s/alone", encode_block_binary(blk), BLOCK_BINARY_ENCODING, 2_000 + seq)
    pipe.release_held(3_000)
    recorder.close()
    [path] = recorder.paths
    with open(path, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert meta["sinewatch"]["validity_rules_version"] == str(REPORT_IN_BLOCK_RULES_VERSION)
    result = replay([path])
    assert result.ok and result.matched == result.recorded_estimates == pipe.counters.estimates > 0


def test_without_it_the_default_rules_and_bytes_are_the_last_versions(tmp_path):
    """Off (the default): version 5's rules, recorded as such, estimates at the block's end."""
    keep = Keep()
    pipe = Pipeline(make_config(tmp_path, rules=SOGI), [keep])
    assert pipe.validity_version == VALIDITY_RULES_VERSION == 5
    x = _sine(3, seed=1)
    for seq in range(3):
        payload = encode_block_binary(Block("s/a", seq, seq * STEP_NS, FS, x[seq * N : (seq + 1) * N]))
        pipe.process("sinewatch/in/s/a", payload, BLOCK_BINARY_ENCODING, seq + 1)
    assert len(keep.estimates) == 2  # held to the next block
    assert json.loads(keep.estimates[0][1])["timestamp_ns"] == round((N - 1) * 1e9 / FS)


def test_frames_of_one_channel_report_in_block_too(tmp_path):
    """A frame key whose layout is one channel (a bank of one, whose detector runs alone): its
    usual frames report at row n - 1 - L and release with their frame, as single blocks do."""
    keep = Keep()
    pipe = _pipeline(tmp_path, [keep])
    x = _sine(8, seed=9)
    for seq in range(8):
        frame = Frame(("one/a",), seq, seq * STEP_NS, FS, x[seq * N : (seq + 1) * N, None].copy())
        pipe.process("sinewatch/in/one", encode_frame_binary(frame, "float64"), FRAME_BINARY_ENCODING, seq + 1)
        assert len(keep.estimates) == seq + 1
        latency = pipe.channels["one/a"].presence.onset_latency_samples
        assert json.loads(keep.estimates[-1][1])["timestamp_ns"] == seq * STEP_NS + round((N - 1 - latency) * 1e9 / FS)


def test_a_rerun_with_other_rules_says_the_rules_it_ran_by(tmp_path):
    """A re-run of a recording made reporting in block, with another estimator, runs under its
    config's rules (version 6) and its file says so: that file replays bit for bit."""
    from sinewatch.apps.cli import main

    config = make_config(tmp_path, rules=SOGI, report_in_block=True)
    recorder = McapRecorder(config)
    pipe = Pipeline(config, [recorder])
    for i, payload in enumerate(_frames(12)):
        pipe.process("sinewatch/in/daq", payload, FRAME_BINARY_ENCODING, 1_000 + i)
    recorder.close()
    out = tmp_path / "rerun.mcap"
    kkl = ["--estimator", "kkl"]
    assert main(["replay", str(recorder.paths[0]), "--no-progress", *kkl, "--out", str(out)]) == 0
    with open(out, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert meta["sinewatch"]["validity_rules_version"] == str(REPORT_IN_BLOCK_RULES_VERSION)
    again = replay([out])
    assert again.ok and again.matched == again.recorded_estimates > 0
