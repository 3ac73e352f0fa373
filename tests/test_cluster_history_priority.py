"""A takeover's history query asks for its replies at ``data_high``, a priority of their own
(``sinewatch.runtime.intake.history_query``): a reply goes with its query's QoS, hop by hop (the
publisher's session to the router, the router to the daemon), so the caches' replies do not
queue behind the publisher's own puts (``data``) in the same priority queue of its session, and
reach the new owner ahead of the live inputs the router sends it. In a 50-fault chaos run on
the tree before (2026-11-28, load 3-16), a new owner's 50 history queries (~4,600 replies)
went out at ``data`` beside the gateway's puts, the gateway's session could push nothing for
30 s and closed its link, twice (19 % of the blocks lost). On real Zenoh sessions through
``sinewatch router`` on 127.0.0.1: the replies of the history query come at ``data_high``, the
live samples of the same publisher at ``data``."""

from __future__ import annotations

import threading

import numpy as np
import zenoh
from cluster_procs import Router

from sinewatch.clients import BlockPublisher, connect
from sinewatch.runtime.intake import HISTORY_PRIORITY, history_query

WAIT_S = 30.0  # the longest a delivery may take on a loaded machine (a wait that ends when it is done)
KEY = "sinewatch/in/p"


def test_a_history_querys_replies_come_at_their_own_priority_and_the_live_inputs_at_theirs(tmp_path):
    router = Router(tmp_path)
    router.start()
    endpoint = [f"tcp/127.0.0.1:{router.port}"]
    try:
        with connect(endpoint) as gateway, connect(endpoint) as daemon:
            live: list[zenoh.Priority] = []
            arrived = threading.Event()
            daemon.declare_subscriber(KEY, lambda s: (live.append(s.priority), arrived.set()))
            # the publisher's token is declared after its cache (zenoh-ext): once the daemon's session sees it,
            # its query reaches the cache
            known = threading.Event()
            tokens = daemon.liveliness().declare_subscriber(f"{KEY}/@adv/**", lambda _: known.set(), history=True)
            publisher = BlockPublisher(gateway, history=16)
            assert publisher.wait_for_subscriber("p", WAIT_S)
            for _ in range(5):
                publisher.publish("p", np.zeros(100, dtype=np.float32), 1000.0)
            assert known.wait(WAIT_S) and arrived.wait(WAIT_S)
            replies = [r.ok for r in history_query(daemon, f"{KEY}/@adv/**?_max=16", 16) if r.ok is not None]
            assert len(replies) == 5
            assert HISTORY_PRIORITY == zenoh.Priority.DATA_HIGH
            assert all(s.priority == HISTORY_PRIORITY for s in replies), [s.priority for s in replies]
            assert all(s.congestion_control == zenoh.CongestionControl.BLOCK for s in replies)  # none dropped
            assert live and all(p == zenoh.Priority.DATA for p in live), live  # the inputs keep theirs
            tokens.undeclare()
            publisher.close()
    finally:
        router.kill()
