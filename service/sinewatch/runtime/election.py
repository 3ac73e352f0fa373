"""Who owns a shard: an election on an etcd lease, and the local deadline that gates publishing.

The recipe is etcd's own (``concurrency.Election`` of the Go client, on one key): a
candidate grants a lease of ``ttl`` seconds and, in one transaction, creates the shard's
election key attached to it if the key does not exist. The one whose transaction created
the key owns the shard; the key's create revision is the election's **term**, which grows
with every election (etcd revisions never go back while its data is kept), so it serves
as a fencing token. The others ask etcd how long the owner's lease has left every ``POLL_S``
(every ``FAST_POLL_S`` they read the key once under a second is left) and try again once it
is gone, which etcd makes it when the owner's lease expires (or is revoked).

The owner keeps its lease alive (a keep-alive every ``ttl / 6``, on a thread of its own, and
only while the daemon's event loop keeps running: a loop stuck for ``LOOP_STALL_TTLS`` TTLs
lets the lease go, so a successor serves the shard) and may publish only
while it can *prove* the lease alive: etcd restarts a lease's countdown when it receives a
keep-alive, so a keep-alive sent at local time ``t`` and acknowledged keeps the lease alive
until at least ``t + ttl``. The deadline is ``t + ttl - guard`` (``guard = ttl / 4``),
strictly inside the TTL: by the time a successor can have been elected, the old owner's
own clock has told it to stop. What the gate holds back is not lost: the daemon stops
taking inputs while the gate is shut and resumes when a keep-alive is acknowledged again
(the lease, and so the key, was never gone), or hands them to its successor if the lease
is lost (the successor restores the last snapshot and resumes after the last published
estimate). A pause that strikes between the check and the put (a SIGSTOP, a long GC) can
still let one estimate out late: its term is older than the successor's, and readers drop
it (:class:`sinewatch.clients.Fence`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

log = logging.getLogger("sinewatch.runtime.election")

# gRPC retries a lost connection after 1 s, then backs off to 120 s by default: an etcd
# restart would then keep every daemon from its lease for far longer than the TTL.
_GRPC_OPTIONS = {
    "grpc.initial_reconnect_backoff_ms": 100,
    "grpc.max_reconnect_backoff_ms": 500,
    # a ping every 5 s: etcd's own floor (--grpc-keepalive-min-time); pinged every 1 s, it answered
    # GOAWAY "too_many_pings" and dropped the connection, and with it any keep-alive under way
    "grpc.keepalive_time_ms": 5000,
    "grpc.keepalive_timeout_ms": 1000,
    "grpc.keepalive_permit_without_calls": 1,
}


def grpc_options(ttl_s: float) -> dict[str, int]:
    """The etcd channel's options for a lease of ``ttl_s``.

    gRPC core takes ``grpc.min_reconnect_backoff_ms`` as the least time a connection attempt
    (TCP, then the HTTP/2 settings exchange) may take before it is abandoned (the attempt's
    deadline is the later of that and the next backoff: here at most 0.5 s). Set to 100 ms
    once, no attempt whose handshake took longer than ~0.6 s could ever succeed: after a
    partition healed on a loaded machine, daemons' channels failed with "connection attempt
    timed out before receiving SETTINGS frame" for good, every owner lost its lease and no
    standby could win one. An attempt gets two TTLs: a handshake slower than that could not
    keep a lease anyway, and a refused connection (etcd restarting) still fails at once and
    is retried after the short backoff above."""
    return {**_GRPC_OPTIONS, "grpc.min_reconnect_backoff_ms": int(2000 * ttl_s)}


POLL_S = 0.2  # how often a standby reads the owner's lease while it is kept alive
# How often it reads the election key once the owner's lease has less than a second left (etcd
# states a lease's remaining TTL in whole seconds, truncated: 0 means expiring within the second,
# or expired and not yet revoked, which etcd's lessor does on a tick of its own, every 500 ms in 3.4)
FAST_POLL_S = 0.025
# How long the daemon's event loop may go without running before the owner stops renewing its
# lease, in TTLs. The keep-alives run on a thread of their own, so a loop stuck in a callback
# (a deadlock, a runaway computation) kept its lease and served nothing, with no successor. Ten
# TTLs: a loop busy with a long batch, a restore, or a put the router holds back (up to its 15 s)
# on a loaded machine must not be deposed for it; with two, healthy owners lost their leases
# ("the daemon's event loop has not run for 6.2 s") beside four CPU burners at load ~20.
LOOP_STALL_TTLS = 10


@dataclass
class Won:
    term: int  # the create revision of the election key: this election's fencing token
    lease_id: int


class LeaseElection:
    """One candidate for one shard (``key``), on one etcd endpoint (``host:port``).

    :meth:`campaign` returns once this candidate owns the shard; :meth:`hold` keeps the
    lease alive and returns when ownership can no longer be proven for a whole TTL (the
    lease expired, or etcd was out of reach that long); :meth:`may_publish` is the gate.

    The etcd client runs on a thread of its own (its own event loop): a keep-alive must
    not wait behind the daemon's work (a backlog of blocks, restoring a snapshot), which
    on a loaded machine took longer than the TTL and deposed a healthy owner. The daemon's
    loop awaits :meth:`campaign` and :meth:`hold` and reads the deadline (one float).
    """

    def __init__(self, endpoint: str, key: str, identity: str, ttl_s: int, loop_stall_s: float | None = None) -> None:
        host, _, port = endpoint.rpartition(":")
        self.host, self.port = host.strip("[]"), int(port)
        self.key = key.encode()
        self.identity = identity.encode()
        self.ttl_s = ttl_s
        self.guard_s = ttl_s / 4
        self.keepalive_s = ttl_s / 6
        self.call_timeout_s = ttl_s / 2
        self.deadline = 0.0  # monotonic: publish only before it
        self.owner = False
        self.won: Won | None = None
        self.keepalives = 0
        self._last_ack_sent = 0.0  # monotonic time the last acknowledged keep-alive was sent
        self.loop_stall_s = LOOP_STALL_TTLS * ttl_s if loop_stall_s is None else loop_stall_s
        self.loop_tick = 0.0  # monotonic: the daemon's loop last ran (the keep-alives need it recent)
        self._changed: asyncio.Event | None = None  # on the daemon's loop
        # called on the daemon's loop when a standby sees the owner's lease stop being renewed
        # (under a second left): a takeover may follow within the second; prepare for it
        self.on_expiring: Callable[[], None] | None = None
        self._daemon_loop: asyncio.AbstractEventLoop | None = None
        self._client: Any = None
        self._running: set[concurrent.futures.Future[Any]] = set()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="sinewatch-etcd", daemon=True)
        self._thread.start()

    # ---- the gate (daemon loop) -------------------------------------------------------------------
    def may_publish(self) -> bool:
        """True while the lease is proven alive (checked before every block)."""
        return self.owner and time.monotonic() < self.deadline

    async def wait_gate(self) -> bool:
        """Wait until the gate opens again (True) or ownership is lost (False)."""
        changed = self._event()
        while self.owner:
            if time.monotonic() < self.deadline:
                return True
            changed.clear()
            await changed.wait()
        return False

    def _event(self) -> asyncio.Event:
        if self._changed is None:
            self._daemon_loop = asyncio.get_running_loop()
            self._changed = asyncio.Event()
        return self._changed

    def _notify(self) -> None:
        """From the etcd thread: wake the daemon's waiters (the deadline or ownership changed)."""
        loop, event = self._daemon_loop, self._changed
        if loop is not None and event is not None and not loop.is_closed():
            loop.call_soon_threadsafe(event.set)

    def _call_daemon(self, fn: Callable[[], None] | None) -> None:
        """From the etcd thread: run ``fn`` on the daemon's loop."""
        loop = self._daemon_loop
        if fn is not None and loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(fn)

    async def _on_etcd(self, coro: Any) -> Any:
        self._event()
        future = asyncio.run_coroutine_threadsafe(coro, self._loop)
        self._running.add(future)
        future.add_done_callback(self._running.discard)
        return await asyncio.wrap_future(future)

    async def campaign(self) -> Won:
        return await self._on_etcd(self._campaign())  # type: ignore[no-any-return]

    async def hold(self) -> None:
        """Keep the lease alive (on the etcd thread) while this loop keeps running: it ticks
        every keep-alive interval, and the keep-alives stop once it has not for ``loop_stall_s``."""
        self.loop_tick = time.monotonic()
        ticker = asyncio.ensure_future(self._tick())
        try:
            await self._on_etcd(self._hold())
        finally:
            ticker.cancel()

    async def _tick(self) -> None:
        while True:
            self.loop_tick = time.monotonic()
            await asyncio.sleep(self.keepalive_s)

    # ---- etcd (its thread) ---------------------------------------------------------------------
    def _etcd(self) -> Any:
        if self._client is None:
            import aetcd  # the cluster extra: imported only by a daemon configured with cluster.etcd

            self._client = aetcd.Client(self.host, self.port, options=grpc_options(self.ttl_s))
        return self._client

    async def _call(self, coro: Any, timeout: float | None = None) -> Any:
        return await asyncio.wait_for(coro, timeout or self.call_timeout_s)

    async def _campaign(self) -> Won:
        """Until elected: try to create the key on this candidate's lease; otherwise wait for
        it to go. The lease is granted once and kept alive while waiting: a grant is a write
        etcd commits and syncs to disk, which took 0.8-2.3 s in three elections of ten on a
        loaded machine; at the key's deletion only the transaction is left to do."""
        lease: tuple[int, float] | None = None  # (id, send time of its last acknowledged grant or keep-alive)
        while True:
            try:
                if lease is None:
                    sent = time.monotonic()
                    granted = await self._call(self._etcd().lease(self.ttl_s), self.ttl_s)
                    lease = (granted.id, sent)
                won, revision, holder = await self._try_once(lease[0])
                if won is not None:
                    return won
                lease = await self._wait_for_delete(revision, holder, *lease)
            except Exception as exc:  # noqa: BLE001 (etcd unreachable, restarting, a call cut short, the lease gone)
                log.info(
                    "election %s: etcd not answering (%s: %s); trying again", self.key.decode(), type(exc).__name__, exc
                )
                if lease is not None:
                    self._spawn_revoke(lease[0])  # a new one next time: this one may have expired meanwhile
                    lease = None
                await asyncio.sleep(min(0.25, self.keepalive_s))

    async def _try_once(self, lease_id: int) -> tuple[Won | None, int, int]:
        """One election transaction; (the win or None, the revision read, the holder's lease id)."""
        client = self._etcd()
        started = time.monotonic()
        tx = client.transactions
        # A keep-alive beside the transaction, not before it (one round trip, not two): a win
        # starts the publish gate from this lease's last acknowledged keep-alive, and the one sent
        # while standing by can be most of a keep-alive interval old on a loaded machine (a new
        # owner's gate was seen shut 0.14 s after its win, for 1.75 s). Sent at ``started``, its
        # acknowledgement keeps the lease until at least ``started + ttl`` on etcd's side.
        reply, (ok, responses) = await asyncio.gather(
            self._call(client.refresh_lease(lease_id)),
            self._call(
                client.transaction(
                    compare=[tx.create(self.key) == 0],
                    success=[tx.put(self.key, self.identity, lease=lease_id), tx.get(self.key)],
                    failure=[tx.get(self.key)],
                ),
                self.ttl_s,
            ),
        )
        if reply.TTL <= 0:  # the transaction cannot have put the key on a lease etcd no longer has
            raise LookupError(f"lease {lease_id:x} expired while standing by")
        kvs = responses[-1]
        revision = kvs[0][1].header.revision if kvs else 0
        holder = int(kvs[0][1].lease) if kvs else 0
        if ok:
            self.won = Won(term=kvs[0][1].create_revision, lease_id=lease_id)
            self.owner = True
            self._ack(started)  # the lease lives at least a TTL past its last acknowledged keep-alive's sending
            log.info(  # where a slow takeover's time went
                "election %s: won term %d (keep-alive and transaction %.0f ms)",
                self.key.decode(),
                self.won.term,
                (time.monotonic() - started) * 1e3,
            )
            return self.won, revision, holder
        return None, revision, holder

    async def _wait_for_delete(self, revision: int, holder: int, lease_id: int, acked: float) -> tuple[int, float]:
        """Until the key is gone; returns this candidate's lease with the send time of its last
        acknowledged keep-alive (one every ``ttl / 6`` meanwhile).

        While the holder keeps its lease alive, a time-to-live request on the holder's lease
        every ``POLL_S`` (a read, answered without a disk write; -1 once etcd revoked it, which
        deletes the key in the same commit). Once it says less than a second is left (0: the
        holder stopped renewing), the key itself is read every ``FAST_POLL_S`` until it goes,
        and the lease's time to live every ``POLL_S`` still (a holder that renews again, e.g.
        etcd back in time, sends it back up). With a read of the key every 0.2 s throughout, a
        takeover waited up to 0.2 s after the deletion. A watch would tell at once, but aetcd's
        ``watch_once`` was seen to hang for good in its cancellation after the event had come (a
        standby that never took over); a read cannot hang past its timeout."""
        client = self._etcd()
        fast_until = 0.0  # monotonic: read the key (not the lease) until then
        wake = time.monotonic() + POLL_S
        while True:
            await asyncio.sleep(max(0.0, wake - time.monotonic()))
            if time.monotonic() >= acked + self.keepalive_s:
                sent = time.monotonic()
                reply = await self._call(client.refresh_lease(lease_id))
                if reply.TTL <= 0:
                    raise LookupError(f"lease {lease_id:x} expired while standing by")
                acked = sent
            now = time.monotonic()
            if now < fast_until or not holder:
                gone = await self._call(client.get(self.key)) is None
            else:
                info = await self._call(client.get_lease_info(holder, keys=False))
                gone = info.TTL < 0
                if info.TTL == 0 and not fast_until:
                    self._call_daemon(self.on_expiring)
                fast_until = now + POLL_S if info.TTL == 0 else 0.0
            if gone:
                log.info("election %s: the owner's key is gone (after revision %d)", self.key.decode(), revision)
                return lease_id, acked
            wake = now + (FAST_POLL_S if now < fast_until else POLL_S)

    def _ack(self, sent: float) -> None:
        self._last_ack_sent = sent
        self.deadline = sent + self.ttl_s - self.guard_s
        self._notify()

    async def _hold(self) -> None:
        """Keep the lease alive while this daemon owns the shard; return when it is lost."""
        won = self.won
        assert won is not None
        client = self._etcd()
        failing = False  # the keep-alives fail (logged once per run of failures)
        try:
            while True:
                sent = time.monotonic()
                reply: Any = None
                try:
                    if sent - self.loop_tick > self.loop_stall_s:  # its loop stuck, the owner serves nothing
                        raise TimeoutError(f"the daemon's event loop has not run for {sent - self.loop_tick:.1f} s")
                    reply = await self._call(client.refresh_lease(won.lease_id))
                except Exception as exc:  # noqa: BLE001 (unreachable etcd: the deadline decides)
                    # the first failure of a run is logged: why an owner stepped down shows in
                    # its log (a chaos run's owners once went silent before losing their leases)
                    (log.debug if failing else log.info)(
                        "election %s: keep-alive failed (%s: %s)", self.key.decode(), type(exc).__name__, exc
                    )
                    failing = True
                if reply is not None and reply.TTL > 0:
                    self.keepalives += 1
                    failing = False
                    self._ack(sent)
                elif reply is not None:  # etcd says the lease is gone: so is the key
                    log.warning("election %s: lease %x expired", self.key.decode(), won.lease_id)
                    return
                elif time.monotonic() >= self._last_ack_sent + self.ttl_s:
                    log.warning("election %s: no keep-alive acknowledged for a TTL: stepping down", self.key.decode())
                    return
                await asyncio.sleep(max(0.0, sent + self.keepalive_s - time.monotonic()))
        finally:
            self.owner = False
            self.deadline = 0.0
            self._notify()
            self._spawn_revoke(won.lease_id)  # if etcd still holds it, the successor need not wait for its TTL

    def _spawn_revoke(self, lease_id: int) -> None:
        async def revoke() -> None:
            with contextlib.suppress(Exception):
                await self._call(self._etcd().revoke_lease(lease_id))

        task = asyncio.ensure_future(revoke())
        _background.add(task)
        task.add_done_callback(_background.discard)

    async def _close(self) -> None:
        won, self.won = self.won, None
        if self._client is not None:
            if won is not None:
                with contextlib.suppress(Exception):
                    await self._call(self._client.revoke_lease(won.lease_id))
            with contextlib.suppress(Exception):
                await self._client.close()
            self._client = None

    async def close(self) -> None:
        """Give the shard up now (a graceful stop): revoke the lease, so a successor need
        not wait for its TTL; then end the etcd thread."""
        self.owner = False
        self.deadline = 0.0
        self._notify()
        for future in list(self._running):  # a campaign or a hold still running there
            future.cancel()  # thread-safe: cancels its task on the etcd thread's loop
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self._on_etcd(self._close()), self.ttl_s)
        self._loop.call_soon_threadsafe(self._loop.stop)


_background: set[asyncio.Task[None]] = set()
