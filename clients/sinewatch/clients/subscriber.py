"""Subscribing to estimates, errors and status (JSON messages)."""

from __future__ import annotations

import json
import queue
from collections.abc import Iterator
from typing import Any

import zenoh


class JsonSubscription:
    """A subscription whose messages arrive as decoded JSON dicts (key under "_key").

    Zenoh hands each sample to a callback on its own thread, which only decodes it and
    puts it in a queue; :meth:`get` and :meth:`iter` read that queue with a timeout.
    Close it (or use ``with``) to undeclare.
    """

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self._queue: queue.Queue[dict[str, Any]] = queue.Queue()
        self.undecodable = 0
        self._sub = session.declare_subscriber(key_expr, self._on_sample)
        self._closed = False

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
        except ValueError:
            self.undecodable += 1
            return
        msg["_key"] = str(sample.key_expr)
        self._queue.put(msg)

    def get(self, timeout: float | None = None) -> dict[str, Any] | None:
        """The next message, or None if none arrives within ``timeout`` seconds."""
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def iter(self, timeout: float | None = None) -> Iterator[dict[str, Any]]:
        """Messages until ``timeout`` seconds pass without one (forever if None)."""
        while (msg := self.get(timeout)) is not None:
            yield msg

    def close(self) -> None:
        if not self._closed:
            self._sub.undeclare()
            self._closed = True

    def __enter__(self) -> JsonSubscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def subscribe_estimates(session: zenoh.Session, key_expr: str = "sinewatch/est/**") -> JsonSubscription:
    return JsonSubscription(session, key_expr)


def subscribe_errors(session: zenoh.Session, key_expr: str = "sinewatch/err/**") -> JsonSubscription:
    return JsonSubscription(session, key_expr)


def subscribe_status(session: zenoh.Session, key_expr: str = "sinewatch/status/**") -> JsonSubscription:
    return JsonSubscription(session, key_expr)
