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


SUBSCRIBER = """
import sys, threading
from sinewatch.clients.session import client_section, open_session
seqs, cond = [], threading.Condition()
def on(sample):
    with cond:
        seqs.append(int.from_bytes(sample.payload.to_bytes()[:8], "little"))
        cond.notify_all()
with open_session(client_section([sys.argv[1]])) as session:
    sub = session.declare_subscriber("stall/test", on)
    print("ready", flush=True)
    n = int(sys.stdin.readline())  # the samples put: report once they are all here, or after 30 s
    with cond:
        cond.wait_for(lambda: len(seqs) >= n, timeout=30)
        print(len(seqs), seqs == list(range(len(seqs))), flush=True)
"""


def test_a_router_waits_for_a_subscriber_that_reads_nothing_for_7_s(tmp_path):
    """The router's side: a subscriber that reads nothing for 7 s (here its process is stopped;
    a daemon catching up after a takeover on a loaded machine did the same) keeps its link, and
    gets every sample once it reads again, the publisher held back meanwhile. With Zenoh's 5 s
    the router closed that daemon's link and what was queued to it was lost."""
    import subprocess
    import sys

    router = Router(tmp_path)
    router.start()
    endpoint = [f"tcp/127.0.0.1:{router.port}"]
    sub = subprocess.Popen(
        [sys.executable, "-c", SUBSCRIBER, endpoint[0]], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert sub.stdout is not None and sub.stdin is not None and sub.stdout.readline().strip() == "ready"
        with open_session(client_section(endpoint)) as session:
            pub = session.declare_publisher("stall/test", congestion_control=zenoh.CongestionControl.BLOCK)
            matched = threading.Event()
            listener = pub.declare_matching_listener(lambda status: status.matching and matched.set())
            assert matched.wait(30)
            listener.undeclare()
            sub.send_signal(signal.SIGSTOP)
            stopped = time.monotonic()
            threading.Timer(STALL_S, sub.send_signal, (signal.SIGCONT,)).start()  # the puts below block meanwhile
            sent = 0
            while time.monotonic() < stopped + STALL_S + 0.5:
                pub.put(sent.to_bytes(8, "little") + bytes(PAYLOAD - 8))
                sent += 1
            sub.stdin.write(f"{sent}\n")
            sub.stdin.flush()
            count, in_order = sub.stdout.readline().split()
    finally:
        sub.send_signal(signal.SIGCONT)
        sub.kill()
        sub.wait()
        router.kill()
    print(f"{sent} samples put, {count} received by the subscriber stopped {STALL_S} s")
    assert int(count) == sent and in_order == "True"
