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
