"""The daemon's intake: a Zenoh subscriber and a pump thread that hand the event loop its inputs
in batches, and the order a takeover's history goes to the pipeline.

Why a thread: Zenoh delivers samples on its own threads into a bounded channel (never
blocking a Zenoh callback on Python work; as deep as the queue with ``queue_policy = "drop"``:
:func:`zenoh_side_channel`); the pump drains it in batches and hands each batch
to the event loop with one ``call_soon_threadsafe`` (:mod:`sinewatch.runtime.daemon` says how
backpressure and shutdown use it).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import logging
import math
import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Protocol

import zenoh
import zenoh.ext

from sinewatch.core.pipeline import Pipeline
from sinewatch.runtime.cluster import Ownership
from sinewatch.schemas.codec import HEADER as BLOCK_HEADER
from sinewatch.schemas.codec import MAGIC as BLOCK_MAGIC
from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.frame import FRAME_MAGIC

log = logging.getLogger("sinewatch.runtime.daemon")  # the daemon's log: operators filter on one name

HISTORY_TIMEOUT_S = 10.0  # how long the publishers' caches may take to answer a new subscriber's history query
# the replies a query for every key's whole cache may bring (100 keys of 1,024 blocks: 102,400)
HISTORY_FIFO_ALL = 1 << 20
# A takeover's history queries open at a time, one per key (Intake._histories_by_key): a shard of up
# to 64 keys asks for all of them at once. Eight at a time, a 50-key shard's last channel had its
# first estimate 2.49 s after the lease's expiry in a failover test beside four burners (load 8-16;
# the history 1.19 s), the round trips one after another; a shard of thousands of keys is not asked
# for every one at once
HISTORY_QUERIES_AT_ONCE = 64
# The priority a history query asks its replies to travel at: a reply goes with its query's QoS, hop
# by hop (the publisher's session to the router, the router to this daemon). Not the inputs' ``data``:
# at the publisher's session its cache's replies then fill a queue of their own, not the one its
# puts go through, and at the router they reach a new owner ahead of the live inputs (which the
# router drops for a daemon whose link is congested), so that the router's pushes of those BLOCK
# replies wait only for the link, not behind the inputs as well (tests/test_cluster_history_priority.py)
HISTORY_PRIORITY = zenoh.Priority.DATA_HIGH


def zenoh_side_channel(policy: str, batch: int, capacity: int) -> Any:
    """The channel Zenoh's receiving thread hands this intake its samples through.

    ``"block"``: a small FIFO; past it Zenoh itself holds the data back, and so does the
    publisher (peer mode: the back-pressure loses nothing). ``"drop"`` (a daemon behind a
    router): a FIFO as deep as the queue, so that Zenoh's thread does not wait while the pump
    is behind. That thread also reads this daemon's query replies, snapshots and admin queries
    off the same link; with a full FIFO it stops, and the router, pushing the daemon a ``BLOCK``
    reply (a takeover's history queries), stops reading the sender's link, the gateway's, for
    everyone (docs/cluster.md, "A daemon behind real time keeps reading its link"). A pump is
    behind when its process is starved (a takeover's 50 history threads share the GIL with it).
    Not a ring: what a ring drops is counted nowhere, where the pump counts every input the
    queue drops."""
    if policy == "drop":
        return zenoh.handlers.FifoChannel(max(64, capacity))
    return zenoh.handlers.FifoChannel(max(64, batch * 2))


@dataclass
class IntakeCounters:
    received: int = 0
    dropped: int = 0
    backpressure_waits: int = 0
    unrecovered: int = 0  # blocks Zenoh reported missed for good (past the publishers' history)
    not_owned: int = 0  # inputs of keys another shard owns (cluster.shard), dropped unread


# (key, payload, encoding, received monotonic ns)
Item = tuple[str, bytes, str, int]


def _block_seq(payload: bytes) -> int | None:
    """A binary block's seq, read from its header without decoding (None: not a binary block)."""
    if payload[:4] != BLOCK_MAGIC or len(payload) < BLOCK_HEADER.size:
        return None
    return int.from_bytes(payload[8:16], "little")


class InOrder(list[Item]):
    """A batch the daemon takes in the order given, ahead of any backlog it takes in turns
    (:class:`KeyTurns`): a takeover's catch-up (:func:`catch_up_order`)."""


def catch_up_order(
    replies: list[tuple[Item, Any, int]], published: dict[str, int]
) -> tuple[list[tuple[Item, Any, int]], list[tuple[Item, Any, int]]]:
    """A takeover's history (``(item, publisher, sn)``, each key's blocks in order) in the
    order it goes to the pipeline, as (catch-up, rest); ``published``: each key's last seq the
    previous owner published. The catch-up, key by key: each key's blocks up to ``published``
    (they only bring the state up to date), its first block to publish and the one after it
    (which releases the first's estimate from the hold, ``hold_estimates``: its latency is
    within a block). Then the rest, the keys taken in turn. Channel k's first estimate of a
    takeover then waits for the catch-up of k channels, not of all of them: with the keys taken
    in turn from the start, no estimate came before every channel's state was brought up to
    date (~5 blocks each at a snapshot interval of 0.5 s: 1.5 s under load in a chaos run's
    kill), and none before a whole key's history without turns. The daemon takes the catch-up
    as it is given (:class:`InOrder`): taken in turns with the rest, the last channel's first
    estimate came after the whole history (3,170 blocks: 2.3 s beside four CPU burners)."""
    by_key: dict[str, list[tuple[Item, Any, int]]] = {}
    for reply_item in replies:
        by_key.setdefault(reply_item[0][0], []).append(reply_item)
    first: list[tuple[Item, Any, int]] = []
    rest: list[list[tuple[Item, Any, int]]] = []
    for key, items in by_key.items():
        last = published.get(key)
        n = 0
        if last is not None:  # up to and including the second block after ``last``
            while n < len(items) and (_block_seq(items[n][0][1]) or 0) <= last:
                n += 1
            n = min(n + 2, len(items))
        first += items[:n]
        rest.append(items[n:])
    return first, [it for turn in itertools.zip_longest(*rest) for it in turn if it is not None]


class KeyTurns:
    """Inputs waiting for the pipeline, taken one key at a time in turn, each key's in order.

    The order between keys is free (a channel's state sees only its own key's blocks), and a
    burst comes key by key: after a router restart zenoh-ext hands over each publisher's
    recovered blocks at once, as its query is answered, so in arrival order the last key's first
    block waited for every other key's whole outage (50 keys of 19 blocks: every channel served
    again 1.1 s after the first, and 12-14 s beside four CPU burners). Taken in turns, each key's
    next block waits for one of each other key's, whenever it came. The daemon takes a backlog of
    more than one batch this way only; otherwise inputs go on in arrival order (the order of
    ErrorReports across keys, for one, is the order the inputs came in)."""

    def __init__(self) -> None:
        self._by_key: dict[str, collections.deque[Item]] = {}  # its order: the keys' turns
        self._in_order: collections.deque[Item] = collections.deque()  # InOrder batches: taken first, as given

    def __len__(self) -> int:
        """The keys waiting for their turn, plus the items of :class:`InOrder` batches waiting."""
        return len(self._by_key) + len(self._in_order)

    def add(self, items: list[Item]) -> None:
        if isinstance(items, InOrder):
            self._in_order.extend(items)
            return
        for item in items:
            self._by_key.setdefault(item[0], collections.deque()).append(item)

    def take(self, n: int) -> list[Item]:
        """Up to ``n`` items: those of :class:`InOrder` batches first, as given; then from the
        keys in turn (a key served goes to the end of the turn)."""
        in_order = self._in_order
        out: list[Item] = [in_order.popleft() for _ in range(min(n, len(in_order)))]
        by_key = self._by_key
        while len(out) < n and by_key:
            key = next(iter(by_key))
            waiting = by_key.pop(key)
            out.append(waiting.popleft())
            if waiting:
                by_key[key] = waiting
        return out


class IntakeHost(Protocol):
    """What the intake needs of its daemon (:class:`sinewatch.runtime.daemon.Daemon`): the intake
    sits below it and calls back only through these, on the event loop."""

    config: SinewatchConfig
    force_exit: threading.Event

    @property
    def session(self) -> zenoh.Session: ...

    @property
    def pipeline(self) -> Pipeline: ...

    def enqueue(self, batch: list[Item]) -> None: ...

    def report_drops(self, dropped: Counter[str]) -> None: ...

    def report_unrecovered(self, key: str, n: int) -> None: ...


def history_query(session: zenoh.Session, selector: str, blocks: int | None) -> Any:
    """One query on the publishers' caches, with Zenoh's default ``BLOCK`` (a router forwards the
    replies with the query's QoS: with ``DROP`` a takeover's burst of replies lost replies and
    final replies in the router's queue, and each such query waited out its timeout, the key's
    history flagged as a gap), at ``HISTORY_PRIORITY``. Its FIFO holds every reply asked for, so
    that Zenoh's thread never waits for this one to be read while another key's is: the daemon's
    link is read as fast as the replies come, and its router never waits on it for them."""
    return session.get(
        selector,
        zenoh.handlers.FifoChannel((blocks or HISTORY_FIFO_ALL) + 64),
        consolidation=zenoh.ConsolidationMode.NONE,
        accept_replies=zenoh.ReplyKeyExpr.ANY,
        timeout=HISTORY_TIMEOUT_S,
        priority=HISTORY_PRIORITY,
    )


class Intake:
    """Zenoh subscriber + pump thread feeding the event loop in batches."""

    def __init__(self, daemon: IntakeHost, loop: asyncio.AbstractEventLoop, history_blocks: int | None = None) -> None:
        cfg = daemon.config
        self._daemon = daemon
        self._loop = loop
        self._batch = cfg.limits.intake_batch
        self._policy = cfg.limits.queue_policy
        self._capacity = cfg.limits.queue_capacity
        self._room = threading.Semaphore(cfg.limits.queue_capacity)
        self.counters = IntakeCounters()
        self._owner = Ownership.of(cfg)  # a shard (cluster.shard) and/or a worker's share of the keys
        fifo = zenoh_side_channel(self._policy, self._batch, self._capacity)
        self._miss_listener = None
        self._subscriber: zenoh.Subscriber[Any] | zenoh.ext.AdvancedSubscriber[Any]
        # The newest sample handed over per publisher (its source id -> sequence number): the
        # history this intake asks for itself and the samples zenoh-ext delivers overlap, and a
        # recovery can deliver again what was delivered; each sample goes to the pipeline once.
        self._last_sn: dict[Any, int] = {}
        self._lock = threading.Lock()
        self._held: list[tuple[Item, Any, int]] | None = None  # live samples waiting for their key's history
        self._awaited: set[str] | None = None  # the keys whose history is still on its way (None: every key)
        self._stopping = False
        self._known: dict[str, int] = {}  # key -> the seq of its last block in the state (history up to it is dropped)
        self._key_of: dict[str, str] = {}  # publisher (source id) -> its key: which channel a miss belongs to
        self._published: dict[str, int] = {}  # key -> the seq of its last block the previous owner published
        self._block_rate: dict[str, float] = {}  # key -> its blocks a second (a takeover's later queries)
        if cfg.zenoh.recovery:
            # Blocks a subscriber missed (a router restart, a reconnect) are fetched again
            # from the publishers' caches (heartbeats tell what was missed); what is past their
            # history is reported here. The publishers' history at subscription is asked for
            # by this intake itself (History below), not by zenoh-ext's subscriber: in zenoh-ext
            # (1.9-1.10) a live sample that arrives during the subscriber's history query
            # starts a second query, for that publisher's whole cache; if the history query
            # ends first, the next live sample is delivered at once and the history, still
            # waiting on the second query, is dropped as older than it, with no miss reported
            # (seen on 42 of 50 channels in one takeover); when the second query ends first,
            # the whole cache (1,024 blocks a key) is delivered and had to be read and
            # recorded before the first new estimate (takeovers of 3-4 s under load).
            self._held = []
            self._subscriber = zenoh.ext.declare_advanced_subscriber(
                daemon.session,
                cfg.keys.input,
                fifo,
                recovery=zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
                subscriber_detection=True,
            )
        else:
            self._subscriber = daemon.session.declare_subscriber(cfg.keys.input, fifo)
        self._thread = threading.Thread(target=self._pump, name="sinewatch-intake", daemon=True)
        self._closed = threading.Event()
        self._thread.start()
        # Only now, with the pump draining the FIFO: zenoh-ext hands recovered samples to the
        # FIFO holding the subscriber's lock, which registering a listener takes too; with the
        # FIFO full and nobody draining it yet, a takeover's daemon hung here for good.
        if isinstance(self._subscriber, zenoh.ext.AdvancedSubscriber):
            self._miss_listener = self._subscriber.sample_miss_listener(self._on_miss)
            # each key's last block already in the state (restored from a snapshot or a file): the
            # history up to it is dropped unread rather than decoded, recorded and skipped
            keys = Counter(ch.key for ch in daemon.pipeline.channels.values())
            self._known = {
                ch.key: ch.last_seq
                for ch in daemon.pipeline.channels.values()
                if ch.last_seq is not None and keys[ch.key] == 1
            }
            resume = daemon.pipeline.resume_points
            self._published = {
                ch.key: resume[ch.name].published_seq
                for ch in daemon.pipeline.channels.values()
                if ch.name in resume and keys[ch.key] == 1
            }
            # each key's blocks a second (from its channel's mean block length): a key's query sent later
            # asks for as many more as came meanwhile (Intake._histories_by_key)
            self._block_rate = {
                ch.key: ch.sample_rate_hz * ch.blocks / ch.samples
                for ch in daemon.pipeline.channels.values()
                if keys[ch.key] == 1 and ch.blocks and ch.samples
            }
            queries: dict[str, int | None]
            if history_blocks and self._known:  # a takeover: its shard's keys only, each its own query
                queries = dict.fromkeys(self._known, history_blocks)
                with self._lock:
                    self._awaited = set(queries)
            else:  # every key's whole cache (or its newest ``history_blocks``), in one query
                queries = {"": history_blocks}
            threading.Thread(target=self._history, args=(queries,), name="sinewatch-history", daemon=True).start()

    def _history(self, queries: dict[str, int | None]) -> None:
        """The publishers' cached samples asked for once, after subscribing: per key (``queries``:
        key -> its newest blocks to ask for; the key "" for every key of ``keys.input`` at once, None
        for all the caches hold), each key's handed over as soon as its own query ends (its catch-up
        first, :func:`catch_up_order`), then what arrived live for that key meanwhile (held back
        until then), each sample once; from then on the pump hands that key's over directly. Handed
        over key by key, a takeover's first estimate waits for one key's history, not for every
        key's: a history of 6,397 blocks took 1.82 s through a loaded router, and the first estimate
        came after all of it (a 50-fault chaos run's kill: 2.35 s after the lease's expiry)."""
        total = 0
        try:
            if "" in queries:
                replies = self._drain(self._query(f"{self._daemon.config.keys.input}/@adv/**", queries[""]))
                total = len(replies)
                if not self._hand_over_history(replies, None):
                    return
            else:
                by_key = self._histories_by_key(queries)
                if by_key is None:
                    return
                total = by_key
        except zenoh.ZError as exc:  # the session closing under it: the live samples still go on
            log.warning("intake: history query failed: %s", exc)
        with self._lock:  # whatever is still held (a query that failed): on in arrival order
            held, self._held, self._awaited = self._held or [], None, None
            if not self._stopping:
                self._hand_over(held)
        log.info("intake: %d block(s) of history, %d key(s) in turn", total, len(queries))

    def _histories_by_key(self, queries: dict[str, int | None]) -> int | None:
        """Each key's history query, ``HISTORY_QUERIES_AT_ONCE`` of them open at a time (the next
        sent as one ends), each key handed over as its own query ends, in the order they end; the
        blocks of history (None once unsubscribed). With every key's query sent at once, the
        caches answered them all through the router together: the last keys' replies came last,
        some after their 10-s timeout (a 50-fault chaos run's takeover after an 11,578-block history
        left ch092-ch099 unserved for 60 s), and every key's newest blocks were as old as the
        takeover. A query sent later asks for blocks that are newer by then, and a key whose query
        is slow holds back no other key's history."""
        ended: queue.Queue[tuple[str, list[tuple[Item, Any, int]]]] = queue.Queue()
        waiting = iter(queries.items())
        total = 0
        started = time.monotonic()

        def ask_next() -> bool:
            key, blocks = next(waiting, ("", None))
            if not key:
                return False
            if blocks:  # the newest blocks reach back as far as when the first queries went out
                blocks += math.ceil((time.monotonic() - started) * self._block_rate.get(key, 0.0))
            query = self._query(f"{key}/@adv/**" + (f"?_max={blocks}" if blocks else ""), blocks)
            threading.Thread(
                target=lambda: ended.put((key, self._drain(query, key))), name="sinewatch-history-key", daemon=True
            ).start()
            return True

        open_queries = sum(ask_next() for _ in range(HISTORY_QUERIES_AT_ONCE))
        while open_queries:
            key, replies = ended.get()  # every drain ends: a query ends by its timeout at the latest
            open_queries -= 1
            total += len(replies)
            if not self._hand_over_history(replies, key):
                return None
            open_queries += ask_next()
        return total

    def _drain(self, query: Any, key: str = "") -> list[tuple[Item, Any, int]]:
        """One query's replies of keys this process owns, until the query ends (its final reply,
        or its timeout: what came before it is kept)."""
        replies: list[tuple[Item, Any, int]] = []
        with contextlib.suppress(zenoh.ZError):  # the session closing under it: what came is kept
            for reply in query:
                if (item := self._history_reply(reply)) is not None:
                    replies.append(item)
                elif reply.err is not None:  # its timeout: what is past it is the held blocks' gap
                    log.info("intake: history query of %s: %s", key or "every key", reply.err.payload.to_string())
        return replies

    def _query(self, selector: str, blocks: int | None) -> Any:
        return history_query(self._daemon.session, selector, blocks)

    def _history_reply(self, reply: zenoh.Reply) -> tuple[Item, Any, int] | None:
        sample = reply.ok
        return None if sample is None else self._own(sample, history=True)

    def _hand_over_history(self, replies: list[tuple[Item, Any, int]], key: str | None) -> bool:
        """Hand over one key's history (``key``; None: every key's), its catch-up first, then what
        was held back for it; False once unsubscribed (a deposed owner: these are its successor's)."""
        catch_up, rest = catch_up_order(replies, self._published)
        with self._lock:  # the pump waits here: nothing live of this key goes ahead of its history
            if self._stopping:
                self._held = None
                return False
            held = self._held or []
            if key is None:
                mine, self._held = held, []
            else:
                mine = [item for item in held if item[0][0] == key]
                self._held = [item for item in held if item[0][0] != key]
                if self._awaited is not None:
                    self._awaited.discard(key)
            self._hand_over(catch_up, in_order=True)
            self._hand_over(rest + mine)
        return True

    def _in_state(self, key: str, payload: bytes) -> bool:
        """A binary block whose seq (read from its header) is at or before its channel's last
        block in the state: already taken in (a takeover's history reaches back past its
        snapshot, twice what it lacks; most of it was in the snapshot)."""
        last = self._known.get(key)
        seq = _block_seq(payload) if last is not None else None
        return seq is not None and last is not None and seq <= last

    def _own(self, sample: zenoh.Sample, history: bool = False) -> tuple[Item, Any, int] | None:
        """(item, publisher, sequence number) of a sample of a key this process owns, else None
        (and None for a block of the history already in the state)."""
        key = str(sample.key_expr)
        # another daemon's or worker's keys: not ours to copy, decode, record or count
        if self._owner is not None and not self._owner.owns(key):
            self.counters.not_owned += 1
            return None
        info = sample.source_info
        source, sn = (str(info.source_id), info.source_sn) if info is not None else (None, 0)
        if source is not None:
            self._key_of[source] = key
        payload = sample.payload.to_bytes()
        if history and self._in_state(key, payload):
            return None
        return (key, payload, str(sample.encoding), time.monotonic_ns()), source, sn

    def _hand_over(self, items: list[tuple[Item, Any, int]], in_order: bool = False) -> None:
        """Admit and pass on, in batches, the samples not handed over before (per publisher,
        a sequence number past the last one handed over; a sample without one always);
        ``in_order``: batches the daemon takes as given (:class:`InOrder`)."""
        last = self._last_sn
        kind = InOrder if in_order else list
        batch: list[Item] = kind()
        dropped: Counter[str] = Counter()
        for item, source, sn in items:
            if source is not None:
                if sn <= last.get(source, -1):
                    continue
                last[source] = sn
            if self._admit(item, dropped):
                batch.append(item)
            if len(batch) >= self._batch:
                self._loop.call_soon_threadsafe(self._daemon.enqueue, batch)
                batch = kind()
        if batch:
            self._loop.call_soon_threadsafe(self._daemon.enqueue, batch)
        if dropped:  # one report per key per batch: a flood of drops must not flood the loop
            self._loop.call_soon_threadsafe(self._daemon.report_drops, dropped)

    def _pump(self) -> None:
        handler = self._subscriber.handler
        try:
            while True:
                sample = handler.recv()  # raises ZError once undeclared and drained
                batch = []
                while sample is not None:
                    if (item := self._own(sample)) is not None:
                        batch.append(item)
                    if len(batch) >= self._batch:
                        break
                    sample = handler.try_recv()
                with self._lock:
                    if self._held is not None:  # histories still on their way: their keys' samples wait for them
                        awaited = self._awaited
                        waiting = [it for it in batch if awaited is None or it[0][0] in awaited]
                        self._held += waiting
                        if len(waiting) < len(batch):
                            self._hand_over([it for it in batch if awaited is not None and it[0][0] not in awaited])
                    else:
                        self._hand_over(batch)
        except zenoh.ZError:
            pass  # channel closed by stop(): intake is over
        finally:
            self._closed.set()

    def _on_miss(self, miss: zenoh.ext.Miss) -> None:
        """On a Zenoh thread: blocks lost for good. Counted here, and reported at once as an
        ``unrecovered`` ErrorReport on the publisher's key: the pipeline flags the gap on the
        channel's next estimate, but the last blocks of a stream that ends (or pauses) have
        no next estimate, and their loss must still be told (a failover test waited for the
        estimate of a lost last block)."""
        self.counters.unrecovered += miss.nb
        key = self._key_of.get(str(miss.source))
        log.warning("intake: %d block(s) of %s could not be recovered", miss.nb, key or f"publisher {miss.source}")
        if key is not None:
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile: the daemon is gone
                self._loop.call_soon_threadsafe(self._daemon.report_unrecovered, key, miss.nb)

    def _admit(self, item: Item, dropped: Counter[str]) -> bool:
        """Take room for an input: one block, or one per channel of a multi-channel frame
        (``queue_capacity`` counts blocks, so a backlog of frames holds as many samples as
        one of blocks)."""
        self.counters.received += 1
        weight = self.weight(item[1])
        taken = 0
        while taken < weight and self._room.acquire(blocking=False):
            taken += 1
        if taken == weight:
            return True
        if self._policy == "drop":
            self.release(taken)
            self.counters.dropped += 1
            dropped[item[0]] += 1
            return False
        self.counters.backpressure_waits += 1
        while taken < weight:
            if self._room.acquire(timeout=0.5):  # wake up to notice a forced exit
                taken += 1
            elif self._daemon.force_exit.is_set():
                self.release(taken)
                return False
        return True

    def weight(self, payload: bytes) -> int:
        """The room an input takes: a binary frame's channel count (its header's u16 at offset 6,
        read without decoding; at most the whole queue), else 1."""
        if payload[:4] == FRAME_MAGIC and len(payload) >= 8:
            return max(1, min(int.from_bytes(payload[6:8], "little"), self._capacity))
        return 1

    def release(self, n: int) -> None:
        if n:
            self._room.release(n)

    async def stop(self) -> None:
        """Stop intake: no new inputs; everything already received is handed over."""
        # Not under self._lock: the pump can hold it for as long as it waits for room in the
        # queue, which only this event loop frees; taking it here deadlocked a deposed owner
        # (it never stood by again, so its shard had no successor). One assignment: atomic.
        self._stopping = True
        loop = asyncio.get_running_loop()
        # Off the event loop too: undeclaring takes zenoh-ext's lock, which a Zenoh thread holds
        # while it waits for room in the FIFO, which the pump frees once the event loop frees
        # room in the queue; undeclared on the loop, two deposed owners hung for good when etcd
        # restarted (no "standby" after "no longer the owner", no admin answers)
        await loop.run_in_executor(None, self._undeclare)
        await loop.run_in_executor(None, self._closed.wait)

    def _undeclare(self) -> None:
        if self._miss_listener is not None:
            self._miss_listener.undeclare()
        self._subscriber.undeclare()
