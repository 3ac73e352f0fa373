"""Opening a client session to a sinewatch daemon (or to a Zenoh router in front of it)."""

from __future__ import annotations

import zenoh

from sinewatch.schemas.config import DEFAULT_ENDPOINT, ZenohSection
from sinewatch.zenoh_session import open_session

DEFAULT_CONNECT = [DEFAULT_ENDPOINT]


def connect(endpoints: list[str] | None = None, *, timeout_s: float = 10.0, mode: str = "client") -> zenoh.Session:
    """A Zenoh session that connects to ``endpoints`` (the daemon's default endpoint if
    None), listens nowhere and does not scout. Zenoh keeps retrying for ``timeout_s``
    seconds, so a client may start before the daemon. Close it, or use ``with``."""
    section = ZenohSection(
        mode=mode,
        listen=[],
        connect=endpoints or DEFAULT_CONNECT,
        raw={"connect/timeout_ms": int(timeout_s * 1000)},
    )
    return open_session(section)
