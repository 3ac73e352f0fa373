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


def _run(cls: type[Pipeline], tmp_path) -> tuple[Everything, Pipeline]:
    rules = [
        EstimatorRule(match="sinewatch/in/daq/s$*", estimator="sogi-fll", params={}),
        EstimatorRule(match="sinewatch/in/**", estimator="ges-kalman", params=KALMAN_10K),
    ]
    sink = Everything()
    pipe = cls(make_config(tmp_path, rules=rules), [sink])
    for seq, payload in enumerate(_frames()):
        if seq == 3:  # a fault in c2's estimator (a kernel bug, say) on frame 6 only, from now on
            est = pipe.channels["daq/c2"].estimator
            update = est.update

            def faulty(samples, *, last_only=False, t0_ns=None, _update=update):
                if t0_ns == 6 * STEP:
                    raise ZeroDivisionError("injected kernel fault")
                return _update(samples, last_only=last_only, t0_ns=t0_ns)

            est.update = faulty
        pipe.process("sinewatch/in/daq", payload, FRAME_BINARY_ENCODING, seq)
    pipe.release_held(10**12)
    return sink, pipe


def test_a_usual_frame_s_banks_give_what_the_checked_path_gives_through_a_fault(tmp_path):
    """Frames of five channels in two banks (four of ges-kalman, one of sogi-fll: a bank of
    one, whose detector runs on its own), a fault injected into one channel's estimator on one
    frame (its bank raises, is rolled back and run channel by channel): the same estimates byte
    for byte and in order, the same errors and channel counters as every frame checked."""
    usual, pipe = _run(Counted, tmp_path)
    checked, checked_pipe = _run(NoUsualFrame, tmp_path)
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
    valid = {json.loads(p)["diagnostics"]["valid"] for _, p in usual.estimates}
    assert valid == {True, False}  # held estimates both confirmed and not, compared alike
