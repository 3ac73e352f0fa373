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
