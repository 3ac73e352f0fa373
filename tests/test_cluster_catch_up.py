"""The order a takeover's history goes to the pipeline (``sinewatch.runtime.intake.catch_up_order``),
and the order a daemon takes a burst of inputs in (``KeyTurns``: the keys in turn),
on real binary blocks as the gateways publish them: each key's blocks stay in order; every
key's catch-up (its blocks up to the previous owner's last published one, then its first
block to publish) comes before any key's rest, so channel k's first estimate waits for k
catch-ups, not for every channel's."""

from __future__ import annotations

import numpy as np

from sinewatch.runtime.intake import KeyTurns, catch_up_order
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
    order = _order(catch_up_order(_history(keys, range(10, 16)), published))
    assert order == [
        (keys[0], 10), (keys[0], 11), (keys[0], 12), (keys[0], 13),  # up to 12, then 13: the first to publish
        (keys[1], 10), (keys[1], 11), (keys[1], 12),
        (keys[2], 10), (keys[2], 11), (keys[2], 12), (keys[2], 13), (keys[2], 14),
        (keys[0], 14), (keys[1], 13), (keys[2], 15),  # the rest: the keys in turn
        (keys[0], 15), (keys[1], 14),
        (keys[1], 15),
    ]  # fmt: skip
    for key in keys:  # nothing lost, nothing twice, each key in order
        assert [sn for k, sn in order if k == key] == list(range(10, 16))


def test_a_key_without_a_resume_point_and_a_history_wholly_published():
    keys = ["sinewatch/in/a", "sinewatch/in/b"]
    # a: no resume point (a cold start, or a channel the old owner never published): taken in turn;
    # b: all of its history published already: all of it is catch-up, and nothing of it is left for the turns
    order = _order(catch_up_order(_history(keys, range(3)), {keys[1]: 7}))
    assert order == [(keys[1], 0), (keys[1], 1), (keys[1], 2), (keys[0], 0), (keys[0], 1), (keys[0], 2)]


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
