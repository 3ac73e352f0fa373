"""Held estimates (``hold_estimates``) at a change of ownership: a daemon never publishes a held
estimate under a term it does not hold now.

The owner's snapshot carries what it holds, made and stamped under its term. A successor that
restored it once released those estimates with the old term's bytes, while the old owner, which
ran on past the snapshot, had published them itself: one block published by two daemons under
one term (the 5-fault chaos test saw about a dozen channel-blocks per takeover). These tests run
the takeover as :meth:`sinewatch.runtime.cluster.ClusterMember.take_over` and the daemon's
intake do it (restore, resume points from what the standby saw published, the new term, then
:meth:`Pipeline.take_over_held`), on pipelines with real sinks, no Zenoh.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sinewatch.core.channel import ResumePoint
from sinewatch.core.hold import restamp
from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.runtime.cluster import last_published
from sinewatch.schemas.codec import Block, encode_block_binary
from sinewatch.schemas.config import EstimatorRule, SinewatchConfig
from sinewatch.schemas.messages import Fencing

FS = 10_000.0
BLOCK = 250  # 25 ms: an estimate at a block's end leaves with the next block
T00 = 1_700_000_000_000_000_000
KEY = "sinewatch/in/v"


class Keep(NullSink):
    def __init__(self) -> None:
        self.out: list[bytes] = []

    def on_estimate(self, key, payload, log_time_ns):
        self.out.append(payload)

    def messages(self) -> list[dict]:
        return [json.loads(p) for p in self.out]


def _blocks(n: int) -> list[Block]:
    t = np.arange(n * BLOCK) / FS
    x = np.sin(2 * np.pi * 50.0 * t + 0.3) + np.random.default_rng(3).normal(0, 1e-3, t.size)
    return [
        Block("v", seq, T00 + round(seq * BLOCK * 1e9 / FS), FS, x[seq * BLOCK : (seq + 1) * BLOCK]) for seq in range(n)
    ]


def _config() -> SinewatchConfig:
    return SinewatchConfig(rules=[EstimatorRule(match="sinewatch/in/**", estimator="ges-kalman")], hold_estimates=True)


def _feed(p: Pipeline, blocks: list[Block]) -> None:
    for b in blocks:
        p.process(KEY, encode_block_binary(b), "", b.t0_ns)


def _take_over(p: Pipeline, snapshot: dict, published: dict[str, tuple[int, int]], term: int) -> None:
    """What the cluster's take_over and the daemon's start_intake do, in their order."""
    p.restore(snapshot)
    for name, (seq, timestamp_ns) in published.items():
        ch = p.channels.get(name)
        if ch is None or ch.last_seq is None or ch.last_seq < seq:
            p.resume_points[name] = ResumePoint(seq, timestamp_ns + round(1e9 / FS))
    p.set_fencing(Fencing(shard="s", term=term))
    p.take_over_held(published)


def _owner(blocks: list[Block], snapshot_after: int, dies_after: int) -> tuple[Keep, dict]:
    """An owner under term 1 that is snapshotted after block ``snapshot_after`` and dies after
    block ``dies_after``: what it published, and the snapshot."""
    sink = Keep()
    owner = Pipeline(_config(), [sink])
    owner.set_fencing(Fencing(shard="s", term=1))
    _feed(owner, blocks[: snapshot_after + 1])
    snapshot = json.loads(json.dumps(owner.snapshot()))  # as the standby receives it
    assert snapshot["channels"][0].get("held"), "the snapshot holds an estimate: the case under test"
    _feed(owner, blocks[snapshot_after + 1 : dies_after + 1])
    return sink, snapshot


@pytest.mark.parametrize(
    "snapshot_after, dies_after",
    [
        (10, 11),  # the owner published the snapshot's held estimate before it died
        (10, 14),  # and several blocks past it (the successor catches up to them)
        (10, 10),  # it died before publishing it: the successor must, under its own term
    ],
)
def test_a_takeover_never_publishes_a_held_estimate_under_the_previous_term(snapshot_after, dies_after):
    """Every block's estimate is published once across the two owners (none lost, none twice),
    and every one the successor publishes carries its own term. Before the fix the successor
    released the snapshot's held estimate as it was: stamped with term 1, which the owner had
    published too (the first two cases), and the third published under a term it did not hold."""
    blocks = _blocks(30)
    old, snapshot = _owner(blocks, snapshot_after, dies_after)
    seen = old.messages()
    published = {"v": (seen[-1]["seq"], seen[-1]["timestamp_ns"])} if seen else {}
    new = Keep()
    successor = Pipeline(_config(), [new])
    _take_over(successor, snapshot, published, term=2)
    _feed(successor, blocks[snapshot_after + 1 :])  # the publishers' history, then live blocks
    successor.release_held(T00)
    mine = new.messages()
    assert {m["fencing"]["term"] for m in mine} == {2}
    seqs = [m["seq"] for m in seen] + [m["seq"] for m in mine]
    assert seqs == list(range(len(blocks))), "every block's estimate once, in order, across the two owners"
    assert successor.counters.held_dropped == (1 if dies_after > snapshot_after else 0)


def test_a_takeover_keeps_the_held_estimates_bytes_but_their_term():
    """A held estimate the successor publishes is the one the owner made, byte for byte, but for
    its fencing: its values and validity are the owner's (the detector that confirms it is the
    restored one)."""
    blocks = _blocks(20)
    old, snapshot = _owner(blocks, 10, 10)
    last = old.messages()[-1]
    successor = Pipeline(_config(), [new := Keep()])
    _take_over(successor, snapshot, {"v": (last["seq"], last["timestamp_ns"])}, term=7)
    _feed(successor, blocks[11:12])
    ran_on = Keep()
    owner = Pipeline(_config(), [ran_on])
    owner.set_fencing(Fencing(shard="s", term=1))
    _feed(owner, blocks[:12])
    expected = ran_on.out[-1].replace(b'"fencing":{"shard":"s","term":1}', b'"fencing":{"shard":"s","term":7}')
    assert new.out == [expected]


def test_a_deposed_owner_drops_what_it_holds():
    """An owner that lost its lease drops its held estimates (its successor publishes them,
    from its snapshot or the inputs again): nothing is left to release at its stop, nor when it
    takes a block again under a later term."""
    blocks = _blocks(12)
    sink = Keep()
    owner = Pipeline(_config(), [sink])
    owner.set_fencing(Fencing(shard="s", term=1))
    _feed(owner, blocks[:10])
    n = len(sink.out)
    assert owner.drop_held() == 1
    assert owner.release_held(T00) == 0 and len(sink.out) == n
    assert owner.counters.held_dropped == 1
    owner.set_fencing(Fencing(shard="s", term=3))  # re-elected later, on its own state
    owner.take_over_held({})
    _feed(owner, blocks[10:])
    assert {m["fencing"]["term"] for m in sink.messages()[n:]} == {3}


@pytest.mark.parametrize("name", ["v", 'a "quoted" name', "Spannung Ü/ß ✓"])
def test_restamp_replaces_the_fencing_member_only(name):
    """The fencing is found as the message's last member of that name, whatever the channel's
    name holds (escaped quotes, non-ASCII text), and a message with no fencing (formats 1-3) is
    left as it is."""
    body = {"format_version": 5, "channel": name, "seq": 1, "diagnostics": {"extras": {"fencing": 1}}}
    fenced = {**body, "fencing": {"shard": "s", "term": 1}, "time_quality": None}
    payload = json.dumps(fenced, ensure_ascii=False, separators=(",", ":"))
    out = json.loads(restamp(payload.encode(), '{"shard":"s","term":12}'))
    assert out == {**body, "fencing": {"shard": "s", "term": 12}, "time_quality": None}
    assert json.loads(restamp(payload.encode(), "null"))["fencing"] is None
    old = json.dumps(body, separators=(",", ":")).encode()
    assert restamp(old, "null") == old


class _ElectionJustWon:
    """The election at the instant a campaign returns: the lease is held, so the gate is open,
    and the takeover (re-stamp or drop the held estimates, then serve) has not run yet."""

    def may_publish(self) -> bool:
        return True


def test_the_idle_release_waits_for_the_takeover_not_for_the_won_election():
    """A standby that restored its owner's snapshot ahead holds the owner's held estimates,
    stamped with the owner's term. The 5-fault chaos test saw one daemon publish them under that
    term in the instant between winning the election and taking over: the idle-release timer ran
    while the gate was already open (about 50 channel-blocks published by two daemons under one
    term). Now the timer (and the drain) release only once the daemon serves the shard."""
    from sinewatch.runtime.cluster import ClusterMember
    from sinewatch.runtime.daemon import Daemon

    blocks = _blocks(12)
    _, snapshot = _owner(blocks, 10, 10)
    daemon = Daemon(_config(), install_signal_handlers=False)
    daemon._pipeline = Pipeline(_config(), [sink := Keep()])
    daemon._pipeline.restore(snapshot)  # restored ahead, as the owner's lease runs out
    member = ClusterMember(daemon)
    member.election = _ElectionJustWon()  # type: ignore[assignment]
    member.role = "standby"
    daemon.cluster = member
    daemon._last_log_time = T00 + 10**12  # long after the channel's last block: idle
    daemon.release_idle()
    assert sink.out == [], "nothing leaves before the takeover has re-stamped what the state holds"
    daemon.pipeline.set_fencing(Fencing(shard="s", term=2))
    daemon.pipeline.take_over_held({})
    member.role = "active"
    daemon.release_idle()
    assert [m["fencing"]["term"] for m in sink.messages()] == [2]


def test_a_deposed_owner_notes_as_published_the_block_before_its_first_held_one():
    """What a deposed owner notes as published when it stands down (``cluster.last_published``,
    read before it drops what it holds) is the block before its first held estimate, not its last
    block. Noted as its last block, the held block was taken for published: re-elected later from
    a snapshot, the daemon caught up past it without publishing it and flagged no gap (a block
    lost in a failover round, the owner re-elected after its own lease ran out at load 37)."""
    blocks = _blocks(14)
    sink = Keep()
    owner = Pipeline(_config(), [sink])
    owner.set_fencing(Fencing(shard="s", term=1))
    _feed(owner, blocks[:6])
    snapshot = json.loads(json.dumps(owner.snapshot()))
    _feed(owner, blocks[6:10])
    last = sink.messages()[-1]
    assert owner.channels["v"].last_seq == 9 and last["seq"] == 8, "block 9's estimate is held: the case under test"
    published = last_published(owner)
    assert published == {"v": (8, last["timestamp_ns"])}
    assert owner.drop_held() == 1  # what stop_intake does next
    again = Keep()
    reelected = Pipeline(_config(), [again])  # its state from the snapshot, the publishers' history after it
    _take_over(reelected, snapshot, published, term=3)
    _feed(reelected, blocks[6:])
    reelected.release_held(T00)
    seqs = [m["seq"] for m in sink.messages()] + [m["seq"] for m in again.messages()]
    assert seqs == list(range(len(blocks))), "every block's estimate once, in order, across the two terms"
