"""A client's link to its router survives the router stalling for longer than Zenoh's 5 s.

A router waits up to ``wait_before_close`` (Zenoh's default 5 s) to push to a subscriber that
takes nothing, and meanwhile stops reading its other links; a publisher's puts
(``CongestionControl.BLOCK``) then wait as long. With Zenoh's 5 s on the publisher too, the
publisher closed its own link to the router and every key's samples in flight were lost, to
every subscriber (the gateway of the 50-fault chaos run, twice, its router stalled on
a daemon it then cut off). sinewatch gives a client session 30 s
(:data:`sinewatch.clients.session.CLIENT_WAIT_BEFORE_CLOSE_US`): here the router itself is
stopped (SIGSTOP) for 7 s while a client publishes as fast as it can, and a second client must
receive every sample, in order.
"""

from __future__ import annotations

import signal
import threading
import time

import pytest
import zenoh
from cluster_procs import Router

from sinewatch.clients.session import client_section, open_session

STALL_S = 7.0  # longer than Zenoh's 5 s, shorter than the links' lease (10 s): a stalled router, not a dead one
PAYLOAD = 8192


def publish_through_a_stalled_router(tmp_path, raw: dict[str, int]) -> tuple[int, list[int]]:
    router = Router(tmp_path)
    router.start()
    endpoint = [f"tcp/127.0.0.1:{router.port}"]
    got: list[int] = []
    cond = threading.Condition()

    def on(sample: zenoh.Sample) -> None:
        with cond:
            got.append(int.from_bytes(sample.payload.to_bytes()[:8], "little"))
            cond.notify_all()

    section = client_section(endpoint)
    section.raw.update(raw)
    try:
        with open_session(client_section(endpoint)) as sub_session, open_session(section) as pub_session:
            sub = sub_session.declare_subscriber("stall/test", on)
            pub = pub_session.declare_publisher("stall/test", congestion_control=zenoh.CongestionControl.BLOCK)
            matched = threading.Event()  # the subscriber's declaration reached the publisher through the router
            listener = pub.declare_matching_listener(lambda status: status.matching and matched.set())
            assert matched.wait(30)
            listener.undeclare()
            sent = 0
            assert router.proc is not None
            router.proc.send_signal(signal.SIGSTOP)
            stalled = time.monotonic()
            threading.Timer(STALL_S, _cont, (router,)).start()  # a thread: the puts below block meanwhile
            while time.monotonic() < stalled + STALL_S + 0.5:  # past the resumption: the link still carries
                pub.put(sent.to_bytes(8, "little") + bytes(PAYLOAD - 8))
                sent += 1
            with cond:
                cond.wait_for(lambda: bool(got) and got[-1] == sent - 1, timeout=30)
            sub.undeclare()
    finally:
        router.kill()
    return sent, got


def _cont(router: Router) -> None:
    if router.proc is not None and router.proc.poll() is None:
        router.proc.send_signal(signal.SIGCONT)


def test_a_publisher_waits_out_a_stalled_router_and_nothing_is_lost(tmp_path):
    sent, got = publish_through_a_stalled_router(tmp_path, {})
    print(f"{sent} samples put, {len(got)} received")
    assert got == list(range(sent))


@pytest.mark.slow
def test_with_zenoh_s_5_s_the_publisher_closes_its_own_link_and_samples_are_lost(tmp_path):
    """The same with Zenoh's default on the publisher: what the test above guards against."""
    sent, got = publish_through_a_stalled_router(
        tmp_path, {"transport/link/tx/queue/congestion_control/block/wait_before_close": 5_000_000}
    )
    print(f"{sent} samples put, {len(got)} received")
    assert len(got) < sent
