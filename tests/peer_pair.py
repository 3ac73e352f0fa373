"""An event loop on a thread of its own and two Zenoh peer sessions on 127.0.0.1, the second
connected to the first (no scouting): what the in-process cluster tests run a daemon's part on."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Iterator

import zenoh

from sinewatch.clients.session import free_loopback_port, open_session
from sinewatch.schemas.config import ZenohSection

JOIN_S = 30.0  # the longest the loop's thread may take to end on a loaded machine


def wait_until_routed(session: zenoh.Session, key_expr: str, *, to_queryable: bool, timeout: float) -> bool:
    """Until ``session`` routes a put (``to_queryable=False``: a subscriber matches) or a query
    (``to_queryable=True``: a queryable matches) on ``key_expr`` somewhere: True, or False after
    ``timeout``. A declaration reaches the other peer asynchronously, and a put or query sent before
    it has arrived goes nowhere (no error): on a loaded machine a test's first query after declaring
    a queryable on the other session came back empty."""
    entity = session.declare_querier(key_expr) if to_queryable else session.declare_publisher(key_expr)
    routed = threading.Event()
    listener = entity.declare_matching_listener(lambda status: status.matching and routed.set())
    try:
        return bool(entity.matching_status.matching) or routed.wait(timeout)  # type: ignore[attr-defined]
    finally:
        listener.undeclare()
        entity.undeclare()  # type: ignore[no-untyped-call]


@contextlib.contextmanager
def loop_and_two_peers() -> Iterator[tuple[asyncio.AbstractEventLoop, zenoh.Session, zenoh.Session]]:
    """(loop, the listening session, the session connected to it)."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    loop = asyncio.new_event_loop()
    runner = threading.Thread(target=loop.run_forever, daemon=True)
    runner.start()
    quiet = {"multicast_scouting": False}
    try:
        with (
            open_session(ZenohSection(mode="peer", listen=[endpoint], connect=[], **quiet)) as listening,
            open_session(ZenohSection(mode="peer", listen=[], connect=[endpoint], **quiet)) as connected,
        ):
            yield loop, listening, connected
    finally:
        loop.call_soon_threadsafe(loop.stop)
        runner.join(JOIN_S)
