"""The shard election on a real etcd (the one `make etcd` installs): one owner at a time,
terms that grow, a gate that shuts strictly inside the TTL when the owner cannot reach
etcd, and a successor elected only after the owner's lease is gone."""

from __future__ import annotations

import asyncio
import time

import pytest
from cluster_procs import Proxy, etcd_server

from sinewatch.runtime.election import LeaseElection
from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.errors import ConfigError

TTL = 2


def test_a_standby_needs_etcd():
    with pytest.raises((ConfigError, ValueError), match=r"expected 'active' without cluster\.etcd"):
        SinewatchConfig.model_validate({"cluster": {"role": "standby"}})
    cfg = SinewatchConfig.model_validate({"cluster": {"role": "standby", "etcd": "127.0.0.1:2379"}})
    assert cfg.cluster.lease_ttl_s == 3  # the default: at most 3 s


def test_one_owner_the_gate_shuts_inside_the_ttl_and_the_successor_waits_for_the_lease(tmp_path):
    async def scenario(endpoint_a: str, endpoint_b: str, proxy: Proxy) -> dict[str, float]:
        key = "sinewatch/admin/election/test"
        a = LeaseElection(endpoint_a, key, "a", TTL)
        b = LeaseElection(endpoint_b, key, "b", TTL)
        won_a = await asyncio.wait_for(a.campaign(), 30)
        hold_a = asyncio.ensure_future(a.hold())
        assert a.may_publish()
        campaign_b = asyncio.ensure_future(b.campaign())
        await asyncio.sleep(TTL * 1.5)  # b reads the key held: it does not win while a keeps its lease alive
        assert not campaign_b.done() and a.may_publish() and a.keepalives >= 2

        proxy.sever()  # a is cut off from etcd
        cut = time.monotonic()
        deadline = a.deadline  # from a's last acknowledged keep-alive, sent before the cut
        assert deadline - cut < TTL - a.guard_s + 1e-3
        await asyncio.sleep(max(0.0, deadline - time.monotonic()))  # the gate is a deadline on a's own clock
        assert not a.may_publish()
        shut = time.monotonic()
        await asyncio.wait_for(hold_a, 30)  # a stands down: no keep-alive acknowledged for a TTL
        stood_down = time.monotonic()
        won_b = await asyncio.wait_for(campaign_b, 30)
        elected = time.monotonic()
        assert won_b.term > won_a.term  # the fencing token grows
        hold_b = asyncio.ensure_future(b.hold())
        assert b.may_publish() and not a.may_publish()
        await b.close()
        hold_b.cancel()
        await a.close()
        return {
            "shut": shut - cut,
            "stood_down": stood_down - cut,
            "elected": elected - cut,
            "deadline": deadline - cut,
        }

    with etcd_server(tmp_path) as etcd:
        proxy = Proxy(etcd.port)
        try:
            t = asyncio.run(scenario(f"127.0.0.1:{proxy.port}", etcd.endpoint, proxy))
        finally:
            proxy.close()
    print(t)
    # a stopped publishing before etcd could have let its lease go (the lease outlives a's last acknowledged
    # keep-alive by a TTL), so before b could be elected
    assert t["shut"] < TTL
    assert t["deadline"] < t["elected"]
    assert t["elected"] < TTL + 2.0  # b took over within 2 s of the lease's latest expiry


def test_an_owner_cut_off_wins_again_once_the_partition_heals_over_a_slow_link(tmp_path):
    """After a partition heals, the etcd channel connects again even when a connection's
    handshake is slow (a loaded machine, a long path). Seen in the 50-fault chaos run at load
    ~30: gRPC gave each connection attempt ~0.1-0.6 s (its minimum connect timeout is
    ``grpc.min_reconnect_backoff_ms``, set to 100 ms then), every attempt through the healed
    proxies "timed out before receiving SETTINGS frame", the owners stepped down and no
    standby could be elected. Here etcd's first bytes on each new connection come 1 s late."""

    async def scenario(endpoint: str, proxy: Proxy) -> float:
        a = LeaseElection(endpoint, "sinewatch/admin/election/slow", "a", TTL)
        await asyncio.wait_for(a.campaign(), 30)
        hold = asyncio.ensure_future(a.hold())
        proxy.sever()
        await asyncio.wait_for(hold, 30)  # a stands down: no keep-alive acknowledged for a TTL
        assert not a.may_publish()
        proxy.handshake_delay_s = 1.0
        proxy.heal()
        healed = time.monotonic()
        won = await asyncio.wait_for(a.campaign(), 30)  # its old lease expires meanwhile: the key goes with it
        elected = time.monotonic() - healed
        hold = asyncio.ensure_future(a.hold())
        assert won.term > 0 and a.may_publish()
        await a.close()
        hold.cancel()
        return elected

    with etcd_server(tmp_path) as etcd:
        proxy = Proxy(etcd.port)
        try:
            elected = asyncio.run(scenario(f"127.0.0.1:{proxy.port}", proxy))
        finally:
            proxy.close()
    print(f"elected again {elected:.2f} s after the partition healed")


def test_an_owner_whose_event_loop_is_stuck_lets_its_lease_go(tmp_path):
    """The keep-alives run on a thread of their own, so that a busy event loop does not depose
    a healthy owner; but an owner whose loop is stuck (a callback that never returns, in a live
    process: not a SIGSTOP, which stops the keep-alive thread too) serves nothing. Its
    keep-alives stop once its loop has not run for ``loop_stall_s`` (ten TTLs; one and a half here), so its lease
    expires and the other candidate is elected while the stuck loop is still stuck."""
    import threading

    stall_s = 1.5 * TTL  # the daemon's limit is ten TTLs (30 s at its default TTL): shorter here, the same path
    stuck_for = stall_s + TTL + 2.5  # at most: longer than the stall limit, a TTL and the 2 s a takeover may take

    async def scenario(endpoint: str) -> tuple[float, float]:
        a = LeaseElection(endpoint, "sinewatch/admin/election/stuck", "a", TTL, loop_stall_s=stall_s)
        b = LeaseElection(endpoint, "sinewatch/admin/election/stuck", "b", TTL)
        loop_a = asyncio.new_event_loop()  # a's daemon loop, in a thread of its own
        threading.Thread(target=loop_a.run_forever, daemon=True).start()
        on_a = asyncio.run_coroutine_threadsafe
        await asyncio.wrap_future(on_a(asyncio.wait_for(a.campaign(), 30), loop_a))
        hold_a = on_a(a.hold(), loop_a)
        campaign_b = asyncio.ensure_future(b.campaign())
        await asyncio.sleep(TTL * 1.5)  # a keeps its lease while its loop runs (longer than the stall limit)
        assert not campaign_b.done() and a.may_publish()
        release, resumed = threading.Event(), threading.Event()
        stuck_at: list[float] = []

        def stick() -> None:  # a's loop stuck, from when it runs this (its thread may wake late)
            stuck_at.append(time.monotonic())
            release.wait(stuck_for)
            resumed.set()

        asked = time.monotonic()
        loop_a.call_soon_threadsafe(stick)
        won_b = await asyncio.wait_for(campaign_b, 30)
        elected = time.monotonic() - stuck_at[0]
        print(f"a's loop ran the stuck callback {stuck_at[0] - asked:.2f} s after it was scheduled")
        hold_b = asyncio.ensure_future(b.hold())
        assert not resumed.is_set() and b.may_publish()  # elected while a's loop was still stuck
        release.set()  # a's loop runs again (no need to wait out the rest of ``stuck_for``)
        await asyncio.wrap_future(hold_a)  # once a's loop runs again, it finds it has stood down
        assert not a.may_publish() and won_b.term > 0
        await b.close()
        hold_b.cancel()
        await asyncio.wrap_future(on_a(a.close(), loop_a))
        loop_a.call_soon_threadsafe(loop_a.stop)
        return elected, a.loop_stall_s

    with etcd_server(tmp_path) as etcd:
        elected, stall_s = asyncio.run(scenario(etcd.endpoint))
    print(f"elected {elected:.2f} s after the owner's loop got stuck (stall limit {stall_s} s, TTL {TTL} s)")
    # the last keep-alive went out before the stall limit; the lease expires at most a TTL after it
    assert stall_s <= elected < stall_s + TTL + 2.0


def test_the_tests_read_of_the_election_key_waits_out_a_reset_connection(tmp_path):
    """The chaos test reads the election key right after faults that restart etcd or sever its
    connections: the read waits for etcd to answer again and is tried again on a reset
    connection (gRPC's retries, ``cluster_procs.ETCD_READ_OPTIONS``), rather than failing the test
    (it did under load, with "recvmsg:Connection reset by peer"). Here the read's first connection
    is closed at once (a severed proxy in front of etcd), then the proxy heals."""
    import threading

    import aetcd
    from cluster_procs import election_key

    async def put(endpoint: str) -> None:
        host, _, port = endpoint.rpartition(":")
        async with aetcd.Client(host, int(port)) as client:
            await client.put(b"sinewatch/admin/election/shard-x", b"d1")

    with etcd_server(tmp_path) as etcd:
        asyncio.run(put(etcd.endpoint))
        proxy = Proxy(etcd.port)
        proxy.sever()
        result: list[tuple[str, int]] = []
        reader = threading.Thread(target=lambda: result.append(election_key(f"127.0.0.1:{proxy.port}", "shard-x")))
        reader.start()
        try:
            assert proxy.refused.wait(30)  # the read's first connection was closed
            proxy.heal()
            reader.join(60)
        finally:
            proxy.close()
        assert not reader.is_alive()
        assert len(result) == 1 and result[0][0] == "d1" and result[0][1] > 0, result
