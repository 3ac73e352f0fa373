"""Zenoh sessions from the config, with safe defaults; a client session to a daemon.

Zenoh's own defaults are wide open (a peer listens on every interface and scouts by
multicast); sinewatch always writes the endpoints and the scouting switch explicitly.
The daemon opens its session here too, so both ends share one way of configuring Zenoh.
"""

from __future__ import annotations

import json
import socket
from typing import Any

import zenoh

from sinewatch.schemas.config import DEFAULT_ENDPOINT, ZenohSection
from sinewatch.schemas.errors import ConfigError

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


#: Zenoh's connect/retry for every sinewatch session: 0.25 s, then doubling up to 1 s.
RECONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2.0}


#: How long a client's put with CongestionControl.BLOCK may wait for room before Zenoh closes
#: the client's link (``transport/link/tx/queue/congestion_control/block/wait_before_close``,
#: microseconds). Zenoh's 5 s is a router's own bound on a subscriber that takes nothing: a
#: router waiting that out for one stalled daemon stops reading its other links meanwhile, so
#: its publishers' puts waited as long, and with the same 5 s they closed their own links too,
#: losing every key's samples in flight to every subscriber (the gateway of the 50-fault chaos
#: run did, twice). A client's only link is its router's: it waits longer than the router
#: does; a router that is gone, not stalled, is found by the link's lease (10 s) all the same.
CLIENT_WAIT_BEFORE_CLOSE_US = 30_000_000
#: The same bound on a router (``sinewatch router``): 4 s, under the 10-s lease of the links it
#: reads. A router pushes a message on the task that reads the link it came from; waiting for a
#: subscriber that reads nothing, that task reads nothing more from the sender, whose link the
#: router then expires once a lease has passed without a message read from it (Zenoh's
#: ``read_loop``: the lease timer runs beside the push). With 15 s the router closed the
#: gateway's link instead of the stalled subscriber's (once in each of three 50-fault chaos runs:
#: the gateway's blocked put then held its queue's lock for its own 30 s, its link's sender
#: waiting on it, and no daemon had an input for 30 s). Under the lease, the router gives the
#: stalled subscriber up first, twice over if two pushes in a row wait. A daemon behind a router never stops reading its link on its own (its
#: intake's deep FIFO, its channels' rings: docs/cluster.md), so what a router closes is a daemon
#: stopped (SIGSTOP, a VM paused) or starved for seconds; it reconnects when it runs again.
ROUTER_WAIT_BEFORE_CLOSE_US = 4_000_000

#: The lease a client session announces (``transport/link/tx/lease``, ms): how long its router
#: may go without reading anything from the client's link before it expires the link. A router's
#: task that reads a link also pushes what came on it to the other sessions, and its lease timer
#: counts the time spent in those pushes: pushing a gateway's history replies to a new owner that
#: read them slowly (each push within the router's 4-s wait), a router read nothing more from the
#: gateway for over Zenoh's 10 s and expired the gateway's link, silently; the gateway's session,
#: its reading task blocked meanwhile in a reply of its own (zenoh-ext's cache answers a query on
#: that task, holding the cache's lock, which every put of the publisher then waits for), found
#: out only when that reply's 30-s wait ran out: no input reached any daemon for 30 s, three times
#: in two 50-fault chaos runs (stacks taken with gdb during the stall: the router idle, the
#: gateway's puts waiting for the cache's lock and the transport's, its reply waiting for room).
#: The router's own lease, what its clients expire its link by, stays Zenoh's 10 s: a router that
#: is gone is found as soon as before. `tests/test_cluster_router_stall.py -k keeps_the_link`.
CLIENT_LEASE_MS = 60_000
#: Keep-alives every lease / this: 2.5 s, as with Zenoh's defaults (10 s / 4).
CLIENT_KEEP_ALIVES_A_LEASE = 24

#: The daemons' input keys by default (``keys.input``): what ``sinewatch router`` forwards to
#: subscribers with ``CongestionControl.DROP`` (:func:`router_input_qos`).
DEFAULT_ROUTER_INPUTS = ["sinewatch/in/**"]


def router_input_qos(key_exprs: list[str]) -> list[dict[str, Any]]:
    """A router's ``qos/network`` rule: puts on ``key_exprs`` leave the router with
    ``CongestionControl.DROP``, whatever their publisher asked for (the publisher's own put to
    the router keeps its ``BLOCK``). A router pushes a ``BLOCK`` put to every matching
    subscriber in turn on the reading task of the publisher's link, so one subscriber that
    reads nothing (a daemon SIGSTOPped, paused by a VM, swapped out) stops that link for every
    key and every other subscriber until its queue frees or its link closes: a gateway's
    other shard and the stopped daemon's own successor got nothing for up to the link's lease
    (10 s), and per-shard key prefixes do not help, since one gateway link carries every
    shard's keys (docs/cluster.md, "A stopped daemon holds back no one"). With ``DROP`` the
    router drops what the full queue of that one subscriber cannot take, at once once it is
    congested, and goes on; a daemon that was only slow gets what it missed again from the
    publishers' caches (zenoh-ext's heartbeat recovery), and flags as a gap what is past them."""
    return [
        {
            "id": "sinewatch_inputs_drop",
            "messages": ["put"],
            "flows": ["egress"],
            "key_exprs": list(key_exprs),
            "overwrite": {"congestion_control": "drop"},
        }
    ]


def zenoh_config(section: ZenohSection) -> zenoh.Config:
    conf = zenoh.Config()
    _insert(conf, "mode", section.mode)
    _insert(conf, "listen/endpoints", section.listen)
    _insert(conf, "connect/endpoints", section.connect)
    _insert(conf, "scouting/multicast/enabled", section.multicast_scouting)
    if section.shared_memory is not None:
        _insert(conf, "transport/shared_memory/enabled", section.shared_memory)
    # A lost router is retried every second at most (Zenoh's default backs off to 4 s, and a
    # daemon and its feeder each waiting out their own back-off left estimation stopped for up
    # to 9.5 s after a router came back); `raw` can set its own
    _insert(conf, "connect/retry", RECONNECT_RETRY)
    wait = {"client": CLIENT_WAIT_BEFORE_CLOSE_US, "router": ROUTER_WAIT_BEFORE_CLOSE_US}.get(section.mode)
    if wait is not None:
        _insert(conf, "transport/link/tx/queue/congestion_control/block/wait_before_close", wait)
    if section.mode == "client":
        _insert(conf, "transport/link/tx/lease", CLIENT_LEASE_MS)
        _insert(conf, "transport/link/tx/keep_alive", CLIENT_KEEP_ALIVES_A_LEASE)
    for path, value in section.raw.items():
        _insert(conf, path, value)
    return conf


def _insert(conf: zenoh.Config, path: str, value: Any) -> None:
    try:
        conf.insert_json5(path, json.dumps(value))
    except Exception as exc:  # noqa: BLE001 (zenoh raises ZError or a plain exception, with the reason)
        raise ConfigError(f"zenoh config {path} = {value!r}: {exc}") from None


def open_session(section: ZenohSection) -> zenoh.Session:
    try:
        return zenoh.open(zenoh_config(section))
    except zenoh.ZError as exc:
        raise ConfigError(
            f"could not open the Zenoh session ({section.mode}, listen={section.listen}, "
            f"connect={section.connect}): {exc}"
        ) from None


def client_section(connect: list[str]) -> ZenohSection:
    """A client session that listens nowhere and connects to ``connect``."""
    return ZenohSection(mode="client", listen=[], connect=connect)


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for tests and the demo)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
