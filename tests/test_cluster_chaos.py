"""Shard ownership under faults, as processes: etcd, a Zenoh router, two shards with two
daemons each (an owner and a standby), a gateway publishing 100 channels in real time, a
CPU burner at twice the core count throughout, and faults drawn with a fixed seed:

- ``kill``: SIGKILL of a shard's owner (restarted afterwards: it stands by);
- ``pause``: SIGSTOP of an owner until its successor publishes (longer than the TTL), then SIGCONT;
- ``cut``: an owner cut off from etcd (a TCP proxy severed) while still on Zenoh, then healed;
- ``router``: the Zenoh router killed and restarted;
- ``etcd``: etcd killed and restarted on the same data.

Asserted, on what a fenced reader (:class:`sinewatch.clients.Fence`) keeps: no (channel,
block) published twice; every block estimated once or counted in exactly one gap; every
takeover's first estimate within 2 s of the old owner's lease expiry. The expiry is taken at
its latest, the fault's time plus the TTL (the owner's last keep-alive reached etcd before
the fault, at most a keep-alive interval, TTL/6, earlier): the takeover time reported can
understate the true one by up to that interval. The table in docs/cluster.md is this test's
output: ``pytest -s tests/test_cluster_chaos.py`` (``-m slow`` for the 50-fault run).
"""

from __future__ import annotations

import contextlib
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from cluster_procs import (
    CHANNELS,
    Estimates,
    Gateway,
    GatewayProcess,
    ProxyProcess,
    Router,
    Tokens,
    after,
    check_channel,
    cpu_burner,
    daemon_config,
    election_key,
    etcd_server,
    published_once_each,
    recorded_estimates,
    start_daemon,
    stop_all,
    takeover_timeline,
    wait_warm,
)

from sinewatch.clients import connect
from sinewatch.runtime.cluster import shard_of

SHARDS = {"sinewatch_in_1of2": "1/2", "sinewatch_in_2of2": "2/2"}  # shard_id -> shard
DAEMONS = {"a1": ("1/2", "active"), "b1": ("1/2", "standby"), "a2": ("2/2", "active"), "b2": ("2/2", "standby")}
SHARD_IDS = {d: f"sinewatch_in_{shard.replace('/', 'of')}" for d, (shard, _) in DAEMONS.items()}
KINDS = ("kill", "pause", "cut", "router", "etcd")
SEED = 20261126
TAKEOVER_LIMIT_S = 2.0
TTL_S = 3  # lease_ttl_s of the daemons (cluster_procs.daemon_config)


def run_chaos(tmp_path: Path, faults: list[str], gateway_process: bool = False) -> list[dict[str, Any]]:
    """``gateway_process``: the gateway in a process of its own (the 50-fault run: with the gateway and
    the test's subscriber in one loaded process, the router closed this process's link from the 20th
    fault on); the 5-fault run keeps it on a session of this process, as in the runs CI passed."""
    rng = random.Random(SEED)
    rows: list[dict[str, Any]] = []
    procs: dict[str, subprocess.Popen[bytes]] = {}
    with contextlib.ExitStack() as stack:
        etcd = stack.enter_context(etcd_server(tmp_path))
        router = Router(tmp_path)
        router.start()
        stack.callback(router.kill)
        proxies = {d: ProxyProcess(etcd.port) for d in DAEMONS}
        for p in proxies.values():
            stack.callback(p.close)
        configs = {
            d: daemon_config(tmp_path, d, shard, role, router.port, f"127.0.0.1:{proxies[d].port}")
            for d, (shard, role) in DAEMONS.items()
        }
        session = stack.enter_context(connect([f"tcp/127.0.0.1:{router.port}"]))
        estimates = Estimates(session, tmp_path)  # a failed wait shows the daemons' log tails
        try:
            tokens = Tokens(session, tmp_path)
            for d in DAEMONS:
                procs[d] = start_daemon(tmp_path, d, configs[d])
            tokens.wait_count("active", len(SHARDS), timeout=240)  # both shards elected (compiling takes a while)
            tokens.wait_count("standby", len(DAEMONS) - len(SHARDS), timeout=240)
            gateway = GatewayProcess(router.port) if gateway_process else Gateway(router.port)
            stack.callback(gateway.close)
            gateway.start()
            estimates.wait(lambda e: all(len(e[c]) >= 10 for c in CHANNELS), "every channel estimated")
            stack.enter_context(cpu_burner())
            restarted: str | None = None  # a killed owner, restarted: it may still be starting
            for n, kind in enumerate(faults):
                if restarted is not None and kind != "etcd":  # its start (~10-20 s under the burners) overlaps an
                    # etcd restart only: a daemon still starting when the router goes away cannot open its Zenoh
                    # session and exits (seen at load 15), and a shard faulted meanwhile would have no warm standby
                    tokens.wait_daemons(list(DAEMONS), timeout=240)
                    wait_warm(session, restarted, SHARD_IDS[restarted])
                    restarted = None
                shard_id = rng.choice(sorted(SHARDS))
                term = estimates.newest_term(shard_id) or 0
                owner, _ = election_key(etcd.endpoint, shard_id)  # etcd's word: an admin query can go unanswered
                t0, t0_wall = time.monotonic(), time.time()
                row: dict[str, Any] = {"n": n, "fault": kind, "shard": shard_id, "owner": owner, "t0_wall": t0_wall}
                if kind == "kill":
                    procs[owner].send_signal(signal.SIGKILL)
                    procs[owner].wait()
                    # restarted at once (its start, ~25 s at load 10, overlaps the takeover): it campaigns on a new
                    # lease, and stands by unless the old one has expired and it is elected before the standby
                    procs[owner] = start_daemon(tmp_path, owner, configs[owner])
                    restarted = owner
                    new = estimates.wait_for_new_term(shard_id, term, f"fault {n}: no successor after a kill")
                elif kind == "pause":
                    procs[owner].send_signal(signal.SIGSTOP)
                    new = estimates.wait_for_new_term(shard_id, term, f"fault {n}: no successor after a pause")
                    procs[owner].send_signal(signal.SIGCONT)
                elif kind == "cut":
                    proxies[owner].sever()
                    new = estimates.wait_for_new_term(shard_id, term, f"fault {n}: no successor after a cut")
                    proxies[owner].heal()
                elif kind == "router":
                    router.kill()
                    router.start()
                    new = None
                else:
                    etcd.kill()
                    etcd.start()
                    new = None
                row["pause_s"] = round(time.monotonic() - t0, 2)
                print(f"fault {n} ({kind}) done after {row['pause_s']} s", flush=True)
                if new is not None:
                    first = estimates.first_of_term[(shard_id, new)]
                    row["term"] = f"{term} -> {new}"
                    row["new_term"] = new
                    row["seen_s"] = round(first - (t0 + TTL_S), 3)  # at this test's subscriber (printed only)
                t_back = time.monotonic()
                estimates.wait(lambda e, t=t_back: all(after(e[c], t) for c in CHANNELS), f"fault {n}: all served")
                row["resumed_s"] = round(
                    max(after(estimates.by_channel[c], t_back)[0]["_arrival"] for c in CHANNELS) - t_back, 3
                )
                rows.append(row)
                print(f"fault {row}", flush=True)
                t_settle = time.monotonic()  # a second of normal service before the next fault
                estimates.wait(lambda e, t=t_settle: all(len(after(e[c], t)) >= 10 for c in CHANNELS), "settled")
            gateway.finish(estimates)
            tokens.wait_daemons(list(DAEMONS), timeout=240)  # status names every standby
            status = subprocess.run(
                [sys.executable, "-m", "sinewatch", "status", "--connect", f"tcp/127.0.0.1:{router.port}", "--summary"],
                capture_output=True, text=True, timeout=60, check=False,
            )  # fmt: skip
            elected = {s: election_key(etcd.endpoint, s) for s in SHARDS}
        finally:
            stop_all(procs)

    print(status.stdout)
    print("\n".join(str(r) for r in rows))
    # What the daemons published, from their recordings and the subscriber together: an estimate published
    # while the subscriber's own link was down (a router restart) is in a recording.
    recorded = recorded_estimates(tmp_path, list(DAEMONS))
    every = published_once_each(estimates.by_channel, recorded, estimates.fenced_off)
    for row in rows:  # the takeover: the new owner's first estimate, as it published it, after t0 + TTL (see above)
        if "new_term" in row:
            fencing = {"shard": row["shard"], "term": row["new_term"]}
            published = [
                (m["_published_ns"], d) for d, msgs in recorded.items() for m in msgs if m.get("fencing") == fencing
            ]
            if not published:  # its owner killed by the next fault before its recorder wrote a chunk of the term:
                row["takeover_s"] = row["seen_s"]  # timed at this test's subscriber instead (later, never earlier)
                continue
            first_ns, successor = min(published)
            row["takeover_s"] = round(first_ns / 1e9 - (row["t0_wall"] + TTL_S), 3)
            if row["takeover_s"] >= TAKEOVER_LIMIT_S:  # where its time went, in the failure's message
                row["timeline"] = takeover_timeline(
                    tmp_path,
                    successor,
                    fencing,
                    row["t0_wall"],
                    row["t0_wall"] + TTL_S,
                    recorded[successor],
                    estimates.by_channel,
                    gateway.sent_wall,
                )
                print(row["timeline"])
    lost = {c: check_channel(every[c], gateway.sent[c], estimates.unrecovered[c]) for c in CHANNELS}
    shard_channels = {s: [c for c in CHANNELS if shard_of(f"sinewatch/in/{c}", 2) == int(SHARDS[s][0])] for s in SHARDS}
    for row in rows:
        row["lost_blocks"] = sum(lost[c][1] for c in shard_channels[row["shard"]])
    raw_pairs = [(m["channel"], m["seq"]) for m in estimates.raw]
    print(
        f"{'#':>3} {'fault':<7} {'shard':<18} {'owner':<5} {'term':<14} {'takeover_s':>10} {'seen_s':>7} {'resumed_s':>9}"
    )
    for r in rows:
        print(
            f"{r['n']:>3} {r['fault']:<7} {r['shard']:<18} {r['owner']:<5} {r.get('term', '-'):<14} "
            f"{r.get('takeover_s', '-')!s:>10} {r.get('seen_s', '-')!s:>7} {r['resumed_s']:>9}"
        )
    takeovers = sorted(r["takeover_s"] for r in rows if "takeover_s" in r)
    if takeovers:
        print(
            f"takeovers {len(takeovers)}: min {takeovers[0]} median {takeovers[len(takeovers) // 2]} max {takeovers[-1]} s"
        )
    print(
        f"blocks sent {sum(gateway.sent.values())}, lost (flagged as gaps) {sum(v[1] for v in lost.values())}, "
        f"gaps {sum(v[0] for v in lost.values())}; raw duplicates {len(raw_pairs) - len(set(raw_pairs))}, "
        f"dropped by the fence {estimates.fence.dropped}"
    )
    assert status.returncode == 0, status.stderr
    # status names each shard's newest term, its owner and its standby, as etcd has them (the election key's
    # create revision and value)
    table = {words[0]: words for words in map(str.split, status.stdout.splitlines()) if words and words[0] in SHARDS}
    for shard_id, shard in SHARDS.items():
        owner, term = elected[shard_id]
        assert term >= (estimates.newest_term(shard_id) or 0)  # a later election may have published nothing yet
        standby = {d for d, (sh, _) in DAEMONS.items() if sh == shard} - {owner}
        assert table[shard_id][1:] == [str(term), owner, *standby], status.stdout
    for r in rows:
        if "takeover_s" in r:
            assert r["takeover_s"] < TAKEOVER_LIMIT_S, r
    assert sum(1 for r in rows if r.get("term")) >= 1
    return rows


def _faults(n: int) -> list[str]:
    rng = random.Random(SEED)
    first = list(KINDS)
    rng.shuffle(first)  # every kind at least once
    return (first + [rng.choice(KINDS) for _ in range(n - len(KINDS))])[:n] if n >= len(KINDS) else first[:n]


@pytest.mark.timeout(600)
def test_chaos_five_faults_no_estimate_twice_no_block_unaccounted(tmp_path):
    rows = run_chaos(tmp_path, _faults(5))
    assert len(rows) == 5


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_chaos_fifty_faults(tmp_path):
    rows = run_chaos(tmp_path, _faults(50), gateway_process=True)
    assert len(rows) == 50
