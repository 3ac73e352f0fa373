"""The TLS router's access control denies by default: per role, per key space, per action.

A real Zenoh router process runs ``deploy/zenoh-router-tls.json5`` with the certificates of
``deploy/tls/make-certs.sh``; each role (gateway, sinewatch-daemon, reader, and the router's
own certificate, a Common Name from the CA that no rule lists) opens its own Zenoh session
over mutual TLS on 127.0.0.1 and tries each action on each key space sinewatch uses: put,
subscribe, liveliness tokens, queryables, queries, liveliness queries, and Zenoh's admin
space. What the configuration's table grants must arrive; everything else must not.

How absence is shown without waiting on a clock: a Zenoh router handles one link's messages
in order, and a query answered by the router (here one nobody serves) comes back only after
everything the session sent before it was routed; the watching session then does the same,
so whatever the router forwarded to it is already in its queue (``barrier``).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import queue
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import zenoh
from cluster_procs import Etcd, config_head, start_daemon
from conftest import TIMEOUT
from test_deploy import certs, secure_router, tls_section  # noqa: F401 (certs is a fixture)

from sinewatch.clients import BlockPublisher
from sinewatch.clients.session import free_loopback_port, open_session

DAEMON, GATEWAY, READER, UNLISTED = "sinewatch-daemon", "gateway", "reader", "router"
ROLES = [GATEWAY, DAEMON, READER, UNLISTED]

#: one key per key space, as the daemon and its clients use them
SPACES = {
    "in": "sinewatch/in/acl/a",
    "est": "sinewatch/est/acl/a",
    "err": "sinewatch/err/acl/a",
    "status": "sinewatch/status/acl",
    "pq": "sinewatch/pq/harmonics/acl/a",
    "admin-snapshot": "sinewatch/admin/shard/acl/snapshot",
}
MAY_PUT = {"in": {GATEWAY}, "admin-snapshot": {DAEMON}} | {s: {DAEMON} for s in ("est", "err", "status", "pq")}
MAY_READ = {
    "in": {DAEMON},
    "est": {DAEMON, READER},  # a standby daemon notes what the active one published
    "err": {READER},
    "status": {READER},
    "pq": {READER},
    "admin-snapshot": {DAEMON},
}
ACTIVE = "sinewatch/admin/shard/acl/active"
OWN_ADMIN = "sinewatch/admin/acl-daemon/channels"  # a daemon's own admin queryable
BARRIER_KEY = "sinewatch/acl-barrier"  # nobody serves it and no rule grants it: the router answers

_serial = itertools.count()


def barrier(*sessions: zenoh.Session) -> None:
    """Each session's earlier messages have been routed and what was routed to it is queued."""
    for s in sessions:
        list(s.get(BARRIER_KEY, timeout=TIMEOUT))


@dataclass
class Net:
    sessions: dict[str, zenoh.Session]
    watch_daemon: zenoh.Session  # a second daemon: sees in/**, admin/**, the shard's tokens
    watch_reader: zenoh.Session  # a second reader: sees est/err/status/pq
    second_gateway: zenoh.Session
    watchers: dict[str, Inbox] = field(default_factory=dict)  # space -> what a watcher received

    def watcher_session(self, space: str) -> zenoh.Session:
        return self.watch_daemon if space in ("in", "admin-snapshot") else self.watch_reader

    def writer(self, space: str) -> zenoh.Session:
        """A session allowed to put on ``space`` other than the ones tested (Zenoh delivers
        a session's own puts to its own subscribers without asking the router)."""
        return self.second_gateway if space == "in" else self.watch_daemon


class Inbox:
    """A subscriber whose samples' payloads land in a queue."""

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self.queue: queue.Queue[bytes] = queue.Queue()
        self.sub = session.declare_subscriber(key_expr, lambda s: self.queue.put(s.payload.to_bytes()))

    def undeclare(self) -> None:
        self.sub.undeclare()


def drain(inbox: Inbox) -> list[bytes]:
    got = []
    with contextlib.suppress(queue.Empty):
        while True:
            got.append(inbox.queue.get_nowait())
    return got


def wait_for(inbox: Inbox, payload: bytes) -> bool:
    """True once ``payload`` arrives (other messages are passed over); False after TIMEOUT,
    a guard for a loaded machine."""
    while True:
        try:
            if inbox.queue.get(timeout=TIMEOUT) == payload:
                return True
        except queue.Empty:
            return False


@pytest.fixture(scope="module")
def net(certs) -> Iterator[Net]:  # noqa: F811
    port = free_loopback_port()
    endpoint = f"tls/127.0.0.1:{port}"
    with secure_router(certs, port):
        opened = {role: open_session(tls_section(certs, role, endpoint)) for role in ROLES}
        wd = open_session(tls_section(certs, DAEMON, endpoint))
        wr = open_session(tls_section(certs, READER, endpoint))
        n = Net(opened, wd, wr, open_session(tls_section(certs, GATEWAY, endpoint)))
        try:
            for space, key in SPACES.items():
                n.watchers[space] = Inbox(n.watcher_session(space), key.rsplit("/", 1)[0] + "/**")
            # a daemon's admin queryable and standby token, for the query checks
            wd.declare_queryable(OWN_ADMIN, lambda q: q.reply(OWN_ADMIN, b"{}"))
            token = wd.liveliness().declare_token("sinewatch/admin/shard/acl/standby/acl-daemon")
            # every watcher's subscription is known to the router and to each writer: the
            # watcher's barrier returns once the router has routed its declaration (and sent it
            # on to the writer's link); the writer's, once that declaration is in the writer's
            # hands. A put before then can be dropped as having no subscriber.
            for space in SPACES:
                barrier(n.watcher_session(space), n.writer(space))
                payload = f"ready-{space}".encode()
                n.writer(space).put(SPACES[space], payload)
                assert wait_for(n.watchers[space], payload), f"the {space} watcher never saw its writer"
            yield n
            token.undeclare()
        finally:
            for s in [*opened.values(), wd, wr, n.second_gateway]:
                s.close()


@pytest.mark.parametrize("space", list(SPACES))
@pytest.mark.parametrize("role", ROLES)
def test_put(net, role, space):
    """Only the space's writer may put on it: a forged estimate, input, error, status, power-
    quality report or shard snapshot from anyone else never reaches a subscriber."""
    payload = f"put-{role}-{space}-{next(_serial)}".encode()
    sub = net.watchers[space]
    net.sessions[role].put(SPACES[space], payload)
    if role in MAY_PUT[space]:
        assert wait_for(sub, payload)
    else:
        barrier(net.sessions[role], net.watcher_session(space))
        assert payload not in drain(sub), f"{role} could put on {space}"


@pytest.mark.parametrize("space", list(SPACES))
@pytest.mark.parametrize("role", ROLES)
def test_subscribe(net, role, space):
    """Only the space's readers receive what is put on it."""
    session = net.sessions[role]
    sub = Inbox(session, SPACES[space].rsplit("/", 1)[0] + "/**")
    try:
        barrier(session)  # the router has the declaration (or has refused it)
        payload = f"read-{role}-{space}-{next(_serial)}".encode()
        net.writer(space).put(SPACES[space], payload)
        assert wait_for(net.watchers[space], payload)  # it was routed
        if role in MAY_READ[space]:
            assert wait_for(sub, payload)
        else:
            barrier(session)
            assert payload not in drain(sub), f"{role} could read {space}"
    finally:
        sub.undeclare()


@pytest.mark.parametrize("role", ROLES)
def test_liveliness_token_on_a_shard(net, role):
    """Only a daemon may hold a shard's active token: a reader's (or gateway's) token at
    ``<admin>/shard/<shard>/active/<id>`` would keep every standby from taking over."""
    session = net.sessions[role]
    forged = f"{ACTIVE}/zz-evil-{role}"
    token = session.liveliness().declare_token(forged)
    try:
        barrier(session)
        seen = {str(r.ok.key_expr) for r in net.watch_daemon.liveliness().get(f"{ACTIVE}/*", timeout=TIMEOUT) if r.ok}
        assert (forged in seen) == (role == DAEMON), f"{role}'s token seen: {forged in seen}"
    finally:
        token.undeclare()


@pytest.mark.parametrize("role", ROLES)
def test_admin_queryable(net, role):
    """Only a daemon may answer ``<admin>/<daemon_id>/channels`` (what ``sinewatch status`` shows)."""
    session = net.sessions[role]
    key = f"sinewatch/admin/evil-{role}/channels"
    queryable = session.declare_queryable(key, lambda q: q.reply(key, b'{"forged": true}'))
    try:
        barrier(session)
        replies = {
            str(r.ok.key_expr) for r in net.watch_daemon.get("sinewatch/admin/*/channels", timeout=TIMEOUT) if r.ok
        }
        assert OWN_ADMIN in replies  # the real one answers
        assert (key in replies) == (role == DAEMON), f"{role}'s queryable answered: {key in replies}"
    finally:
        queryable.undeclare()


@pytest.mark.parametrize("role", ROLES)
def test_admin_query(net, role):
    """Daemons and readers may ask daemons what they serve; gateways and others may not."""
    replies = {
        str(r.ok.key_expr) for r in net.sessions[role].get("sinewatch/admin/*/channels", timeout=TIMEOUT) if r.ok
    }
    allowed = role in (DAEMON, READER)
    assert (OWN_ADMIN in replies) == allowed, f"{role} got {replies}"


@pytest.mark.parametrize("role", ROLES)
def test_liveliness_query_of_the_shards(net, role):
    """Daemons and readers may see which daemon is active or standing by; nobody else."""
    got = {
        str(r.ok.key_expr)
        for r in net.sessions[role].liveliness().get("sinewatch/admin/shard/**", timeout=TIMEOUT)
        if r.ok
    }
    allowed = role in (DAEMON, READER)
    assert ("sinewatch/admin/shard/acl/standby/acl-daemon" in got) == allowed, f"{role} got {got}"


@pytest.mark.parametrize("role", ROLES)
def test_the_router_admin_space_is_closed(net, role):
    """Zenoh's own admin space (``@/<router zid>/router/**``: links, routes, config) is no
    client's business."""
    session = net.sessions[role]
    own = f"@/{session.zid()}/"
    foreign = [
        str(r.ok.key_expr)
        for r in session.get("@/**", timeout=TIMEOUT)
        if r.ok and not str(r.ok.key_expr).startswith(own)
    ]
    assert foreign == [], f"{role} read {foreign[:3]}"


# ---- the attack end to end: a reader's token on a shard, then the active daemon killed ----
def stack_etcd(tmp_path: Path) -> Etcd:
    server = Etcd(tmp_path / "etcd-data")
    server.start()
    return server


def _secure_daemon(
    tmp_path: Path, cert_dir: Path, daemon_id: str, role: str, port: int, etcd: str | None = None
) -> subprocess.Popen[bytes]:
    cfg = tmp_path / f"{daemon_id}.toml"
    # the shard's owner is elected on etcd; a 2-s TTL (etcd's least): how fast a takeover is is not tested here
    election = f'etcd = "{etcd}"\nlease_ttl_s = 2\n' if etcd else ""
    cfg.write_text(
        config_head(daemon_id, f"tls/127.0.0.1:{port}")
        + f"""[zenoh.raw]
"transport/link/tls/root_ca_certificate" = "{cert_dir / "ca.pem"}"
"transport/link/tls/connect_certificate" = "{cert_dir / "sinewatch-daemon.pem"}"
"transport/link/tls/connect_private_key" = "{cert_dir / "sinewatch-daemon-key.pem"}"
"transport/link/tls/enable_mtls" = true
"transport/link/tls/verify_name_on_connect" = true
[cluster]
shard_id = "acl"
role = "{role}"
snapshot_interval_s = 0.5
{election}[recording]
enabled = false
[workers]
count = 1
"""
    )
    return start_daemon(tmp_path, daemon_id, cfg)


def test_a_readers_forged_active_token_does_not_stop_failover(tmp_path, certs):  # noqa: F811
    """The outside test's attack: a reader declares ``.../shard/<shard>/active/zz-evil-reader``;
    the active daemon is SIGKILLed; the standby must still take over (ownership is an etcd
    election: a liveliness token, forged or not, decides nothing)."""
    port = free_loopback_port()
    etcd = stack_etcd(tmp_path)
    endpoint = f"tls/127.0.0.1:{port}"
    procs: dict[str, subprocess.Popen[bytes]] = {}
    with secure_router(certs, port):
        reader = open_session(tls_section(certs, READER, endpoint))
        gateway = open_session(tls_section(certs, GATEWAY, endpoint))
        tokens: set[str] = set()
        cond = threading.Condition()

        def on_token(sample: zenoh.Sample) -> None:
            with cond:
                (tokens.add if sample.kind == zenoh.SampleKind.PUT else tokens.discard)(str(sample.key_expr))
                cond.notify_all()

        arrivals: list[tuple[float, dict]] = []

        def on_estimate(sample: zenoh.Sample) -> None:
            with cond:
                arrivals.append((time.monotonic(), json.loads(sample.payload.to_bytes())))
                cond.notify_all()

        watch = reader.liveliness().declare_subscriber("sinewatch/admin/shard/acl/**", on_token, history=True)
        est = reader.declare_subscriber("sinewatch/est/**", on_estimate)
        stop = threading.Event()
        try:
            # both at once (the standby campaigns a TTL after its start, so the intended owner usually wins; either
            # way the owner is killed and the other must take over)
            for d, role in (("a1", "active"), ("s1", "standby")):
                procs[d] = _secure_daemon(tmp_path, certs, d, role, port, etcd.endpoint)
            roles = {f"sinewatch/admin/shard/acl/{r}/{d}": (r, d) for r in ("active", "standby") for d in procs}
            with cond:
                assert cond.wait_for(
                    lambda: {roles[t][0] for t in tokens if t in roles} == {"active", "standby"}, TIMEOUT * 3
                ), tokens
                owner = next(roles[t][1] for t in tokens if t in roles and roles[t][0] == "active")
            successor = ({"a1", "s1"} - {owner}).pop()
            evil = reader.liveliness().declare_token("sinewatch/admin/shard/acl/active/zz-evil-reader")
            pub = BlockPublisher(gateway)
            assert pub.wait_for_subscriber("acl/a", TIMEOUT)

            def feed() -> None:
                n = 0
                while not stop.is_set():
                    x = np.sin(2 * np.pi * 50.0 * (np.arange(100) + n * 100) / 1000.0)
                    pub.publish("acl/a", x, sample_rate_hz=1000.0)
                    n += 1
                    stop.wait(0.1)  # the gateway's real-time pace

            feeder = threading.Thread(target=feed)
            feeder.start()
            with cond:
                assert cond.wait_for(lambda: len(arrivals) >= 5, TIMEOUT), f"{owner} never estimated"
            procs[owner].send_signal(signal.SIGKILL)
            procs[owner].wait()
            killed = time.monotonic()
            with cond:  # estimates again: the standby took over despite the reader's token
                took_over = cond.wait_for(lambda: any(t > killed + 0.3 for t, _ in arrivals), TIMEOUT)
                seen_tokens = set(tokens)
            stop.set()
            feeder.join()
            evil.undeclare()
        finally:
            stop.set()
            for p in procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
            for p in procs.values():
                p.wait(timeout=TIMEOUT)
            watch.undeclare()
            est.undeclare()
            reader.close()
            gateway.close()
            etcd.kill()
    assert took_over, "no estimate after the active daemon was killed: the standby did not take over"
    assert f"sinewatch/admin/shard/acl/active/{successor}" in seen_tokens, seen_tokens
