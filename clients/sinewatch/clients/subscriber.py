"""Subscribing to estimates, errors and status (JSON messages)."""

from __future__ import annotations

import json
import queue
import threading
from collections.abc import Iterator
from typing import Any

import zenoh


class Fence:
    """The newest election term seen per shard (an Estimate's ``fencing``, format 4): a
    message whose term is older than one already seen from its shard comes from an owner
    that has been deposed and has not noticed yet (a paused process, a partition), and is
    dropped. Messages without ``fencing`` (daemons that own their keys without an
    election, recordings of earlier builds) pass. Thread-safe."""

    def __init__(self) -> None:
        self.newest: dict[str, int] = {}  # shard_id -> newest term seen
        self.dropped = 0  # messages of an older term, after a newer one of their shard
        self._lock = threading.Lock()

    def accept(self, msg: dict[str, Any]) -> bool:
        fencing = msg.get("fencing")
        if not isinstance(fencing, dict):
            return True
        shard, term = fencing.get("shard"), fencing.get("term")
        if not isinstance(shard, str) or not isinstance(term, int):
            return True
        with self._lock:
            newest = self.newest.get(shard)
            if newest is not None and term < newest:
                self.dropped += 1
                return False
            self.newest[shard] = term
            return True


class JsonSubscription:
    """A subscription whose messages arrive as decoded JSON dicts (key under "_key").

    Zenoh hands each sample to a callback on its own thread, which only decodes it and
    puts it in a queue; :meth:`get` and :meth:`iter` read that queue with a timeout.
    With a :class:`Fence` (estimates, by default), what a deposed shard owner publishes
    after its successor's first message is dropped (counted in ``fence.dropped``).
    Close it (or use ``with``) to undeclare.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, fence: Fence | None = None) -> None:
        self._queue: queue.Queue[dict[str, Any]] = queue.Queue()
        self.undecodable = 0
        self.fence = fence
        self._sub = session.declare_subscriber(key_expr, self._on_sample)
        self._closed = False

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
        except ValueError:
            self.undecodable += 1
            return
        if self.fence is not None and not self.fence.accept(msg):
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


def subscribe_estimates(
    session: zenoh.Session, key_expr: str = "sinewatch/est/**", fence: Fence | None = None
) -> JsonSubscription:
    """Estimates, fenced: a deposed shard owner's late ones are dropped (``fence``, or a new one)."""
    return JsonSubscription(session, key_expr, fence if fence is not None else Fence())


def subscribe_errors(session: zenoh.Session, key_expr: str = "sinewatch/err/**") -> JsonSubscription:
    return JsonSubscription(session, key_expr)


def subscribe_status(session: zenoh.Session, key_expr: str = "sinewatch/status/**") -> JsonSubscription:
    return JsonSubscription(session, key_expr)
