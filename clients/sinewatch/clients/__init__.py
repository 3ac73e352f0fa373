"""A small client library for sinewatch: publish sample blocks, subscribe to estimates.

    from sinewatch.clients import connect, BlockPublisher, subscribe_estimates

    with connect(["tcp/127.0.0.1:7450"]) as session:
        pub = BlockPublisher(session)
        pub.publish("feeder1/phase-a", samples, sample_rate_hz=10_000.0)
        with subscribe_estimates(session, "sinewatch/est/**") as estimates:
            for est in estimates.iter(timeout=5.0):
                print(est["channel"], est["frequency_hz"])

``sinewatch feed`` and ``sinewatch tail`` are thin command-line wrappers over these.
"""

from sinewatch.clients.publisher import BlockPublisher
from sinewatch.clients.session import DEFAULT_CONNECT, connect
from sinewatch.clients.subscriber import (
    Fence,
    JsonSubscription,
    subscribe_errors,
    subscribe_estimates,
    subscribe_status,
)

__all__ = [
    "DEFAULT_CONNECT",
    "BlockPublisher",
    "Fence",
    "JsonSubscription",
    "connect",
    "subscribe_errors",
    "subscribe_estimates",
    "subscribe_status",
]
