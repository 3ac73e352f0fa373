"""A daemon behind a router (``queue_policy = "drop"``) keeps reading its Zenoh link while its
intake's pump is behind (``sinewatch.runtime.intake.zenoh_side_channel``). With a small FIFO
between Zenoh's receiving thread and the pump, a pump starved of the GIL or of CPU (a takeover's
50 history threads beside it, on a loaded machine) lets the FIFO fill; Zenoh's thread then waits
on it and reads nothing more off the link, replies included, and the router, pushing the daemon
a ``BLOCK`` reply, stops reading the sender's link (the gateway's) for everyone.

On real Zenoh sessions on 127.0.0.1: the pump is held (it waits for the intake's lock), a
publisher puts ``INPUTS`` blocks (more than the old FIFO held), then a marker on another key of
the same link; the marker must arrive while the pump is still held (with the FIFO it did not
within 30 s), and once the pump runs again every input is handed over, once, in order; the
``"block"`` policy keeps its small FIFO for peer mode, where the back-pressure holds the
publisher back and loses nothing."""

from __future__ import annotations

import asyncio
import threading
from collections import Counter

import zenoh
from peer_pair import loop_and_two_peers, wait_until_routed

from sinewatch.runtime.intake import Intake, zenoh_side_channel
from sinewatch.schemas.config import SinewatchConfig

INPUTS = 3000  # past the FIFO a pump's batch of 256 had (512)
QUEUE = 65536  # the cluster daemons' queue (and so the FIFO): it holds every input here, none is dropped
WAIT_S = 30.0  # the longest a delivery may take on a loaded machine (a wait that ends when it is done)


class Host:
    """What an intake needs of its daemon: the config, the session, and a queue that is counted."""

    def __init__(self, session: zenoh.Session) -> None:
        self.config = SinewatchConfig.model_validate(
            {
                "daemon_id": "d1",
                "zenoh": {"recovery": False},
                "limits": {"queue_policy": "drop", "queue_capacity": QUEUE},
            }
        )
        self.session = session
        self.force_exit = threading.Event()
        self.pipeline = None
        self.intake: Intake | None = None
        self.seqs: list[int] = []
        self.drops: Counter[str] = Counter()
        self.got = threading.Condition()

    def enqueue(self, batch: list[tuple[str, bytes, str, int]]) -> None:
        assert self.intake is not None
        self.intake.release(len(batch))  # taken by the estimators at once: the queue never fills here
        with self.got:
            self.seqs += [int.from_bytes(payload[8:16], "little") for _, payload, _, _ in batch]
            self.got.notify_all()

    def report_drops(self, dropped: Counter[str]) -> None:
        self.drops.update(dropped)

    def report_unrecovered(self, key: str, n: int) -> None:
        raise AssertionError("no recovery here")


def test_a_dropping_intake_keeps_its_link_read_while_its_pump_is_held():
    with loop_and_two_peers() as (loop, publisher, daemon_session):
        marker = threading.Event()
        daemon_session.declare_subscriber("test/marker", lambda _: marker.set())
        host = Host(daemon_session)
        intake = host.intake = Intake(host, loop)  # type: ignore[arg-type]
        # both subscriptions known to the publisher first: a put sent before goes nowhere (a
        # loaded run lost its first inputs so, and waited for 3,000 that could never come)
        for key in ("sinewatch/in/ch0", "test/marker"):
            assert wait_until_routed(publisher, key, to_queryable=False, timeout=WAIT_S), key
        with intake._lock:  # the pump held, as a pump starved of the GIL is
            for seq in range(INPUTS):  # a binary block's header: its seq at bytes 8-16 (all the intake reads)
                block = b"SWSB\0\0\0\0" + seq.to_bytes(8, "little")
                publisher.put("sinewatch/in/ch0", block, congestion_control=zenoh.CongestionControl.BLOCK)
            publisher.put("test/marker", b"", congestion_control=zenoh.CongestionControl.BLOCK)
            arrived_while_held = marker.wait(WAIT_S)
        assert arrived_while_held
        with host.got:  # then every input, once each, in order
            assert host.got.wait_for(lambda: len(host.seqs) >= INPUTS, WAIT_S), (
                len(host.seqs),
                host.seqs[:5],
                host.seqs[-5:],
            )
        assert host.seqs == list(range(INPUTS)) and not host.drops
        asyncio.run_coroutine_threadsafe(intake.stop(), loop).result(WAIT_S)


def test_the_blocking_policy_keeps_a_small_fifo_that_holds_the_publisher_back():
    assert isinstance(zenoh_side_channel("block", 256, 8192), zenoh.handlers.FifoChannel)
    assert isinstance(zenoh_side_channel("drop", 256, 8192), zenoh.handlers.FifoChannel)
