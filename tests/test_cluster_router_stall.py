"""A client's link to its router survives the router stalling for longer than Zenoh's 5 s.

A router waits up to ``wait_before_close`` (Zenoh's default 5 s) to push to a subscriber that
takes nothing, and meanwhile stops reading its other links; a publisher's puts
(``CongestionControl.BLOCK``) then wait as long. With Zenoh's 5 s on the publisher too, the
publisher closed its own link to the router and every key's samples in flight were lost, to
every subscriber (the gateway of the 50-fault chaos run, twice, its router stalled on
a daemon it then cut off). sinewatch gives a client session 30 s
(:data:`sinewatch.clients.session.CLIENT_WAIT_BEFORE_CLOSE_US`): here the router itself is
stopped (SIGSTOP) for 7 s while a client publishes, and a second client must receive every
sample, in order.

Only ``wait_before_close`` is under test, not Zenoh's lease: every session here (the router's
and the clients') announces a lease of 60 s instead of 10 s. With 10 s, a client that had heard
nothing from the router for 3 s before the stop (its last keep-alive can be 2.5 s old) found
the router's link expired before the resumed router spoke again, on a loaded machine, and
reconnected: the samples put during the stall were lost to it, the later ones arrived.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np
import pytest
import zenoh
from cluster_procs import Router

from sinewatch.clients import BlockPublisher
from sinewatch.clients.session import client_section, open_session
from sinewatch.schemas.config import ZenohSection

STALL_S = 7.0  # longer than Zenoh's default wait_before_close: a stalled router or subscriber, not a dead one
# A lease (ms) far beyond the stall and a loaded machine's resumption; keep-alives every 2.5 s
# (lease / keep_alive) as with Zenoh's defaults, so that only the lease differs from a daemon's link
LEASE = {"transport/link/tx/lease": 60_000, "transport/link/tx/keep_alive": 24}
AFTER = 100  # samples put once the stopped process runs again: the link still carries them
PAYLOAD = 8192  # 8-KB samples fill the sockets' and Zenoh's queues (a few MB) within the first ~500 puts
WAIT_S = 60.0  # the longest a delivery may take on a loaded machine (a wait that ends when it is done)


def long_lease_client(endpoint: list[str], raw: dict[str, Any] | None = None) -> ZenohSection:
    section = client_section(endpoint)
    section.raw.update({**LEASE, **(raw or {})})
    return section


def resume_after(proc: subprocess.Popen[Any], resumed: threading.Event) -> None:
    """SIGCONT to ``proc`` after ``STALL_S`` (a timer thread: the puts block meanwhile)."""

    def cont() -> None:
        if proc.poll() is None:
            proc.send_signal(signal.SIGCONT)
        resumed.set()

    threading.Timer(STALL_S, cont).start()


def put_until_after(pub: zenoh.Publisher, resumed: threading.Event) -> tuple[int, float]:
    """Numbered samples until ``resumed`` is set and ``AFTER`` more; how many, and the longest
    a put waited (seconds)."""
    sent, after, longest = 0, 0, 0.0
    while after < AFTER:
        was_resumed = resumed.is_set()
        began = time.monotonic()
        pub.put(sent.to_bytes(8, "little") + bytes(PAYLOAD - 8))
        longest = max(longest, time.monotonic() - began)
        sent += 1
        after += was_resumed
    return sent, longest


def losses(got: list[int], sent: int) -> str:
    """'' when ``got`` is every sample 0..sent-1 once, in order; else what is wrong, briefly
    (a list diff of ~600 numbers says less)."""
    if got == list(range(sent)):
        return ""
    missing = sorted(set(range(sent)) - set(got))
    runs: list[list[int]] = []
    for m in missing:
        if runs and runs[-1][1] == m - 1:
            runs[-1][1] = m
        else:
            runs.append([m, m])
    disorder = next((i for i in range(1, len(got)) if got[i] <= got[i - 1]), None)
    return (
        f"{len(got)} of {sent} received; {len(missing)} missing in runs {[tuple(r) for r in runs[:10]]}; "
        f"{len(got) - len(set(got))} duplicates; first out of order at index {disorder}"
    )


def numbered_samples() -> tuple[list[int], threading.Condition, Any]:
    """(the numbers received so far, a condition notified at each, the subscriber's callback)."""
    got: list[int] = []
    cond = threading.Condition()

    def on(sample: zenoh.Sample) -> None:
        with cond:
            got.append(int.from_bytes(sample.payload.to_bytes()[:8], "little"))
            cond.notify_all()

    return got, cond, on


def publish_through_a_stalled_router(tmp_path, raw: dict[str, int]) -> tuple[int, list[int], float]:
    router = Router(tmp_path, LEASE)
    router.start()
    endpoint = [f"tcp/127.0.0.1:{router.port}"]
    got, cond, on = numbered_samples()
    try:
        with (
            open_session(long_lease_client(endpoint)) as sub_session,
            open_session(long_lease_client(endpoint, raw)) as pub_session,
        ):
            sub = sub_session.declare_subscriber("stall/test", on)
            pub = pub_session.declare_publisher("stall/test", congestion_control=zenoh.CongestionControl.BLOCK)
            matched = threading.Event()  # the subscriber's declaration reached the publisher through the router
            listener = pub.declare_matching_listener(lambda status: status.matching and matched.set())
            assert matched.wait(WAIT_S)
            listener.undeclare()
            assert router.proc is not None
            resumed = threading.Event()
            router.proc.send_signal(signal.SIGSTOP)
            resume_after(router.proc, resumed)
            sent, longest = put_until_after(pub, resumed)
            with cond:
                cond.wait_for(lambda: bool(got) and got[-1] == sent - 1, timeout=WAIT_S)
            sub.undeclare()
    finally:
        router.kill()
    return sent, got, longest


def test_a_publisher_waits_out_a_stalled_router_and_nothing_is_lost(tmp_path):
    sent, got, longest = publish_through_a_stalled_router(tmp_path, {})
    # how long a put waited (~7 s) is printed, not asserted: a timed assertion fails on a loaded
    # machine; that the test catches a publisher giving up after 5 s is the slow test below
    print(f"{sent} samples put, {len(got)} received; the longest put waited {longest:.1f} s")
    assert losses(got, sent) == ""


@pytest.mark.slow
def test_with_zenoh_s_5_s_the_publisher_closes_its_own_link_and_samples_are_lost(tmp_path):
    """The same with Zenoh's default on the publisher: what the test above guards against."""
    sent, got, _ = publish_through_a_stalled_router(
        tmp_path, {"transport/link/tx/queue/congestion_control/block/wait_before_close": 5_000_000}
    )
    print(f"{sent} samples put, {len(got)} received")
    assert len(got) < sent


SUBSCRIBER = """
import json, sys, threading
from sinewatch.clients.session import client_section, open_session
seqs, cond = [], threading.Condition()
def on(sample):
    with cond:
        seqs.append(int.from_bytes(sample.payload.to_bytes()[:8], "little"))
        cond.notify_all()
section = client_section([sys.argv[1]])
section.raw.update(json.loads(sys.argv[2]))
with open_session(section) as session:
    sub = session.declare_subscriber("stall/test", on)
    print("ready", flush=True)
    n = int(sys.stdin.readline())  # the samples put: report once they are all here, or after the wait
    with cond:
        cond.wait_for(lambda: len(seqs) >= n, timeout=float(sys.argv[3]))
        print(len(seqs), seqs == list(range(len(seqs))), flush=True)
"""


PAST_LEASE_S = 14.0  # a subscriber stopped longer than Zenoh's 10-s lease of the publisher's link


@pytest.mark.slow
def test_a_router_gives_up_a_stopped_subscriber_before_the_publishers_link_expires(tmp_path):
    """The router's side: a subscriber that reads nothing (its process stopped, as the chaos test's
    paused owner is) for longer than the lease of the publisher's link. The router pushes the
    publisher's ``BLOCK`` puts on the task that reads the publisher's link, and Zenoh expires a link
    it has read nothing from for a lease (10 s), whatever kept it from reading: with a router that
    waited 15 s for the stopped subscriber, the publisher's link expired first, and every sample in
    flight was lost, to every subscriber (the gateway's link, in 50-fault chaos runs). ``sinewatch
    router`` waits 4 s (:data:`sinewatch.clients.session.ROUTER_WAIT_BEFORE_CLOSE_US`): it closes
    the stopped subscriber's link instead, and the other subscriber gets every sample, in order.
    Every session here has Zenoh's 10-s lease. Slow (``make test-slow``): the stop outlasts the lease."""
    router = Router(tmp_path)
    router.start()
    endpoint = [f"tcp/127.0.0.1:{router.port}"]
    sub = subprocess.Popen(
        [sys.executable, "-c", SUBSCRIBER, endpoint[0], "{}", "5"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    got, cond, on = numbered_samples()
    try:
        assert sub.stdout is not None and sub.stdin is not None and sub.stdout.readline().strip() == "ready"
        with (
            open_session(client_section(endpoint)) as other_session,
            open_session(client_section(endpoint)) as session,
        ):
            other_session.declare_subscriber("stall/test", on)
            pub = session.declare_publisher("stall/test", congestion_control=zenoh.CongestionControl.BLOCK)
            matched = threading.Event()
            listener = pub.declare_matching_listener(lambda status: status.matching and matched.set())
            assert matched.wait(WAIT_S)
            listener.undeclare()
            resumed = threading.Event()
            sub.send_signal(signal.SIGSTOP)
            threading.Timer(PAST_LEASE_S, lambda: (sub.send_signal(signal.SIGCONT), resumed.set())).start()
            sent, longest = put_until_after(pub, resumed)
            with cond:
                cond.wait_for(lambda: bool(got) and got[-1] == sent - 1, timeout=WAIT_S)
            sub.stdin.write(f"{sent}\n")
            sub.stdin.flush()
            count, _ = sub.stdout.readline().split()
    finally:
        sub.send_signal(signal.SIGCONT)
        sub.kill()
        sub.wait()
        router.kill()
    print(
        f"{sent} put; the other subscriber got {len(got)}, the one stopped {PAST_LEASE_S} s {count}; longest put {longest:.1f} s"
    )
    assert losses(got, sent) == ""
    assert int(count) < sent  # the router gave the stopped subscriber up rather than wait for it


STOPPED = """
import json, sys, threading
from sinewatch.clients.session import client_section, open_session
got = threading.Event()
section = client_section([sys.argv[1]])
section.raw.update(json.loads(sys.argv[2]))
with open_session(section) as session:
    sub = session.declare_subscriber(sys.argv[3], lambda sample: got.set())
    got.wait()
    print("ready", flush=True)  # it has a sample: the router forwards to it
    threading.Event().wait()  # stopped and killed by the test
"""
INPUTS = "sinewatch/in/**"  # `sinewatch router`'s default input keys
STOPPED_N = 8_000  # 8-KB samples put while one subscriber is stopped: 64 MB, far beyond the sockets' buffers


def other_subscriber_while_one_is_stopped(
    tmp_path, router_raw: dict[str, Any], shards: bool = False
) -> tuple[bool, int, float]:
    """Two subscribers of ``sinewatch/in/**`` through ``sinewatch router``, one of them a process
    SIGSTOPped; a publisher puts ``STOPPED_N`` samples with ``CongestionControl.BLOCK``, then a
    marker on a key outside the inputs (which the router forwards as published, never dropped).
    Whether the other subscriber got the marker while the stopped one was still stopped (the
    router neither closes the stopped one's link nor gives up on it meanwhile: a 60-s lease, a
    120-s ``wait_before_close``), how many samples it got, and the longest a put waited. The
    samples it got are printed, not asserted: the router drops to it too what its own queue
    cannot take when the puts outrun it (a daemon gets those again from the publishers' caches).
    ``shards``: per-shard key prefixes, the stopped subscriber on ``sinewatch/in/1/**``, the other on
    ``sinewatch/in/2/**``, the publisher's puts alternating between the two."""
    router = Router(
        tmp_path,
        {**LEASE, "transport/link/tx/queue/congestion_control/block/wait_before_close": 120_000_000, **router_raw},
    )
    router.start()
    endpoint = [f"tcp/127.0.0.1:{router.port}"]
    stopped = subprocess.Popen(
        [sys.executable, "-c", STOPPED, endpoint[0], json.dumps(LEASE), "sinewatch/in/1/**" if shards else INPUTS],
        stdout=subprocess.PIPE,
        text=True,
    )
    got: list[int] = []
    marker = threading.Event()
    longest = [0.0]
    try:
        with (
            open_session(long_lease_client(endpoint)) as sub_session,
            open_session(long_lease_client(endpoint)) as pub_session,
        ):
            sub_session.declare_subscriber(
                "sinewatch/in/2/**" if shards else INPUTS,
                lambda s: got.append(int.from_bytes(s.payload.to_bytes()[:8], "little")),
            )
            sub_session.declare_subscriber("stall/end", lambda s: marker.set())
            keys = ["sinewatch/in/1/ch", "sinewatch/in/2/ch"] if shards else ["sinewatch/in/ch"]
            pubs = [pub_session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k in keys]
            ready = threading.Event()  # both subscribers' declarations have reached the router
            threading.Thread(target=lambda: stopped.stdout and stopped.stdout.readline() and ready.set()).start()
            while not (ready.wait(0.05) and got):  # a warm-up sample every 50 ms until both have one
                for pub in pubs:
                    pub.put((2**63).to_bytes(8, "little"))
            stopped.send_signal(signal.SIGSTOP)
            got.clear()

            def put_all() -> None:
                for n in range(STOPPED_N * len(pubs)):  # STOPPED_N to each shard's keys
                    began = time.monotonic()
                    pubs[n % len(pubs)].put(n.to_bytes(8, "little") + bytes(PAYLOAD - 8))
                    longest[0] = max(longest[0], time.monotonic() - began)
                pub_session.put("stall/end", b"", congestion_control=zenoh.CongestionControl.BLOCK)

            putter = threading.Thread(target=put_all)
            putter.start()
            delivered = marker.wait(40.0)  # not reached with the drop rule: the marker comes within seconds
            received = len(got)
            stopped.send_signal(signal.SIGCONT)  # the router then delivers the rest: the putter ends
            putter.join()
    finally:
        stopped.send_signal(signal.SIGCONT)
        stopped.kill()
        stopped.wait()
        router.kill()
    return delivered, received, longest[0]


@pytest.mark.slow
def test_a_stopped_subscriber_of_the_inputs_holds_back_no_other(tmp_path):
    """``sinewatch router`` forwards the inputs with ``CongestionControl.DROP``
    (:func:`sinewatch.clients.session.router_input_qos`): a daemon that reads nothing (SIGSTOP)
    loses what its queue cannot hold, and its successor, reading the same keys, is served
    meanwhile. Slow: a subscriber's process and 64 MB through a router."""
    delivered, received, longest = other_subscriber_while_one_is_stopped(tmp_path, {})
    print(
        f"marker {delivered}; {received} of {STOPPED_N} received while the other was stopped; longest put {longest:.2f} s"
    )
    assert delivered


@pytest.mark.slow
def test_without_the_drop_rule_a_stopped_subscriber_holds_back_the_other(tmp_path):
    """The same with the router forwarding as published (``BLOCK``): what the test above guards
    against. The router pushes each put to each subscriber in turn on the publisher link's
    reading task, so once the stopped one's queue is full nobody gets anything, whatever the key."""
    delivered, received, longest = other_subscriber_while_one_is_stopped(tmp_path, {"qos/network": []})
    print(
        f"marker {delivered}; {received} of {STOPPED_N} received while the other was stopped; longest put {longest:.2f} s"
    )
    assert not delivered


@pytest.mark.slow
def test_per_shard_key_prefixes_alone_do_not_keep_a_stopped_subscriber_from_holding_back_the_other(tmp_path):
    """Without the drop rule, a stopped subscriber of shard 1's keys holds back the subscriber of
    shard 2's keys all the same: one publisher's link carries both shards' keys, and the router
    stops reading it while it waits to push shard 1's puts. Why the router's rule, not key
    prefixes, is the fix."""
    delivered, received, longest = other_subscriber_while_one_is_stopped(tmp_path, {"qos/network": []}, shards=True)
    print(
        f"marker {delivered}; {received} of {STOPPED_N} received while the other was stopped; longest put {longest:.2f} s"
    )
    assert not delivered


QUERIER = """
import json, os, signal, sys, threading
import zenoh
from sinewatch.clients.session import client_section, open_session
section = client_section([sys.argv[1]])
section.raw.update(json.loads(sys.argv[2]))
congestion = getattr(zenoh.CongestionControl, sys.argv[3])
with open_session(section) as session:
    session.get(  # shaped as zenoh-ext's recovery queries (one publisher's cache), on every key's cache
        "sinewatch/in/**/@adv/*/*/*/**",
        lambda reply: os.kill(os.getpid(), signal.SIGSTOP),  # stopped by its first reply, the rest on their way
        consolidation=zenoh.ConsolidationMode.NONE,
        accept_replies=zenoh.ReplyKeyExpr.ANY,
        timeout=600.0,
        congestion_control=congestion,
    )
    threading.Event().wait()  # continued and killed by the test
"""
CACHED_KEYS = 8  # channels whose caches answer the stopped querier
CACHED_N = 1024  # blocks in each cache (BlockPublisher's default history): 8 x 1,024 x 8 KB = 64 MB of replies
LIVE_N = 4_000  # 8-KB samples put on another key while the querier is stopped: they go out beside the replies


def other_subscriber_while_a_querier_is_stopped(tmp_path, query: str) -> tuple[bool, int]:
    """The caches of a publisher (:class:`~sinewatch.clients.BlockPublisher`, ``CACHED_KEYS``
    keys of ``CACHED_N`` 8-KB blocks) answer a history query from a process that SIGSTOPs itself
    on its first reply (stopped by the test instead, it had taken every reply before the signal
    came); the same session then puts ``LIVE_N`` samples on a key outside the inputs, as many
    bytes as the replies' first half (100 small puts went out before the stopped querier's queue
    was full), and a marker. Whether a second subscriber got the marker while the querier was
    still stopped, and how many of the live puts. The router never gives up on the stopped
    querier during the test (60-s leases, 120-s ``wait_before_close``), nor does the publisher on
    the router (120 s). ``query``: the query's congestion control (zenoh-ext's recovery queries
    go with Zenoh's default, ``BLOCK``), its key shaped as theirs; the router is ``sinewatch router``
    with its inputs' rule."""
    # shared memory off: the replies' bytes go through the sockets, as between hosts (Zenoh passes payloads of
    # 3 KB and more between processes of one host through shared memory by default)
    wait = {
        "transport/link/tx/queue/congestion_control/block/wait_before_close": 120_000_000,
        "transport/shared_memory/enabled": False,
    }
    router = Router(tmp_path, {**LEASE, **wait})
    router.start()
    endpoint = [f"tcp/127.0.0.1:{router.port}"]
    live: list[int] = []
    marker = threading.Event()
    querier: subprocess.Popen[str] | None = None
    try:
        with (
            open_session(long_lease_client(endpoint)) as sub_session,
            open_session(long_lease_client(endpoint, wait)) as pub_session,
        ):
            sub_session.declare_subscriber("stall/live", lambda s: live.append(1))
            sub_session.declare_subscriber("stall/end", lambda s: marker.set())
            publisher = BlockPublisher(pub_session, history=CACHED_N)
            block = np.zeros(PAYLOAD // 4, dtype=np.float32)
            for n in range(CACHED_KEYS * CACHED_N):
                publisher.publish(f"cached{n % CACHED_KEYS}", block, 1000.0)
            querier = subprocess.Popen(
                [sys.executable, "-c", QUERIER, endpoint[0], json.dumps({**LEASE, **wait}), query]
            )
            _, status = os.waitpid(querier.pid, os.WUNTRACED)  # until it has stopped on its first reply
            assert os.WIFSTOPPED(status), status

            def put_live() -> None:
                for n in range(LIVE_N):  # outside the inputs: the router forwards them as put, never dropped
                    payload = n.to_bytes(8, "little") + bytes(PAYLOAD - 8)
                    pub_session.put("stall/live", payload, congestion_control=zenoh.CongestionControl.BLOCK)
                pub_session.put("stall/end", b"", congestion_control=zenoh.CongestionControl.BLOCK)

            putter = threading.Thread(target=put_live)
            putter.start()
            delivered = marker.wait(40.0)  # not stalled, it comes within seconds
            received = len(live)
            querier.send_signal(signal.SIGCONT)  # the router then delivers the rest: the putter ends
            putter.join()
            publisher.close()
    finally:
        end_stopped(querier, router)
    return delivered, received


def end_stopped(proc: subprocess.Popen[str] | None, router: Router) -> None:
    """A test's stopped (or running) helper process continued and killed, then its router."""
    if proc is not None:
        proc.send_signal(signal.SIGCONT)
        proc.kill()
        proc.wait()
    router.kill()


@pytest.mark.slow
def test_a_stopped_querier_of_the_caches_holds_back_the_gateway_s_other_keys(tmp_path):
    """Not fixed, shown: a query shaped as zenoh-ext's recovery queries (Zenoh's default, ``BLOCK``)
    from a process that stops reading while the caches answer it. The router pushes each reply to
    the querier with the query's ``BLOCK`` (it replaces a reply's QoS with the query's, whatever
    the caches' ``RepliesConfig``), on the task that reads the publisher's link, so once the
    stopped querier's queue is full nothing of that publisher reaches anyone. A router rule making
    these queries ``DROP`` as they come in lets the marker through (4,000 of 4,000 live puts), but
    a router restart's burst of recovery queries then waited out their 10 s (a daemon's "could not
    be recovered" 10.1 s after the router's return): the failover test's router restart served every channel again after 10.4 s, not
    within 5 s (docs/cluster.md, "A querier that reads nothing")."""
    delivered, received = other_subscriber_while_a_querier_is_stopped(tmp_path, "BLOCK")
    print(f"marker {delivered}; {received} of {LIVE_N} live puts received while the querier was stopped")
    assert not delivered


LEASE_HOLDER = """
import json, sys, threading
from sinewatch.clients.session import client_section, open_session
section = client_section([sys.argv[1]])
section.raw.update(json.loads(sys.argv[2]))
with open_session(section) as session:
    token = session.liveliness().declare_token("stall/alive")
    print("ready", flush=True)
    threading.Event().wait()  # stopped, continued and killed by the test
"""
QUIET_S = 14.0  # a client the router hears nothing from for longer than Zenoh's 10-s lease


def router_keeps_a_silent_clients_link(tmp_path, raw: dict[str, Any]) -> bool:
    """A client process (its session as sinewatch opens one, plus ``raw``) declares a liveliness
    token through ``sinewatch router``, then is stopped (SIGSTOP) for ``QUIET_S``: the router reads
    nothing from its link meanwhile, and nothing is pushed to it (no ``wait_before_close`` comes
    into it). Whether the router kept the link: no deletion of the token seen by another client."""
    router = Router(tmp_path)
    router.start()
    endpoint = f"tcp/127.0.0.1:{router.port}"
    holder: subprocess.Popen[str] | None = None
    alive, gone = threading.Event(), threading.Event()

    def on_token(sample: zenoh.Sample) -> None:
        (alive if sample.kind == zenoh.SampleKind.PUT else gone).set()

    try:
        with open_session(client_section([endpoint])) as watcher:
            watcher.liveliness().declare_subscriber("stall/alive", on_token, history=True)
            holder = subprocess.Popen(
                [sys.executable, "-c", LEASE_HOLDER, endpoint, json.dumps(raw)], stdout=subprocess.PIPE, text=True
            )
            assert holder.stdout is not None and holder.stdout.readline().strip() == "ready"
            assert alive.wait(WAIT_S)
            holder.send_signal(signal.SIGSTOP)
            kept = not gone.wait(QUIET_S)  # the link's expiry would end the token within the stop
            holder.send_signal(signal.SIGCONT)
    finally:
        end_stopped(holder, router)
    return kept


@pytest.mark.slow
def test_a_router_keeps_the_link_of_a_client_it_has_not_heard_from_for_zenoh_s_lease(tmp_path):
    """A client announces a lease of ``CLIENT_LEASE_MS`` (60 s): how long its router may go without
    reading anything from its link before expiring it. A router's read task of a link is the one
    that pushes what came on it to the other sessions; pushing a gateway's history replies to a new
    owner that reads them slowly (each push within the router's 4-s ``wait_before_close``), it read
    nothing more from the gateway for over 10 s, and then, with Zenoh's 10-s lease, expired the
    gateway's link, silently, while the gateway's session, its reading task blocked in a reply of
    its own, found out only when that reply's 30-s wait ran out: no input reached any daemon for 30
    s, twice in a 50-fault chaos run (stacks in docs/cluster.md). Shown here with the client
    stopped, the router idle: kept with the 60-s lease; expired with Zenoh's 10 s."""
    assert router_keeps_a_silent_clients_link(tmp_path, {})
    zenoh_default = {"transport/link/tx/lease": 10_000, "transport/link/tx/keep_alive": 4}
    assert not router_keeps_a_silent_clients_link(tmp_path, zenoh_default)
