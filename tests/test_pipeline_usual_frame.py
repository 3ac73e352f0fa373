"""A usual frame (the key's last layout, every channel the next block of its sequence, every value
finite) runs its banks from the lists its layout keeps, with no per-column object; everything
unusual on the way hands the bank to the checked path. Either way the estimates, errors and
channel counters are those of the frame path with no usual-frame shortcut at all."""

from __future__ import annotations

import json

import numpy as np
from conftest import make_config

from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.scenarios.demo import KALMAN_10K
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.frame import FRAME_BINARY_ENCODING, Frame, encode_frame_binary
from sinewatch.schemas.messages import Fencing

FS, N, STEP = 10_000.0, 512, 51_200_000
NAMES = ("daq/c0", "daq/c1", "daq/c2", "daq/c3", "daq/s0")  # s0: a rule of its own, a bank of one


class Everything(NullSink):
    def __init__(self) -> None:
        self.estimates: list[tuple[str, bytes]] = []
        self.errors: list[tuple[str, str, int | None]] = []

    def on_estimate(self, key, payload, log_time_ns):
        self.estimates.append((key, payload))

    def on_estimates(self, estimates, log_time_ns):
        self.estimates += estimates

    def on_error(self, key, payload, log_time_ns):
        report = json.loads(payload)
        self.errors.append((key, report["kind"], report["seq"]))


class Counted(Pipeline):
    """The pipeline as it is, counting the banks its usual frames ran."""

    usual_banks = 0

    def _usual_bank(self, *args, **kwargs):
        self.usual_banks += 1
        return super()._usual_bank(*args, **kwargs)


class NoUsualFrame(Pipeline):
    """The frame path with every frame checked channel by channel."""

    def _usual_frame(self, *args, **kwargs):
        return None


def _frames() -> list[bytes]:
    rng = np.random.default_rng(8)
    t = np.arange(N * 14) / FS
    x = np.stack([np.sin(2 * np.pi * 50 * t + c) + 0.01 * rng.standard_normal(t.size) for c in range(5)], 1)
    return [
        encode_frame_binary(Frame(NAMES, seq, seq * STEP, FS, x[seq * N : (seq + 1) * N]), "float32")
        for seq in range(14)
    ]


def _run(cls: type[Pipeline], tmp_path, *, fault: bool) -> tuple[Everything, Pipeline]:
    rules = [
        EstimatorRule(match="sinewatch/in/daq/s$*", estimator="sogi-fll", params={}),
        EstimatorRule(match="sinewatch/in/**", estimator="ges-kalman", params=KALMAN_10K),
    ]
    sink = Everything()
    pipe = cls(make_config(tmp_path, rules=rules), [sink])
    for seq, payload in enumerate(_frames()):
        if fault and seq == 3:  # a fault in c2's estimator (a kernel bug, say) on frame 6 only, from now on
            est = pipe.channels["daq/c2"].estimator
            update = est.update

            def faulty(samples, *, last_only=False, t0_ns=None, _update=update):
                if t0_ns == 6 * STEP:
                    raise ZeroDivisionError("injected kernel fault")
                return _update(samples, last_only=last_only, t0_ns=t0_ns)

            est.update = faulty
        if not fault and seq == 10:  # a new term: every Estimate's template changes, the bank's kept writing with it
            pipe.set_fencing(Fencing(shard="s", term=7))
        pipe.process("sinewatch/in/daq", payload, FRAME_BINARY_ENCODING, seq)
    pipe.release_held(10**12)
    return sink, pipe


def test_a_usual_frame_s_banks_give_what_the_checked_path_gives_through_a_fault(tmp_path):
    """Frames of five channels in two banks (four of ges-kalman, one of sogi-fll: a bank of
    one, whose detector runs on its own), a fault injected into one channel's estimator on one
    frame (its bank raises, is rolled back and run channel by channel): the same estimates byte
    for byte and in order, the same errors and channel counters as every frame checked."""
    usual, pipe = _run(Counted, tmp_path, fault=True)
    checked, checked_pipe = _run(NoUsualFrame, tmp_path, fault=True)
    # both banks of every frame but the first and frame 7 (c2's next block after its lost one:
    # a gap, checked channel by channel)
    assert pipe.usual_banks == 2 * 12
    assert usual.errors == checked.errors == [("sinewatch/err/daq/c2", "estimator_fault", 6)]
    assert usual.estimates == checked.estimates
    assert len(usual.estimates) == 14 * 5 - 1  # every accepted block's, the faulty one's lost
    assert pipe.channel_status() == checked_pipe.channel_status()
    by_channel = {s["channel"]: s for s in pipe.channel_status()}
    assert by_channel["daq/c2"]["gaps"] == 1 and by_channel["daq/c2"]["blocks"] == 13  # seq 6 lost
    assert by_channel["daq/c0"]["gaps"] == 0 and by_channel["daq/c0"]["blocks"] == 14


def test_a_usual_bank_s_kept_writing_gives_the_general_bytes_through_a_new_term(tmp_path):
    """The compiled bank's Estimates written from what its layout keeps (BankWriting) from the
    second frame on, a new fencing term mid-stream (every template changes, the kept writing
    made again): the same estimates byte for byte as every frame checked and written channel by
    channel, valid and converged both ways."""
    usual, pipe = _run(Counted, tmp_path, fault=False)
    checked, checked_pipe = _run(NoUsualFrame, tmp_path, fault=False)
    assert pipe.usual_banks == 2 * 13
    (layout,) = pipe._layouts.values()
    kept = layout.banks[0].writing
    assert kept is not None and kept.layout[4] == '{"shard":"s","term":7}'  # made again for the new term
    assert usual.estimates == checked.estimates and len(usual.estimates) == 14 * 5
    assert usual.errors == checked.errors == []
    assert pipe.channel_status() == checked_pipe.channel_status()
    made = [json.loads(p) for _, p in usual.estimates]
    assert {e["diagnostics"]["valid"] for e in made} == {True, False}  # both kinds compared
    assert {e["diagnostics"]["converged"] for e in made} == {True, False}
    assert [e["fencing"] for e in made if e["seq"] >= 10] == [{"shard": "s", "term": 7}] * 4 * 5


def test_a_kept_writing_gives_bank_payloads_bytes_converged_and_valid(tmp_path):
    """usual_bank_payloads against bank_payloads on one bank's Tracks, each channel's
    (converged at its last row, presence run) chosen to give every pair of flags: the same
    bytes, converged and valid; nothing written once the layout is another (a new term)."""
    from sinewatch.core.channel import Channel
    from sinewatch.core.estimate_bytes import bank_payloads, bank_writing, usual_bank_payloads
    from sinewatch.estimators.bank import update_bank
    from sinewatch.estimators.ges_kalman import GesKalman
    from sinewatch.schemas.codec import Block

    pipe = Pipeline(make_config(tmp_path), [NullSink()])
    chs = [Channel(f"b/{c}", f"sinewatch/in/b/{c}", GesKalman(FS, KALMAN_10K), FS) for c in range(6)]
    t = np.arange(N) / FS
    x = np.stack([np.sin(2 * np.pi * 50 * t + c) for c in range(6)], 1)
    tracks = update_bank([ch.estimator for ch in chs], x, last_only=True)
    tracks._args[0][:, -1, 4] = [1, 0, 1, 1, 0, 1]  # converged at the last row, a channel each
    memory = chs[0].valid_memory_samples
    runs = [0, memory - 1, memory, 5 * memory, memory, 10**9]
    block, t_last = Block("b/0", 3, 0, FS, x[:, 0]), (N - 1) * 100_000
    general = bank_payloads(pipe, chs, [block] * 6, tracks, t_last, [(0, False, False, False)] * 6, runs)
    writing = bank_writing(pipe, chs, block, tracks)
    assert general is not None and writing is not None
    assert usual_bank_payloads(pipe, writing, block, tracks, t_last, runs) == general
    flags = [(converged, valid) for _, converged, valid in general]
    assert flags == [(False, False), (False, False), (True, True), (True, True), (False, True), (True, True)]
    pipe.set_fencing(Fencing(shard="s", term=2))
    assert usual_bank_payloads(pipe, writing, block, tracks, t_last, runs) is None


def test_a_bank_whose_estimates_in_one_call_fail_writes_each_channel_on_its_own(tmp_path, caplog):
    """The kept writing broken from the third frame on (a bug, say): each following frame's
    Estimates in one call fail, are counted and logged the first few times only, and each
    channel's Estimate is written, held and handed out on its own: the same estimates as every
    frame checked."""

    class Broken(Pipeline):
        def _usual_bank(self, bank, *args, **kwargs):
            if bank.writing is not None:
                bank.writing = "not a BankWriting"
            return super()._usual_bank(bank, *args, **kwargs)

    broken, pipe = _run(Broken, tmp_path, fault=False)
    checked, _ = _run(NoUsualFrame, tmp_path, fault=False)
    assert broken.estimates == checked.estimates and len(broken.estimates) == 14 * 5
    assert broken.errors == checked.errors == []
    assert pipe._bank_estimate_failures == 14 - 2  # every frame after the one that made the writing
    assert len([r for r in caplog.records if "in one call failed" in r.getMessage()]) == 5
