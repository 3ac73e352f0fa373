"""Opening a client session to a sinewatch daemon (or to a Zenoh router in front of it)."""

from __future__ import annotations

import zenoh

from sinewatch.schemas.config import DEFAULT_ENDPOINT, ZenohSection
from sinewatch.zenoh_session import open_session

DEFAULT_CONNECT = [DEFAULT_ENDPOINT]


def connect(endpoints: list[str] | None = None, *, mode: str = "client") -> zenoh.Session:
    """A Zenoh session that connects to ``endpoints`` (the daemon's default endpoint if
    None), listens nowhere and does not scout. Use it as a context manager or close it."""
    return open_session(ZenohSection(mode=mode, listen=[], connect=endpoints or DEFAULT_CONNECT))
