"""The per-block shortcuts of the pipeline change no result: the presence detector on float32
samples, the sink dispatch (methods looked up once, NullSink's no-ops skipped) with its
failure, skip and recovery accounting, and the bench that measures them runs."""

from __future__ import annotations

import argparse
import itertools
import json

import numpy as np
import pytest
from conftest import make_config

from sinewatch.core.pipeline import GuardedSink, NullSink, Pipeline
from sinewatch.estimators.presence import SignalPresence
from sinewatch.schemas.codec import Block, encode_block_binary


def test_presence_on_float32_samples_is_presence_on_them_as_float64():
    fs = 10_000.0
    rng = np.random.default_rng(7)
    t = np.arange(40_000) / fs
    x = (np.sin(2 * np.pi * 50 * t) + 0.05 * rng.standard_normal(t.size)).astype(np.float32)
    x[12_000:15_000] *= np.float32(0.01)  # an interruption: run lengths fall to 0 and come back
    a, b = SignalPresence(fs), SignalPresence(fs)
    runs = []
    for lo in range(0, x.size, 1024):
        run32, level32 = a.update(x[lo : lo + 1024])
        run64, level64 = b.update(x[lo : lo + 1024].astype(np.float64))
        assert np.array_equal(run32, run64) and np.array_equal(level32, level64)
        assert np.array_equal(a.sums, b.sums) and np.array_equal(a.counters, b.counters)
        runs.append(run32)
    run = np.concatenate(runs)
    assert run[11_999] > 10_000 and run[13_000] == 0 and run[-1] > 20_000  # present, lost, back
    strided = SignalPresence(fs)  # a non-contiguous view is converted, with the same result
    c = SignalPresence(fs)
    y = np.stack([x, -x], axis=1)[:, 0]
    assert np.array_equal(strided.update(y)[0], c.update(x.astype(np.float64))[0])


class FailingEstimates(NullSink):
    """Fails ``on_estimate`` with ``error`` while ``broken``; counts the estimates it got and
    its ``recover()`` calls; with ``heals``, ``recover()`` ends the failure (a publisher whose
    session is back). Leaves ``on_input`` as NullSink's, as the Zenoh publisher does."""

    def __init__(self, error: Exception, *, broken: bool = False, heals: bool = False):
        self.error, self.broken, self.heals = error, broken, heals
        self.estimates, self.recovered = 0, 0

    def on_estimate(self, key, payload, log_time_ns):
        if self.broken:
            raise self.error
        self.estimates += 1

    def recover(self):
        self.recovered += 1
        self.broken = self.broken and not self.heals


class FlakySink(FailingEstimates):
    """A recorder whose disk fills while ``broken``; also counts its inputs."""

    def __init__(self):
        super().__init__(OSError("disk full"))
        self.inputs = 0

    def on_input(self, key, payload, encoding, log_time_ns):
        self.inputs += 1


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_guarded_sink_skips_counts_and_recovers_at_an_input_after_the_retry_time():
    sink, clock, reports = FlakySink(), Clock(), []
    g = GuardedSink(sink, "flaky", lambda name, msg: reports.append(msg), retry_s=1.0, clock=clock)
    g.on_input("k", b"", "", 1)
    g.on_estimate("k", b"{}", 1)
    sink.broken = True
    g.on_estimate("k", b"{}", 2)  # fails: reported once
    g.on_estimate("k", b"{}", 3)  # skipped
    g.on_output("HarmonicsReport", "k", b"{}", 3)  # skipped, though NullSink's does nothing
    g.on_input("k", b"", "", 4)  # before the retry time: skipped
    assert (g.ok, g.failures, g.skipped, sink.inputs, sink.estimates) == (False, 1, 3, 1, 1)
    assert reports == ["flaky failed in on_estimate: OSError: disk full"]
    sink.broken = False
    clock.t = 1.5
    g.on_input("k", b"", "", 5)  # after it: recover(), then the input goes through
    g.on_estimate("k", b"{}", 5)
    assert (g.ok, g.recoveries, sink.recovered, sink.inputs, sink.estimates) == (True, 1, 1, 2, 2)


def test_a_sink_without_on_input_still_recovers_at_the_next_input():
    """A sink that leaves on_input as NullSink's (the Zenoh publisher) is not called for
    inputs while ok, but an input is still where it comes back after a failure."""

    sink, clock = FailingEstimates(ConnectionError("session closed"), broken=True, heals=True), Clock()
    g = GuardedSink(sink, "zenoh", lambda name, msg: None, retry_s=0.5, clock=clock)
    g.on_input("k", b"", "", 1)
    g.on_estimate("k", b"{}", 1)
    assert not g.ok
    clock.t = 1.0
    g.on_input("k", b"", "", 2)
    g.on_estimate("k", b"{}", 2)
    assert g.ok and sink.recovered == 1 and sink.estimates == 1


def test_a_failing_sink_does_not_stop_the_pipeline(tmp_path):
    sink = FlakySink()
    sink.broken = True
    pipeline = Pipeline(make_config(tmp_path, hold_estimates=False, sink_retry_s=3600.0), [sink])
    fs, n = 10_000.0, 256
    x = np.sin(2 * np.pi * 50 * np.arange(n * 5) / fs)
    for i in range(5):
        pipeline.process(
            "sinewatch/in/a", encode_block_binary(Block("a", i, i * 25_600_000, fs, x[i * n : (i + 1) * n])), "", i
        )
    assert pipeline.counters.estimates == 5 and pipeline.channels["a"].blocks == 5
    (status,) = pipeline.sink_status()
    # skipped: 4 inputs and 4 estimates after the failure, and the ErrorReport of the failure itself
    assert status["failures"] == 1 and status["skipped"] == 4 + 4 + 1


def test_the_pipeline_bench_runs_and_reports_every_figure(tmp_path):
    from sinewatch.apps.bench.pipeline_cost import FRAME_STEPS, STEPS, run

    for per, steps in ((1, STEPS), (3, FRAME_STEPS)):  # blocks, and frames of 3 (the last frame of 2)
        out = tmp_path / f"bench-{per}.json"
        args = argparse.Namespace(
            channels=5, rate=10_000.0, block=256, estimator="ges-kalman", compression="zstd", rounds=2, repeats=2,
            frame_channels=per, json=out,
        )  # fmt: skip
        assert run(args) == 0
        result = json.loads(out.read_text())
        assert result["frame_channels"] == per
        for name in ("pipeline_on", "pipeline_off", *steps, "rest_on", "rest_off"):
            assert result["us_per_block"][name] == result["us_per_block"][name]  # a number, not NaN
            assert name in result["ratio_to_estimator"]
            assert result["ns_per_sample"][name] == pytest.approx(1e3 * result["us_per_block"][name] / 256)
        assert result["ratio_to_estimator"]["estimator"] == 1.0
        assert result["us_per_block"]["pipeline_on"] > result["us_per_block"]["estimator"] > 0
        assert set(result["outside_estimator_us"]) == {"recording_on", "recording_off"}
        assert ("channel_by_channel_off" in result["us_per_block"]) == (per > 1)  # the frame path's steps off


def _track(rng, k: int, *, std: bool, rocof: bool, bad: str | None = None, rms: float = 0.07):
    from sinewatch.estimators.base import Track, TrackStd

    def rows(shape):
        return rng.standard_normal(shape) * 10.0 ** rng.integers(-12, 12, size=shape)

    tr = Track(
        frequency_hz=50.0 + rows((3, k)),
        amplitude=rows((3, k)),
        phase_rad=rows((3, k)),
        offset=rows((3,)),
        converged=np.array([False, True, True]),
        residual_rms=rms,
        rocof_hz_per_s=rows((3, k)) if rocof else None,
        std=TrackStd(rows((3, k)), rows((3, k)), rows((3, k)), rows((3,))) if std else None,
    )
    if bad is not None:  # a non-finite value: the general path writes it as null
        getattr(tr, bad)[-1, ...] = np.nan
    return tr


def test_the_estimate_template_writes_the_bytes_of_the_general_encoder(tmp_path):
    """estimate_payload's first branch (one % formatting of a cached template) against its
    general way (encode_estimate_values, itself proven equal to the pydantic model's bytes) over
    component counts, std and rocof present or not, flags, fencing, time quality, every estimate
    format from 3 on, and values of every magnitude; a non-finite value takes the general way
    (no template is made for it)."""
    from sinewatch.core.estimate_bytes import estimate_payload
    from sinewatch.core.pipeline import Channel
    from sinewatch.estimators import get
    from sinewatch.schemas.messages import Fencing

    rng = np.random.default_rng(11)
    cases = 0
    flags = ((0, False, False, False), (2, True, True, True))
    for version in (3, 4, 5):
        pipe = Pipeline(make_config(tmp_path), [NullSink()], estimate_version=version)
        est = get("ges-kalman")(10_000.0, {})
        ch = Channel("site/a-1.x", "sinewatch/in/site/a-1.x", est, 10_000.0)
        assert ch.presence is not None
        ch.presence.update(np.sin(np.arange(40_000) * 0.0314))  # a long run: estimates valid
        blk = Block("site/a-1.x", 7, 10**18 + 123, 10_000.0, np.zeros(1024))
        t_ns = 10**18 + 5_000_123
        for fencing, k, std, rocof, tq, flag in itertools.product(
            (None, Fencing(shard="s%1", term=3)), (1, 3), (False, True), (False, True), (0, 0x80 | 0x04 | 1), flags
        ):
            pipe.set_fencing(fencing)
            blk.time_quality = tq
            tr = _track(rng, k, std=std, rocof=rocof)
            args = (ch, blk, tr, t_ns, t_ns, *flag)
            ch.template = None
            fast = estimate_payload(pipe, *args)
            assert ch.template is not None  # the template made these bytes
            assert fast == estimate_payload(pipe, *args, fast=False), (version, k, std, rocof)
            cases += 1
        for k, bad in itertools.product((1, 2), ("frequency_hz", "offset", "amplitude")):
            tr = _track(rng, k, std=True, rocof=k == 1, bad=bad)
            ch.template = None
            args = (ch, blk, tr, 10**18, 10**18, 0, False, False, False)
            assert estimate_payload(pipe, *args) == estimate_payload(pipe, *args, fast=False)
            assert ch.template is None  # the general way wrote them
        for name in ("amplitude", "offset"):  # one float32 array: not the one-component reading, same bytes
            tr = _track(rng, 1, std=True, rocof=True)
            setattr(tr, name, getattr(tr, name).astype(np.float32))
            args = (ch, blk, tr, t_ns, t_ns, 0, False, False, False)
            assert estimate_payload(pipe, *args) == estimate_payload(pipe, *args, fast=False)
    assert cases == 3 * 2 * 2 * 2 * 2 * 2 * 2


def _bank_tracks(rng, out, sse, *, std: bool, rocof: bool):
    """A bank's Tracks (``column_tracks``) from its outputs, with random rocof and std or none."""
    from sinewatch.estimators.bank import column_tracks

    n_ch = out.shape[0]
    rocof_out = rng.standard_normal((n_ch, 1, 1)) if rocof else None
    std_out = np.abs(rng.standard_normal((n_ch, 1, 4))) * 1e-6 if std else None
    return column_tracks(out, sse, 1024, rocof=rocof_out, std=std_out)


def test_a_banks_estimates_written_in_one_pass_are_the_general_encoders_bytes(tmp_path):
    """A bank's Tracks (``column_tracks``) carry the bank's last row of every output; the first
    Estimate of the frame writes every channel's floats in one compiled call and each channel
    takes its own: the same bytes as the general encoder, channel by channel, with std and rocof
    or not, values of every magnitude, a channel with a NaN (the general way writes it as null)
    and one whose residual RMS is not finite."""
    from sinewatch.core.estimate_bytes import estimate_payload
    from sinewatch.core.pipeline import Channel
    from sinewatch.estimators import get

    rng = np.random.default_rng(26)
    pipe = Pipeline(make_config(tmp_path), [NullSink()])
    est = get("ges-kalman")(10_000.0, {})
    ch = Channel("site/b", "sinewatch/in/site/b", est, 10_000.0)
    assert ch.presence is not None
    ch.presence.update(np.sin(np.arange(40_000) * 0.0314))
    blk = Block("site/b", 3, 10**18, 10_000.0, np.zeros(1024))
    n_ch = 9
    for std, rocof in itertools.product((False, True), (False, True)):
        out = rng.standard_normal((n_ch, 1, 5)) * 10.0 ** rng.integers(-12, 12, size=(n_ch, 1, 5))
        out[:, :, 4] = 1.0  # converged
        out[4, 0, 2] = np.nan  # channel 4: a NaN phase
        sse = np.abs(rng.standard_normal(n_ch))
        sse[6] = np.inf  # channel 6: no residual RMS
        tracks = _bank_tracks(rng, out, sse, std=std, rocof=rocof)
        for c, tr in enumerate(tracks):
            assert tr.bank_row is not None and tr.bank_row[1] == c
            args = (ch, blk, tr, 10**18, 10**18, 0, False, False, False)
            ch.template = None
            fast = estimate_payload(pipe, *args)
            assert fast == estimate_payload(pipe, *args, fast=False), (c, std, rocof)
            assert (ch.template is None) == (c == 4)  # the NaN went the general way
        assert tracks[0].bank_row is not None and tracks[0].bank_row[0].texts is not None  # one pass made them
        tracks[2].residual_rms = 0.125  # set after column_tracks (as ipdft's bank does): the track's value is written
        args = (ch, blk, tracks[2], 10**18, 10**18, 0, False, False, False)
        assert b'"residual_rms":0.125,' in estimate_payload(pipe, *args)[0]
        assert estimate_payload(pipe, *args) == estimate_payload(pipe, *args, fast=False)


def test_a_bank_of_presence_detectors_is_each_detector_on_its_column():
    """update_presence_bank (one compiled call for a frame's channels) against each detector
    run on its own column: the same runs and states, bit for bit, over interruptions, any
    subset and order of the columns, and blocks of any size; detectors of other parameters
    are left to the caller (None)."""
    from sinewatch.estimators.presence import update_presence_bank

    fs = 10_000.0
    rng = np.random.default_rng(5)
    t = np.arange(30_000) / fs
    x = np.stack([np.sin(2 * np.pi * (50 + c) * t + c) + 0.05 * rng.standard_normal(t.size) for c in range(6)], axis=1)
    x[8_000:11_000, 2] *= 0.01  # an interruption on one column
    x[20_000:, 4] = 0.0  # a signal lost for good on another
    columns = [5, 2, 0, 4]
    alone = [SignalPresence(fs, hysteresis=0.02) for _ in columns]
    bank = [SignalPresence(fs, hysteresis=0.02) for _ in columns]
    lo = 0
    for n in (1024, 333, 4096, 1, 2000, 7000, 15_546):
        block = np.ascontiguousarray(x[lo : lo + n])
        runs = update_presence_bank(bank, block, columns)
        assert runs is not None and runs.shape == (len(columns), n)
        for i, (det, c) in enumerate(zip(alone, columns, strict=True)):
            run, _level = det.update(np.ascontiguousarray(block[:, c]))
            assert np.array_equal(runs[i], run)
            assert np.array_equal(bank[i].sums, det.sums) and np.array_equal(bank[i].counters, det.counters)
        lo += n
    assert lo == t.size and bank[1].run_samples > 0 and bank[3].run_samples == 0
    other = [SignalPresence(fs), SignalPresence(fs, nominal_frequency_hz=60.0)]
    assert update_presence_bank(other, x[:1024], [0, 1]) is None


def test_a_banks_estimates_in_one_compiled_call_are_each_channels_general_bytes(tmp_path):
    """bank_payloads writes a bank's Estimates in one compiled call: each channel's bytes are
    estimate_payload's general way (the pydantic model's bytes), over formats 3-5, fencing (a
    '%' in it), std and rocof, names with a quote and a '%d', time quality, gap/restart/reset/
    jump flags, converged or not, valid or not, values of every magnitude and sign, 0.0 and
    -0.0, a NaN value (that channel the general way), a NaN and an infinite residual RMS."""
    from sinewatch.core.estimate_bytes import bank_payloads, estimate_payload
    from sinewatch.core.pipeline import Channel
    from sinewatch.estimators import get
    from sinewatch.schemas.messages import Fencing

    rng = np.random.default_rng(2611)
    n_ch, t_last = 9, 10**18 + 102_300_000
    cases = 0
    for version, fencing, std, rocof in itertools.product(
        (3, 4, 5), (None, Fencing(shard="s%1", term=3)), (False, True), (False, True)
    ):
        pipe = Pipeline(make_config(tmp_path), [NullSink()], estimate_version=version)
        pipe.set_fencing(fencing)
        chs = []
        for c in range(n_ch):
            ch = Channel(f'site/"q{c}%d', f"sinewatch/in/site/q{c}", get("ges-kalman")(10_000.0, {}), 10_000.0)
            assert ch.presence is not None
            if c % 3:  # the others' signal was never present: not valid
                ch.presence.update(np.sin(np.arange(40_000) * 0.0314))
            chs.append(ch)
        out = rng.standard_normal((n_ch, 1, 5)) * 10.0 ** rng.integers(-300, 300, size=(n_ch, 1, 5))
        out[:, :, 4] = rng.integers(0, 2, n_ch)[:, None]  # converged or not
        out[4, 0, 2] = np.nan  # channel 4: a NaN phase
        out[5, 0, :4] = (0.0, -0.0, 1e16, 123456789.0)
        sse = np.abs(rng.standard_normal(n_ch))
        sse[6], sse[2] = np.inf, np.nan
        tracks = _bank_tracks(rng, out, sse, std=std, rocof=rocof)
        blocks = [
            Block(ch.name, 12345, 10**18 + 7, 10_000.0, np.zeros(1024), None, 0x80 | 4 | 1 if c % 2 else 0)
            for c, ch in enumerate(chs)
        ]
        gaps = [(c % 3, c % 2 == 1, c % 4 == 1, c == 8) for c in range(n_ch)]
        made = bank_payloads(pipe, chs, blocks, tracks, t_last, gaps)
        assert made is not None
        for c, ch in enumerate(chs):
            expected = estimate_payload(pipe, ch, blocks[c], tracks[c], t_last, t_last, *gaps[c], fast=False)
            assert made[c][:2] == expected, (version, fencing, std, rocof, c)
            # valid as the bytes say it, None for the channel written the general way (its NaN)
            assert made[c][2] == (None if c == 4 else b'"valid":true' in expected[0])
            cases += 1
        # a bank that set a track's RMS after column_tracks: not its usual case, nothing written
        tracks[3].residual_rms = 0.125
        assert bank_payloads(pipe, chs, blocks, tracks, t_last, gaps) is None
    assert cases == 3 * 2 * 2 * 2 * n_ch


class Batches(NullSink):
    """Keeps every estimate in order, and the size of each ``on_estimates`` batch it got."""

    def __init__(self):
        self.estimates, self.errors, self.batches = [], [], []

    def on_estimate(self, key, payload, log_time_ns):
        self.estimates.append((key, payload))

    def on_estimates(self, estimates, log_time_ns):
        self.batches.append(len(estimates))
        self.estimates += estimates

    def on_error(self, key, payload, log_time_ns):
        self.errors.append((key, json.loads(payload)["kind"]))


class ChannelByChannel(Pipeline):
    """The frame path without its per-frame shortcuts: each channel checked and its Estimate
    written and handed out on its own."""

    def _usual_frame(self, *args, **kwargs):
        return None

    def _bank_estimates(self, *args, **kwargs):
        return False


def test_a_frames_estimates_in_one_call_are_channel_by_channel_s_messages_in_order(tmp_path):
    """Frames of 6 channels (held back, the default) through the pipeline, the usual frame's
    checks made for the frame at once, one bank's Estimates written in one call and handed to
    the sinks in one batch, against the same pipeline channel by channel: the same estimates
    (bytes, keys, order), errors and channel counters, a NaN column, a lost frame (gap) and a
    channel that leaves and comes back included."""
    from sinewatch.schemas.frame import FRAME_BINARY_ENCODING, Frame, encode_frame_binary

    fs, n, step = 10_000.0, 512, 51_200_000
    rng = np.random.default_rng(5)
    names = [f"daq/c{c}" for c in range(6)]
    t = np.arange(n * 40) / fs
    signals = np.stack([np.sin(2 * np.pi * 50 * t + c) + 0.01 * rng.standard_normal(t.size) for c in range(6)], 1)
    frames = []
    for seq in range(40):
        if seq == 17:
            continue  # lost: a gap on every channel
        cols = list(range(6)) if not 25 <= seq < 28 else [0, 1, 2, 4, 5]  # c3 leaves for three frames
        x = signals[seq * n : (seq + 1) * n, cols].copy()
        if seq == 9:
            x[100, 1] = np.nan  # that channel's error, the others estimated
        frame = Frame(tuple(names[c] for c in cols), seq, seq * step, fs, x)
        frames.append(encode_frame_binary(frame, "float32"))
    got, status = {}, {}
    for cls in (Pipeline, ChannelByChannel):
        sink = Batches()
        pipe = cls(make_config(tmp_path), [sink])
        for seq, payload in enumerate(frames):
            pipe.process("sinewatch/in/daq", payload, FRAME_BINARY_ENCODING, seq)
        pipe.release_held(10**9)
        got[cls.__name__] = sink
        status[cls.__name__] = pipe.channel_status()
    one_call, each = got["Pipeline"], got["ChannelByChannel"]
    assert one_call.estimates == each.estimates and len(each.estimates) == 39 * 6 - 3 - 1
    assert one_call.errors == each.errors == [("sinewatch/err/daq/c1", "non_finite")]
    assert each.batches == [] and len(one_call.batches) == 39  # every frame's bank in one batch
    assert status["Pipeline"] == status["ChannelByChannel"]
    assert [s["gaps"] for s in status["Pipeline"]] == [1, 2, 1, 2, 1, 1]  # the lost frame; c1's NaN, c3's leave
    valid = [json.loads(p)["diagnostics"]["valid"] for _, p in each.estimates]
    assert True in valid and False in valid  # both kinds were compared


def test_a_batch_of_estimates_that_fails_part_way_counts_the_rest_as_skipped():
    """GuardedSink.on_estimates to a sink that takes them one by one: the estimates before the
    failure are written, the failure reported once, the rest of the batch counted as skipped;
    a sink's own batch that raises is one failure; a failed sink skips whole batches."""
    sink = FailingEstimates(OSError("disk full"))
    reports = []
    g = GuardedSink(sink, "flaky", lambda name, msg: reports.append(msg), retry_s=1.0, clock=Clock())
    batch = [(f"k{i}", b"{}") for i in range(5)]
    g.on_estimates(batch, 1)
    assert (sink.estimates, g.failures, g.skipped) == (5, 0, 0)

    class BreaksAtThree(FailingEstimates):
        def on_estimate(self, key, payload, log_time_ns):
            self.broken = self.broken or self.estimates == 2
            super().on_estimate(key, payload, log_time_ns)

    sink = BreaksAtThree(OSError("disk full"))
    g = GuardedSink(sink, "flaky", lambda name, msg: reports.append(msg), retry_s=1.0, clock=Clock())
    g.on_estimates(batch, 1)
    assert (sink.estimates, g.ok, g.failures, g.skipped) == (2, False, 1, 2)
    g.on_estimates(batch, 2)
    assert (sink.estimates, g.failures, g.skipped) == (2, 1, 7)
    assert reports == ["flaky failed in on_estimate: OSError: disk full"]

    class OwnBatch(NullSink):
        def on_estimates(self, estimates, log_time_ns):
            raise ConnectionError("session closed")

    g = GuardedSink(OwnBatch(), "zenoh", lambda name, msg: reports.append(msg), retry_s=1.0, clock=Clock())
    g.on_estimates(batch, 1)
    assert (g.ok, g.failures, g.skipped) == (False, 1, 0)
    assert reports[-1] == "zenoh failed in on_estimates: ConnectionError: session closed"
