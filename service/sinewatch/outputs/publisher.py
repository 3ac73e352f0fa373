"""The Zenoh publisher: a pipeline sink that puts estimates, errors, status and the
power-quality messages on Zenoh.

Estimates, errors and power-quality messages use ``CongestionControl.BLOCK`` (a slow subscriber slows the
publisher rather than losing them); status uses ``DROP`` (the next one comes soon).
Each message announces its encoding (:mod:`sinewatch.schemas.codec`).
"""

from __future__ import annotations

import zenoh

from sinewatch.core.pipeline import NullSink
from sinewatch.schemas.codec import ERROR_JSON_ENCODING, ESTIMATE_JSON_ENCODING, STATUS_JSON_ENCODING
from sinewatch.schemas.power_quality import json_encoding


class ZenohPublisherSink(NullSink):
    """Publishes estimates and errors (BLOCK: not dropped) and status (DROP)."""

    sink_name = "zenoh"

    def __init__(self, session: zenoh.Session) -> None:
        self._session = session
        self._publishers: dict[str, zenoh.Publisher] = {}

    def _publisher(self, key: str, encoding: str, congestion: zenoh.CongestionControl) -> zenoh.Publisher:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._session.declare_publisher(key, encoding=zenoh.Encoding(encoding), congestion_control=congestion)
            self._publishers[key] = pub
        return pub

    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._publisher(key, ESTIMATE_JSON_ENCODING, zenoh.CongestionControl.BLOCK).put(payload)

    def on_estimates(self, estimates: list[tuple[str, bytes]], log_time_ns: int) -> None:
        """A frame's estimates, each put as :meth:`on_estimate` puts it, in one loop."""
        publishers = self._publishers
        for key, payload in estimates:
            pub = publishers.get(key)
            if pub is None:
                pub = self._publisher(key, ESTIMATE_JSON_ENCODING, zenoh.CongestionControl.BLOCK)
            pub.put(payload)

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._publisher(key, ERROR_JSON_ENCODING, zenoh.CongestionControl.BLOCK).put(payload)

    def on_status(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._publisher(key, STATUS_JSON_ENCODING, zenoh.CongestionControl.DROP).put(payload)

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        """Power-quality messages (HarmonicsReport, ThreePhaseReport, PqAggregate): BLOCK."""
        self._publisher(key, json_encoding(kind), zenoh.CongestionControl.BLOCK).put(payload)

    def recover(self) -> None:
        """Declare the publishers afresh on the next put (after a session fault)."""
        self._publishers.clear()

    def close(self) -> None:
        for pub in self._publishers.values():
            pub.undeclare()
        self._publishers.clear()


__all__ = ["ZenohPublisherSink"]
