"""The order a takeover's history goes to the pipeline (``sinewatch.runtime.intake.catch_up_order``),
and the order a daemon takes a burst of inputs in (``KeyTurns``: the keys in turn),
on real binary blocks as the gateways publish them: each key's blocks stay in order; every
key's catch-up (its blocks up to the previous owner's last published one, then its first
block to publish and the one that releases its estimate from the hold) comes before any key's
rest, and the daemon takes it as given, ahead of anything it takes in turns, so channel k's
first estimate waits for k catch-ups, not for every channel's."""

from __future__ import annotations

import numpy as np

from sinewatch.runtime.intake import InOrder, KeyTurns, catch_up_order
from sinewatch.schemas.codec import Block, encode_block_binary


def _history(keys: list[str], seqs: range) -> list[tuple[tuple[str, bytes, str, int], str, int]]:
    """The replies of the per-key history queries: each key's blocks in order, key after key."""
    out = []
    for key in keys:
        for seq in seqs:
            payload = encode_block_binary(Block(key.rsplit("/", 1)[-1], seq, seq * 100_000_000, 1000.0, np.zeros(100)))
            out.append(((key, payload, "application/octet-stream", 0), f"pub-{key}", seq))
    return out


def _order(items: list[tuple[tuple[str, bytes, str, int], str, int]]) -> list[tuple[str, int]]:
    return [(item[0], sn) for item, _, sn in items]


def test_each_keys_catch_up_and_first_block_to_publish_come_before_any_keys_rest():
    keys = [f"sinewatch/in/ch{i}" for i in range(3)]
    published = {keys[0]: 12, keys[1]: 11, keys[2]: 13}  # the previous owner's last estimate per key
    catch_up, rest = catch_up_order(_history(keys, range(10, 16)), published)
    assert _order(catch_up) == [
        # up to 12, then 13 (the first to publish) and 14 (which releases 13's estimate from the hold)
        (keys[0], 10), (keys[0], 11), (keys[0], 12), (keys[0], 13), (keys[0], 14),
        (keys[1], 10), (keys[1], 11), (keys[1], 12), (keys[1], 13),
        (keys[2], 10), (keys[2], 11), (keys[2], 12), (keys[2], 13), (keys[2], 14), (keys[2], 15),
    ]  # fmt: skip
    assert _order(rest) == [(keys[0], 15), (keys[1], 14), (keys[1], 15)]  # the rest: the keys in turn
    order = _order(catch_up + rest)
    for key in keys:  # nothing lost, nothing twice, each key in order
        assert [sn for k, sn in order if k == key] == list(range(10, 16))


def test_a_key_without_a_resume_point_and_a_history_wholly_published():
    keys = ["sinewatch/in/a", "sinewatch/in/b"]
    # a: no resume point (a cold start, or a channel the old owner never published): taken in turn;
    # b: all of its history published already: all of it is catch-up, and nothing of it is left for the turns
    catch_up, rest = catch_up_order(_history(keys, range(3)), {keys[1]: 7})
    assert _order(catch_up) == [(keys[1], 0), (keys[1], 1), (keys[1], 2)]
    assert _order(rest) == [(keys[0], 0), (keys[0], 1), (keys[0], 2)]


def test_a_burst_is_taken_the_keys_in_turn_each_keys_in_order_and_a_key_that_comes_later_joins_the_turn():
    """A router's return: each publisher's recovered blocks come at once, key after key. Taken in
    arrival order, the last key's first block waited for every other key's whole outage (the
    router-restart test's last channel served again 1.1 s after its first, quiet)."""

    def items(key: str, seqs: range) -> list[tuple[str, bytes, str, int]]:
        return [(key, seq.to_bytes(8, "little"), "", 0) for seq in seqs]

    turns = KeyTurns()
    turns.add(items("a", range(4)) + items("b", range(4)))  # as zenoh-ext hands them over
    taken = [(k, int.from_bytes(p, "little")) for k, p, _, _ in turns.take(3)]
    assert taken == [("a", 0), ("b", 0), ("a", 1)]
    turns.add(items("c", range(2)))  # recovered later: it joins the turn at its end
    taken = [(k, int.from_bytes(p, "little")) for k, p, _, _ in turns.take(10)]
    assert taken == [("b", 1), ("a", 2), ("c", 0), ("b", 2), ("a", 3), ("c", 1), ("b", 3)]
    assert len(turns) == 0 and turns.take(5) == []


def test_a_catch_up_is_taken_as_given_ahead_of_a_backlog_taken_in_turns():
    """A takeover's catch-up goes to the daemon as :class:`InOrder` batches: taken in turns with
    the rest of the history (a backlog of more than one batch), the last channel's first estimate
    waited for the whole history (3,170 blocks: +2.73 s after the lease's expiry beside burners)."""

    def items(key: str, seqs: range) -> list[tuple[str, bytes, str, int]]:
        return [(key, seq.to_bytes(8, "little"), "", 0) for seq in seqs]

    turns = KeyTurns()
    turns.add(InOrder(items("a", range(3)) + items("b", range(2))))
    turns.add(items("a", range(3, 5)) + items("b", range(2, 4)))  # the rest of the history
    turns.add(InOrder(items("c", range(2))))  # a second batch of the catch-up, after the rest was queued
    taken = [(k, int.from_bytes(p, "little")) for k, p, _, _ in turns.take(4)]
    assert taken == [("a", 0), ("a", 1), ("a", 2), ("b", 0)]
    assert len(turns) == 5  # two keys in turn, three items in order
    taken = [(k, int.from_bytes(p, "little")) for k, p, _, _ in turns.take(100)]
    assert taken == [("b", 1), ("c", 0), ("c", 1), ("a", 3), ("b", 2), ("a", 4), ("b", 3)]
    assert len(turns) == 0
