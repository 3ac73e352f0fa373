"""Shards and hot standby across processes: etcd (the shards' elections), a real Zenoh
router (`sinewatch router`), three `sinewatch serve` processes (two shards of the channels
and a standby for the first), a gateway publishing 100 channels, and a SIGKILL.

The active daemon of shard 1 first hangs (SIGSTOP: what it receives from then on, nobody
estimates) for half a second, then is killed (SIGKILL). What must hold: the standby takes
over within 2 s of the owner's lease expiry; every channel keeps getting estimates; no
estimate is published twice; the other shard is untouched; what nobody estimated is
flagged once per channel with ``gap_blocks`` equal to the blocks lost, or, with Zenoh's
recovery (the default), nothing is lost: the standby fetches those blocks from the
gateway's cache.

Both failures once seen here are covered: two daemons publishing the same channels from
the first block on (both took themselves for the active one: a liveliness query that
missed the other's token on a loaded machine) cannot happen with one etcd key per shard
(``check_channel`` asserts no estimate twice, on every channel, in every test); the
untouched shard losing blocks while the other's owner was stopped (the router's queue to
the stopped daemon held the gateway back, and a liveliness-driven re-election on the
stalled network) is asserted by ``(0, 0)`` on every shard-2 channel.
"""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cluster_procs import (
    CHANNELS,
    Estimates,
    Gateway,
    Router,
    Tokens,
    after,
    check_channel,
    daemon_config,
    etcd_server,
    published_once_each,
    recorded_estimates,
    restart_timeline,
    start_daemon,
    stop_all,
    takeover_timeline,
)

from sinewatch.clients import connect
from sinewatch.runtime.cluster import shard_of
from sinewatch.runtime.replay import replay

WAIT = 120.0  # the longest any condition may take on a loaded 2-core machine (a CPU burner, a second copy of this file)
TTL_S = 3  # lease_ttl_s of the daemons (cluster_procs.daemon_config)
pytestmark = pytest.mark.timeout(600)  # three processes starting on a loaded machine


def key(channel: str) -> str:
    return f"sinewatch/in/{channel}"


SHARD_1 = [c for c in CHANNELS if shard_of(key(c), 2) == 1]
SHARD_2 = [c for c in CHANNELS if shard_of(key(c), 2) == 2]
ETCD = {"endpoint": ""}  # the running test's etcd (set by the etcd fixture)


@pytest.fixture
def etcd(tmp_path):
    with etcd_server(tmp_path) as server:
        ETCD["endpoint"] = server.endpoint
        yield server


def daemon(
    tmp_path: Path, daemon_id: str, shard: str, role: str, port: int, recovery: bool, ttl_s: int = TTL_S
) -> subprocess.Popen[bytes]:
    cfg = daemon_config(tmp_path, daemon_id, shard, role, port, ETCD["endpoint"], recovery, ttl_s)
    return start_daemon(tmp_path, daemon_id, cfg)


def start_cluster(
    tmp_path: Path, port: int, recovery: bool, procs: dict[str, subprocess.Popen[bytes]], tokens: Tokens
) -> Gateway:
    """The two active daemons (a1: shard 1/2, a2: 2/2), then the standby of shard 1 (s1)
    once they serve, then the gateway (its own Zenoh session); ``procs`` gets the daemons as they start."""
    procs["a1"] = daemon(tmp_path, "a1", "1/2", "active", port, recovery)
    procs["a2"] = daemon(tmp_path, "a2", "2/2", "active", port, recovery)
    tokens.wait_for("active/a1", "active/a2", timeout=WAIT)
    procs["s1"] = daemon(tmp_path, "s1", "1/2", "standby", port, recovery)
    tokens.wait_for("standby/s1", timeout=WAIT)
    gateway = Gateway(port)
    gateway.start()
    return gateway


# Both variants run the same takeover (SIGSTOP, SIGKILL, lease expiry, fencing terms, status,
# replay); they differ only in whether the standby fetches the outage's blocks from the gateway's
# cache. The default run keeps the default (recovery) and its gap-or-nothing check; the gap
# flagged with its size on every channel without recovery runs in `make test-slow` (the chaos
# test checks every block estimated once or in exactly one gap in the default run).
@pytest.mark.parametrize(
    "recovery",
    [True, pytest.param(False, marks=pytest.mark.slow)],
    ids=["zenoh-recovery", "no-recovery"],
)
def test_standby_takes_over_a_killed_shard_within_2_s_of_its_lease_expiry(tmp_path, recovery, etcd):
    rt = Router(tmp_path)
    rt.start()
    port = rt.port
    with contextlib.ExitStack() as stack:
        stack.callback(rt.kill)
        session = stack.enter_context(connect([f"tcp/127.0.0.1:{port}"]))
        tokens, estimates = Tokens(session, tmp_path), Estimates(session, tmp_path)  # failed waits show the logs
        procs: dict[str, subprocess.Popen[bytes]] = {}
        try:
            gateway = start_cluster(tmp_path, port, recovery, procs, tokens)
            stack.callback(gateway.close)
            estimates.wait(lambda e: all(len(e[c]) >= 15 for c in CHANNELS), "every channel estimated", WAIT)

            # the active daemon of shard 1 hangs (what it receives now, nobody estimates) ...
            procs["a1"].send_signal(signal.SIGSTOP)
            t_hang, t_hang_wall = time.monotonic(), time.time()
            estimates.wait(lambda e: all(len(after(e[c], t_hang)) >= 5 for c in SHARD_2), "half a second on", WAIT)
            procs["a1"].send_signal(signal.SIGKILL)  # ... and a watchdog kills it
            t_kill = time.monotonic()
            procs["a1"].wait()
            estimates.wait(lambda e: all(after(e[c], t_kill + 0.3) for c in SHARD_1), "shard 1 served again", WAIT)
            seen_s = max(after(estimates.by_channel[c], t_kill)[0]["_arrival"] for c in SHARD_1) - (t_hang + TTL_S)
            # the killed daemon comes back (same config, role active) once its successor serves: it stands by (its
            # start overlaps the successor's first second of service)
            procs["a1"] = daemon(tmp_path, "a1", "1/2", "active", port, recovery)
            t_back = time.monotonic()
            estimates.wait(lambda e: all(len(after(e[c], t_back)) >= 10 for c in CHANNELS), "a second more", WAIT)
            tokens.wait_for("standby/a1", timeout=WAIT)
            t_again = time.monotonic()
            estimates.wait(lambda e: all(len(after(e[c], t_again)) >= 5 for c in CHANNELS), "half a second more", WAIT)
            gateway.finish(estimates, WAIT)
            status = subprocess.run(
                [sys.executable, "-m", "sinewatch", "status", "--connect", f"tcp/127.0.0.1:{port}", "--json"],
                capture_output=True,
                text=True,
                timeout=WAIT,
                check=False,
            )
        finally:
            stop_all(procs)

    # What the daemons published: this test's subscriber, and their recordings for what it missed (on a loaded
    # machine the subscriber's process lost estimates the daemons had published and recorded)
    recorded = recorded_estimates(tmp_path, ["a1", "a2", "s1"])
    every = published_once_each(estimates.by_channel, recorded)
    for c in SHARD_2:  # the other shard never noticed
        assert check_channel(every[c], gateway.sent[c], estimates.unrecovered[c]) == (0, 0)
    results = [check_channel(every[c], gateway.sent[c], estimates.unrecovered[c]) for c in SHARD_1]
    if recovery:  # the gateway's cache covers the outage: the new owner's own history query brings it back, in
        # order, ahead of the live blocks (docs/cluster.md), and nothing is lost
        assert all(r == (0, 0) for r in results), results
    else:  # what nobody estimated is flagged once per channel, with its size
        assert all(gaps == 1 and lost >= 1 for gaps, lost in results), results

    assert status.returncode == 0, status.stderr
    owners = {r["daemon_id"]: r for r in json.loads(status.stdout)}

    # The takeover: s1's first estimate of every shard-1 channel as s1 published it (its recording's log time; this
    # test's own subscriber, on a loaded machine, can get it seconds later), after the latest a1's lease can have
    # expired (its last keep-alive was sent before the hang, at most TTL/6 before: this can understate by that much)
    firsts: dict[str, int] = {}
    for m in recorded["s1"]:
        if (m.get("fencing") or {}).get("term") == owners["s1"]["term"]:
            firsts.setdefault(m["channel"], m["_published_ns"])
    assert sorted(firsts) == SHARD_1
    takeover_s = max(firsts.values()) / 1e9 - (t_hang_wall + TTL_S)
    print(
        f"takeover: s1 published the first estimate of every shard-1 channel within {takeover_s:.3f} s of a1's lease "
        f"expiry (at the latest {TTL_S} s after it hung; seen here {seen_s:.3f} s after)"
    )
    timeline = takeover_timeline(
        tmp_path,
        "s1",
        {"shard": owners["s1"]["shard_id"], "term": owners["s1"]["term"]},
        t_hang_wall,
        t_hang_wall + TTL_S,
        recorded["s1"],
        estimates.by_channel,
        gateway.sent_wall,
    )
    print(timeline)
    assert takeover_s < 2.0, f"takeover {takeover_s:.3f} s after the lease's expiry; {timeline}"
    assert set(owners) == {"a2", "s1", "a1"}
    assert owners["s1"]["role"] == "active" and owners["s1"]["takeovers"] == 1
    assert owners["s1"]["term"] > owners["a2"]["term"] > 0  # elected after a2 (and after a1, whose term ended)
    fenced = {m["fencing"]["term"] for c in SHARD_1 for m in estimates.by_channel[c]}
    assert len(fenced) == 2 and max(fenced) == owners["s1"]["term"]  # a1's term, then s1's
    assert owners["a1"]["role"] == "standby" and owners["a1"]["shard"] == "1/2"
    assert sorted(c["channel"] for c in owners["s1"]["channels"]) == SHARD_1
    assert sorted(c["channel"] for c in owners["a2"]["channels"]) == SHARD_2
    assert all(c["last_seq"] == gateway.sent[c["channel"]] - 1 for r in owners.values() for c in r["channels"])
    # a standby lists what it would take over: shard 1's channels, as last published
    assert [c["channel"] for c in owners["a1"]["channels"]] == SHARD_1

    # the standby's recording from the takeover on replays bit for bit on its own
    takeover_file = sorted((tmp_path / "s1").glob("*.mcap"))[-1]
    result = replay([takeover_file])
    assert result.ok and result.matched > 0, result


def test_standby_stays_standby_across_a_router_restart(tmp_path, etcd):
    """The router (the whole Zenoh network) goes away for a second and comes back: every
    daemon reconnects, estimates resume within 5 s, nothing is published twice, what was
    lost is flagged, and the standby does not take over a shard whose active daemon is
    still alive (its token comes back with the network)."""
    rt = Router(tmp_path)
    rt.start()
    port = rt.port
    procs: dict[str, subprocess.Popen[bytes]] = {}
    with contextlib.ExitStack() as stack:
        stack.callback(rt.kill)
        session = stack.enter_context(connect([f"tcp/127.0.0.1:{port}"]))
        tokens, estimates = Tokens(session, tmp_path), Estimates(session, tmp_path)
        try:
            gateway = start_cluster(tmp_path, port, True, procs, tokens)
            stack.callback(gateway.close)
            estimates.wait(lambda e: all(len(e[c]) >= 10 for c in CHANNELS), "every channel estimated", WAIT)

            rt.kill()
            t_down = time.monotonic()
            rt.start()  # on the same port
            t_back, t_back_wall = time.monotonic(), time.time()
            estimates.wait(lambda e: all(after(e[c], t_back) for c in CHANNELS), "estimates resume", WAIT)
            seen_s = max(after(estimates.by_channel[c], t_back)[0]["_arrival"] for c in CHANNELS) - t_back
            t_later = time.monotonic()
            estimates.wait(lambda e: all(len(after(e[c], t_later)) >= 10 for c in CHANNELS), "a second more", WAIT)
            gateway.finish(estimates, WAIT)
            tokens.wait_for("active/a1", "active/a2", "standby/s1", timeout=WAIT)
            roles = set(tokens.present)
        finally:
            stop_all(procs)

    # how long the test's own router took to start again is the harness's time, not the daemons' (5.2 s once,
    # with a CPU burner and a second copy of this file running): printed, not asserted. Service resumes when the
    # daemons publish again (their recordings' log times), as the takeover is timed: this test's own subscriber, on
    # a loaded machine, drains the burst of estimates the recovery brings seconds later (printed).
    recorded = recorded_estimates(tmp_path, ["a1", "a2", "s1"])
    back_ns = t_back_wall * 1e9
    resumed = {
        c: min(
            (
                m["_published_ns"]
                for msgs in recorded.values()
                for m in msgs
                if m["channel"] == c and m["_published_ns"] > back_ns
            ),
            default=None,
        )
        for c in CHANNELS
    }
    assert all(t is not None for t in resumed.values()), [c for c, t in resumed.items() if t is None]
    resumed_s = max(resumed.values()) / 1e9 - t_back_wall  # type: ignore[type-var,operator]
    timeline = restart_timeline(
        tmp_path, ["a1", "a2", "s1"], t_back_wall, recorded, estimates.by_channel, gateway.sent_wall
    )
    print(
        f"router restart: down {t_back - t_down:.3f} s; every channel's estimates published again within "
        f"{resumed_s:.3f} s of its return (drained here within {seen_s:.3f} s)\n{timeline}"
    )
    assert resumed_s < 5.0, f"published again {resumed_s:.3f} s after the router's return; {timeline}"
    # nothing twice; any loss flagged with its size (the cache usually covers it). What the daemons published while
    # this test's own session was still reconnecting to the new router never reached it: their recordings have it.
    every = published_once_each(estimates.by_channel, recorded)
    for c in CHANNELS:
        check_channel(every[c], gateway.sent[c], estimates.unrecovered[c])
    assert roles == {"active/a1", "active/a2", "standby/s1"}  # no takeover: a1 was never gone
