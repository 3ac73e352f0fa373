"""A cluster member answers admin queries on a thread of its own, not in a callback on Zenoh's
receiving thread (``sinewatch.runtime.cluster.ClusterMember``): with its event loop busy, the callback
waited for the loop (up to ``ADMIN_QUERY_TIMEOUT_S`` a query), zenoh-python's channel to the
callback's thread filled, and Zenoh read nothing more from the member's link. Behind a router,
everything the router then had to push to it with ``BLOCK`` stops the router reading the sender's
link for everyone ("A querier that reads nothing", docs/cluster.md). On real Zenoh sessions on
127.0.0.1: the member's event loop is held busy; ``QUERIES`` queries come, then a put on the same
link; the put must arrive while the loop is still busy (with the callback it had not within 30 s),
and the last query is answered once the loop runs again."""

from __future__ import annotations

import asyncio
import json
import threading
from types import SimpleNamespace
from typing import Any

import zenoh
from peer_pair import loop_and_two_peers, wait_until_routed

from sinewatch.runtime.cluster import ClusterMember
from sinewatch.schemas.config import SinewatchConfig

QUERIES = 300  # past what zenoh-python's channel to a callback's thread holds (over 60 here)
WAIT_S = 30.0  # the longest a delivery may take on a loaded machine (a wait that ends when it is done)


class Host:
    """What a cluster member needs of its daemon: a config without etcd (it owns its shard alone),
    the session, an empty pipeline, and an intake that is only counted."""

    def __init__(self, session: zenoh.Session) -> None:
        self.config = SinewatchConfig.model_validate({"daemon_id": "d1", "cluster": {"shard": "1/2"}})
        self.session = session
        self.recorder = None
        self.pipeline = SimpleNamespace(channels={}, resume_points={})
        self.intakes = 0

    def start_intake(self, history_blocks: int | None = None) -> None:
        self.intakes += 1

    async def stop_intake(self) -> None:
        return None

    def intake_counters(self) -> Any:
        return SimpleNamespace(not_owned=0)


def test_a_members_link_is_read_while_its_event_loop_is_busy_and_the_admin_query_is_answered_after():
    with loop_and_two_peers() as (loop, asker, member_session):
        marker = threading.Event()
        member_session.declare_subscriber("test/marker", lambda _: marker.set())
        host = Host(member_session)
        cluster = ClusterMember(host)  # type: ignore[arg-type]
        started = threading.Event()
        loop.call_soon_threadsafe(lambda: (cluster.start(loop), started.set()))
        assert started.wait(WAIT_S) and host.intakes == 1  # no etcd: it owns its shard at once
        # the marker's subscriber and the admin queryable known to the asker's session: a put or a query sent before
        # a declaration has come goes nowhere (the marker would never arrive, however the member read its link)
        assert wait_until_routed(asker, "test/marker", to_queryable=False, timeout=WAIT_S)
        assert wait_until_routed(asker, cluster.admin_key, to_queryable=True, timeout=WAIT_S)
        busy, free = threading.Event(), threading.Event()
        loop.call_soon_threadsafe(lambda: (busy.set(), free.wait(WAIT_S)))  # the loop held: a long batch, a start
        assert busy.wait(WAIT_S)
        try:
            # come first on the link: more than a channel to a callback thread holds ...
            asked = [asker.get(cluster.admin_key, timeout=WAIT_S) for _ in range(QUERIES)]
            asker.put("test/marker", b"")  # ... then this: read only if the query's handling did not stop Zenoh
            arrived_while_busy = marker.wait(WAIT_S)
        finally:
            free.set()
        assert arrived_while_busy
        answers = [json.loads(r.ok.payload.to_bytes()) for r in asked[-1] if r.ok is not None]
        assert [(a["daemon_id"], a["role"], a["shard"]) for a in answers] == [("d1", "active", "1/2")]
        asyncio.run_coroutine_threadsafe(cluster.close(), loop).result(WAIT_S)
