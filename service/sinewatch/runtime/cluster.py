"""Beyond one daemon: key-space shards, an admin queryable, and shard ownership on etcd.

Shards. A daemon owns the input keys of ``keys.input``, optionally cut by
``cluster.shard = "i/N"``: it keeps the keys whose CRC-32 (of the UTF-8 key) modulo N is
i - 1 (:class:`Shard`), so N daemons with ``1/N`` .. ``N/N`` split the channels with no
overlap and no gap, whatever the keys are. Every daemon answers the queryable
``<admin>/<daemon_id>/channels`` (:meth:`ClusterMember.admin_reply`): its shard, its role,
its term and each channel it serves, with the time of its last estimate; ``sinewatch
status`` asks them all.

Ownership. With ``cluster.etcd`` set, the daemons of one shard (one ``shard_id``) elect
its owner on an etcd lease (:mod:`sinewatch.runtime.election`): the winner serves the shard and
stamps every estimate and snapshot with the election's term (the fencing token); it
publishes only while it can prove its lease alive (the daemon holds its inputs back
while the gate is shut) and stands down when it cannot for a whole TTL. The others
stand by: they keep the newest snapshot of the shard (``<admin>/shard/<shard_id>/snapshot``,
put by the owner every ``snapshot_interval_s``, tagged with its term), note the last
estimate published per channel, and campaign; warm, they run one block of each kind of
channel through a throwaway pipeline when the first snapshot comes, and restore the newest
snapshot as soon as etcd says the owner's lease is running out. The one elected next
restores the snapshot (unless restored ahead), marks where the old owner left each channel (:class:`sinewatch.core.pipeline.ResumePoint`),
starts a new MCAP file (which carries that state and the new term, so it replays on its
own) and subscribes to the inputs. Blocks Zenoh's history brings again up to the last
published one update the state without being published a second time; the first block
after it is published, its ``gap_blocks`` counting the blocks nobody estimated.

Zenoh liveliness tokens (``.../active/<daemon_id>``, ``.../standby/<daemon_id>``) only say
who is there; they decide nothing. Without ``cluster.etcd`` a daemon owns its shard alone
(a worker of ``serve --workers`` too: its supervisor restarts it from its snapshots).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import re
import threading
import time
import zlib
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import zenoh

from sinewatch.core.pipeline import Pipeline, ResumePoint
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.runtime.election import LeaseElection
from sinewatch.schemas.codec import Block, encode_block_binary
from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.messages import Fencing

log = logging.getLogger("sinewatch.runtime.cluster")

ADMIN_QUERY_TIMEOUT_S = 2.0
ADMIN_QUERY_RING = 64  # admin queries waiting for an answer; past it the oldest goes unanswered (its asker times out)
SNAPSHOT_RING = 2  # snapshots waiting to be read by a standby: only the newest counts
# Estimates a standby may fall behind by (10 s of 100 channels at 10 blocks/s): a ring, past it the
# oldest go (only each channel's newest counts), so that a standby starved of CPU never stops Zenoh's
# thread reading its link; a FIFO there, full, did, and the router, pushing it the owner's estimates
# with BLOCK, stopped reading the owner's link (its estimates, its snapshots) for everyone
STANDBY_ESTIMATE_RING = 10_000
READER_JOIN_S = 0.5  # the longest a takeover waits for the standby's reader to note what its FIFO held


class IntakeCount(Protocol):
    not_owned: int


class Host(Protocol):
    """What a cluster member needs of its daemon (:class:`sinewatch.runtime.daemon.Daemon`)."""

    config: SinewatchConfig
    recorder: McapRecorder | None

    @property
    def session(self) -> zenoh.Session: ...
    @property
    def pipeline(self) -> Pipeline: ...
    def start_intake(self, history_blocks: int | None = None) -> None: ...
    async def stop_intake(self) -> None: ...
    def intake_counters(self) -> IntakeCount: ...


@dataclass(frozen=True)
class Shard:
    """``i/N``: the input keys whose CRC-32 modulo N is i - 1."""

    index: int
    count: int

    @classmethod
    def parse(cls, spec: str) -> Shard:
        i, n = (int(x) for x in spec.split("/"))
        return cls(i, n)

    def owns(self, key: str) -> bool:
        return shard_of(key, self.count) == self.index

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def shard_of(key: str, count: int) -> int:
    """The shard (1..count) that owns input key ``key``: stable across processes, machines
    and Python versions (CRC-32 of the UTF-8 key, not ``hash()``)."""
    return zlib.crc32(key.encode("utf-8")) % count + 1


def worker_of(key: str, workers: int, shards: int = 1) -> int:
    """The worker process (1..workers) that runs input key ``key`` (``serve --workers``).
    The CRC-32 is divided by the shard count before the modulo: within one shard (a fixed
    CRC-32 mod ``shards``) the keys still spread evenly over the workers."""
    return zlib.crc32(key.encode("utf-8")) // shards % workers + 1


@dataclass(frozen=True)
class Ownership:
    """The input keys this process runs: its shard (``cluster.shard``) and, in a worker
    process, its share of the shard (``workers.index`` of ``workers.count``)."""

    shard: Shard | None
    worker: int | None
    workers: int

    @classmethod
    def of(cls, config: SinewatchConfig) -> Ownership | None:
        """None when the process owns every key of ``keys.input``."""
        shard = Shard.parse(config.cluster.shard) if config.cluster.shard else None
        worker = config.workers.index
        if shard is None and worker is None:
            return None
        return cls(shard, worker, max(config.workers.count, 1))

    def owns(self, key: str) -> bool:
        if self.shard is not None and not self.shard.owns(key):
            return False
        shards = self.shard.count if self.shard is not None else 1
        return self.worker is None or worker_of(key, self.workers, shards) == self.worker


def shard_id_of(config: SinewatchConfig) -> str:
    """The configured ``cluster.shard_id``, or one made from ``keys.input`` and the shard;
    a worker process's (``serve --workers``) ends in ``_w<i>of<N>``, so the workers of one
    daemon are not each other's standbys, and a standby daemon's worker i watches worker i."""
    worker = f"_w{config.workers.index}of{config.workers.count}" if config.workers.index is not None else ""
    if config.cluster.shard_id:
        return config.cluster.shard_id + worker
    base = re.sub(r"[^A-Za-z0-9_.\-]+", "_", config.keys.input.replace("/**", "")).strip("_") or "all"
    return (f"{base}_{config.cluster.shard.replace('/', 'of')}" if config.cluster.shard else base) + worker


def last_published(pipeline: Pipeline) -> dict[str, tuple[int, int]]:
    """Per channel, (seq, timestamp_ns) of the last block whose estimates this daemon has
    published: its last block, or, while estimates wait in the hold (``hold_estimates``), the
    block before the first one held (its timestamp one mean block length before that one's)."""
    out: dict[str, tuple[int, int]] = {}
    for ch in pipeline.channels.values():
        if ch.last_seq is None or ch.next_t0_ns is None:
            continue
        if ch.held:
            first = json.loads(ch.held[0][0])
            block_ns = round(1e9 * ch.samples / ch.blocks / ch.sample_rate_hz) if ch.blocks else 0
            out[ch.name] = (int(first["seq"]) - 1, int(first["timestamp_ns"]) - block_ns)
        else:
            out[ch.name] = (ch.last_seq, ch.next_t0_ns - round(1e9 / ch.sample_rate_hz))
    return out


class ClusterMember:
    """One daemon's part in the cluster (see the module docstring). Created and driven by
    :class:`sinewatch.runtime.daemon.Daemon` on its event loop; Zenoh callbacks only hand over."""

    def __init__(self, daemon: Host) -> None:
        cfg = daemon.config
        self.daemon = daemon
        self.shard = Shard.parse(cfg.cluster.shard) if cfg.cluster.shard else None
        self.shard_id = shard_id_of(cfg)
        admin = cfg.keys.admin_prefix.rstrip("/")
        base = f"{admin}/shard/{self.shard_id}"
        self.admin_key = f"{admin}/{cfg.daemon_id}/channels"
        self.active_key = f"{base}/active/{cfg.daemon_id}"
        self.standby_key = f"{base}/standby/{cfg.daemon_id}"
        self.snapshot_key = f"{base}/snapshot"
        self.role = "starting"
        self.takeovers = 0
        self.term: int | None = None  # the term this daemon owns the shard under (None: no election)
        self.newest_term: int | None = None  # the newest term of the shard seen (own, snapshots, estimates)
        self.election: LeaseElection | None = None
        if cfg.cluster.etcd is not None:
            key = f"{admin}/election/{self.shard_id}"
            self.election = LeaseElection(cfg.cluster.etcd, key, cfg.daemon_id, cfg.cluster.lease_ttl_s)
            self.election.on_expiring = self._prepare
        # set on a Zenoh thread (one reference assignment each): (term, payload, monotonic arrival, decoded)
        # of the newest
        self.latest_snapshot: tuple[int, bytes, float, dict[str, Any]] | None = None
        self._restored: tuple[int, bytes, float, dict[str, Any]] | None = None  # the snapshot in the pipeline now
        self._warmed: set[str] = set()  # the channel kinds (estimator, params, rate, block length) run once here
        self._warm_asked = False
        self.published: dict[str, tuple[int, int]] = {}  # channel -> (seq, timestamp_ns) the owner published
        self._stepped_down: float | None = None  # monotonic: when this daemon last stopped serving (its state's age)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._watch: list[Any] = []  # the standby's subscribers
        self._reader: threading.Thread | None = None  # the standby's thread draining the estimates' FIFO
        self._queryable: Any = None
        self._tasks: set[asyncio.Task[None]] = set()

    # ---- start ---------------------------------------------------------------------------------
    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        # Queries into a ring a thread of this daemon answers, not a Python callback on Zenoh's
        # receiving thread: that callback waited for the event loop (up to ADMIN_QUERY_TIMEOUT_S a
        # query) and for the GIL, and meanwhile Zenoh read nothing more from the router; the router,
        # pushing this daemon a BLOCK message (a snapshot, a query), then stopped reading the
        # sender's link for everyone: a takeover's history queries sent in that time waited out
        # their 10 s (a 50-fault chaos run, while a killed daemon was starting again)
        self._queryable = self.daemon.session.declare_queryable(
            self.admin_key, zenoh.handlers.RingChannel(ADMIN_QUERY_RING)
        )
        threading.Thread(
            target=self._drain, args=(self._queryable.handler, self._on_query), name="sinewatch-admin", daemon=True
        ).start()
        if self.election is None:
            self._activate()  # no election: this daemon owns its keys alone
            return
        self._stand_by()
        self._spawn(self._elect_forever())

    def _session(self) -> zenoh.Session:
        return self.daemon.session

    def may_publish(self) -> bool:
        """The gate the daemon checks before each input: always open without an election."""
        return self.election is None or self.election.may_publish()

    def may_release_held(self) -> bool:
        """Whether the estimates the pipeline holds back are this daemon's to publish: only once
        it serves the shard (``active``: a takeover has re-stamped or dropped its predecessor's
        held estimates, :meth:`Daemon.start_intake`) and while its lease is proven. The gate alone
        is not enough: it opens the moment the election is won, before the takeover has run, and a
        standby's restored state holds estimates stamped with the previous owner's term."""
        return self.role == "active" and self.may_publish()

    async def wait_gate(self) -> bool:
        """Wait until this daemon may publish again (True) or has lost the shard (False)."""
        return self.election is None or await self.election.wait_gate()

    async def _elect_forever(self) -> None:
        election = self.election
        assert election is not None
        if self.daemon.config.cluster.role == "standby":  # the intended owner wins a cold start
            await asyncio.sleep(election.ttl_s)
        while self.role != "stopped":
            won = await election.campaign()
            if self.role == "stopped":
                return
            self.take_over(won.term)
            await election.hold()
            if self.role == "stopped":
                return
            await self._step_down()

    # ---- active ----------------------------------------------------------------------------------
    def _activate(self, history_blocks: int | None = None) -> None:
        # Subscribed first: the token says "serving", and a publisher that sees it may send at once.
        self.daemon.start_intake(history_blocks)
        self._set_token(self.active_key)
        self.role = "active"
        self._spawn(self._publish_snapshots())
        log.info(
            "cluster: active for shard %s (%s), term %s",
            self.shard_id,
            self.shard or self.daemon.config.keys.input,
            self.term,
        )

    async def _publish_snapshots(self) -> None:
        """Every ``snapshot_interval_s``, the state of every channel for whoever takes over
        from this daemon: a standby, or the supervisor of a worker. None listening, none is
        built: at 1,000 channels a snapshot took ~7 % of the event loop's time, tens of
        milliseconds at a time (py-spy on the daemon during ``sinewatch bench e2e --channels
        1000``). Only while the lease is proven alive, tagged with the term (attachment)."""
        interval = self.daemon.config.cluster.snapshot_interval_s
        # BLOCK, not Zenoh's default DROP: a snapshot is ~180 kB at 50 ipdft channels, sent in fragments, and
        # dropped whole when the link's queue is full, as it is when an owner works off a backlog. A standby
        # then took over from a snapshot 3 s older than the owner's last estimate (seq 2 against 15 in a failover
        # round beside four CPU burners): 14 blocks a channel to catch up instead of ~5
        publisher = self._session().declare_publisher(
            self.snapshot_key,
            encoding=zenoh.Encoding("application/json"),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        term = self.term
        try:
            while self.role == "active" and self.term == term:
                await asyncio.sleep(interval)
                try:
                    if not publisher.matching_status.matching or not self.may_publish():  # type: ignore[attr-defined]
                        continue
                    # What the state covers is on disk first: a restart from it loses no recorded input.
                    self.daemon.pipeline.flush_sinks()
                    payload = json.dumps(self.daemon.pipeline.snapshot(), separators=(",", ":")).encode()
                    publisher.put(payload, attachment=str(term or 0))
                except Exception:  # a failed put (session closing) must not end the timer
                    log.exception("cluster: snapshot not published")
        finally:
            with contextlib.suppress(zenoh.ZError):
                publisher.undeclare()  # type: ignore[no-untyped-call]

    async def _step_down(self) -> None:
        """The lease is lost (or unprovable for a TTL): stop taking inputs, remember where
        each channel was published up to, and stand by. What was held back behind the gate
        is the successor's (it resumes after the last published estimate)."""
        log.warning("cluster: no longer the owner of shard %s (term %s): standing by", self.shard_id, self.term)
        self.role = "standby"
        pipeline = self.daemon.pipeline
        # Before the intake stops: it drops what the channels hold, which this daemon never published
        self.published.update(last_published(pipeline))
        holding = [ch.name for ch in pipeline.channels.values() if ch.held]
        await self.daemon.stop_intake()
        for name in holding:
            # Its state is past the estimates just dropped: re-elected on it, this daemon took the blocks held
            # for published ones and never published them, nor flagged them (a block lost without a gap in a
            # failover round, the owner re-elected after its own lease ran out at load 37). Without it, the
            # next takeover restores the channel from a snapshot, or from the publishers' history.
            pipeline.channels.pop(name, None)
        self.term = None
        self._stepped_down = time.monotonic()
        self._stand_by()

    # ---- standby ---------------------------------------------------------------------------------
    def _stand_by(self) -> None:
        session = self._session()
        self._set_token(self.standby_key)
        self.role = "standby"
        # The cluster's every estimate into a FIFO a thread of this daemon drains, not a Python callback on
        # Zenoh's receiving thread: that thread took the GIL once an estimate, waiting up to Python's switch
        # interval each time while this process's main thread was busy (loading its kernels at start); at 1,000
        # estimates a second it fell seconds behind, and the owner's snapshots queued behind the estimates
        # (a takeover from a snapshot 6 s old beside four CPU burners: 783 blocks to catch up, 4.2 s)
        estimates = session.declare_subscriber(
            f"{self.daemon.config.keys.estimates_prefix}/**", zenoh.handlers.RingChannel(STANDBY_ESTIMATE_RING)
        )
        # the newest snapshots in a ring (only the newest counts), read on a thread: no Python on Zenoh's thread
        snapshots = session.declare_subscriber(self.snapshot_key, zenoh.handlers.RingChannel(SNAPSHOT_RING))
        threading.Thread(
            target=self._drain, args=(snapshots.handler, self._on_snapshot), name="sinewatch-snapshots", daemon=True
        ).start()
        self._watch = [snapshots, estimates]
        self._reader = threading.Thread(
            target=self._read_estimates, args=(estimates.handler,), name="sinewatch-standby", daemon=True
        )
        self._reader.start()
        log.info("cluster: standby for shard %s", self.shard_id)

    def _read_estimates(self, handler: Any) -> None:
        with contextlib.suppress(zenoh.ZError):  # raised once undeclared and drained
            while True:
                self._on_estimate(handler.recv())

    @staticmethod
    def _drain(handler: Any, on_item: Any) -> None:
        """Hand each item of a Zenoh channel to ``on_item`` on this thread, until it is undeclared."""
        with contextlib.suppress(zenoh.ZError):  # raised once undeclared and drained
            while True:
                on_item(handler.recv())

    def _unwatch(self) -> None:
        """Undeclare the standby's subscribers and wait (briefly) until what the estimates' FIFO
        still held is noted: ``published`` is read next, on this thread."""
        for sub in self._watch:
            sub.undeclare()
        self._watch = []
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.join(timeout=READER_JOIN_S)

    def _on_snapshot(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        try:  # only a daemon may put here (the router's access control); still, keep only snapshots
            decoded = json.loads(payload)  # kept decoded: a takeover restores it at once
            ok = isinstance(decoded.get("channels"), list)
            term = int(sample.attachment.to_string()) if sample.attachment is not None else 0
        except (ValueError, AttributeError):
            ok = False
        if not ok:
            log.warning("cluster: %d bytes on %s are not a snapshot: ignored", len(payload), self.snapshot_key)
            return
        latest = self.latest_snapshot
        if latest is None or term >= latest[0]:  # an older term's late snapshot never replaces a newer one
            self.latest_snapshot = (term, payload, time.monotonic(), decoded)
            loop = self._loop
            if not self._warm_asked and loop is not None and not loop.is_closed():
                self._warm_asked = True
                loop.call_soon_threadsafe(self._warm, decoded)
            self._note_term(term)

    def _on_estimate(self, sample: zenoh.Sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
            fencing = msg.get("fencing")
            if fencing is not None:
                if fencing["shard"] != self.shard_id:
                    return  # another shard's channel: never ours to resume
                if self.newest_term is not None and fencing["term"] < self.newest_term:
                    return  # a deposed owner's late estimate: not what the shard's readers keep
                self._note_term(int(fencing["term"]))
            self.published[msg["channel"]] = (int(msg["seq"]), int(msg["timestamp_ns"]))
        except (ValueError, KeyError, TypeError):
            return  # not an Estimate: nothing to note

    def _note_term(self, term: int) -> None:
        if term and (self.newest_term is None or term > self.newest_term):
            self.newest_term = term

    def _warm(self, snapshot: dict[str, Any]) -> None:
        """Run one block through a throwaway pipeline for each kind of channel in ``snapshot``
        not run here before (on the event loop, while standing by): what a channel's first
        block costs once per process then is not paid at the takeover. ``warm_up`` at start
        loads the estimators' kernels with example parameters only; a channel's own (e.g. the
        interpolated DFT's uncertainty tables for its window: 0.12 s with its kernels, quiet)
        came with the first block the new owner processed."""
        started = time.monotonic()
        kinds: dict[str, dict[str, Any]] = {}
        for item in snapshot.get("channels", []):
            try:
                length = round(item["samples"] / item["blocks"]) if item.get("blocks") else 0
                kind = json.dumps(
                    [
                        item["estimator"].get("estimator"),
                        item["estimator"].get("params"),
                        item["sample_rate_hz"],
                        length,
                    ]
                )
            except (KeyError, TypeError, AttributeError, ValueError, ZeroDivisionError):
                # not a channel's state (a forged snapshot's: the router's access control keeps them out): nothing
                # to warm up; it raised out of this callback, logged as an error of the event loop
                log.warning("cluster: a snapshot's channel without its state: not warmed up")
                continue
            if length > 0 and kind not in self._warmed:
                kinds.setdefault(kind, item)
        if not kinds:
            return
        rng = np.random.default_rng(0)  # seeded: the same throwaway block every time
        for kind, item in kinds.items():
            self._warmed.add(kind)
            length = round(item["samples"] / item["blocks"])
            scratch = Pipeline(self.daemon.config, [])
            try:
                scratch.restore({"channels": [item]})
                seq = (item["last_seq"] or 0) + 1
                block = Block(
                    item["name"],
                    seq,
                    item["next_t0_ns"] or 0,
                    float(item["sample_rate_hz"]),
                    rng.standard_normal(length),
                )
                scratch.process(item["key"], encode_block_binary(block), "", time.time_ns())
            except Exception:  # a warm-up that fails costs the takeover its time, nothing else
                log.exception("cluster: warming up for %s failed", item.get("name"))
        log.info("cluster: %d kind(s) of channel warmed up in %.0f ms", len(kinds), (time.monotonic() - started) * 1e3)

    def _prepare(self) -> None:
        """A warm standby: the owner's lease is running out (etcd says under a second left, no
        keep-alive since), so restore the newest snapshot into the pipeline now, while the lease
        lasts, rather than after the election (restoring 50 channels took 6-450 ms, 1.1 s once
        under load, all of it between the election and the first estimate). Nothing is served
        from it until this daemon is elected; a snapshot that comes later is restored then."""
        if self.role != "standby" or self.latest_snapshot is None or self.latest_snapshot is self._restored:
            return
        self._warm(self.latest_snapshot[3])
        started = time.monotonic()
        self._restore(self.latest_snapshot)
        log.info(
            "cluster: the owner's lease is running out: snapshot restored in %.0f ms",
            (time.monotonic() - started) * 1e3,
        )

    def _restore(self, latest: tuple[int, bytes, float, dict[str, Any]]) -> None:
        pipeline = self.daemon.pipeline
        if self._restored is not None:  # an earlier one restored ahead: start from this one alone
            pipeline.channels.clear()
            pipeline.resume_points.clear()
        self._restored = latest
        try:
            pipeline.restore(latest[3])
        except Exception:  # a snapshot that does not restore must not stop the takeover
            log.exception("cluster: the snapshot of shard %s does not restore; serving from scratch", self.shard_id)
            pipeline.channels.clear()
            pipeline.resume_points.clear()

    def take_over(self, term: int | None = None) -> None:
        """Restore the newest snapshot (unless restored ahead, :meth:`_prepare`), mark where the
        previous owner left each channel, serve the shard and start a new recording file (with
        this state and ``term``)."""
        started = time.monotonic()
        succeeds = self.latest_snapshot is not None or bool(self.published)  # not a cold start: someone served
        self._unwatch()
        pipeline = self.daemon.pipeline
        latest = self.latest_snapshot
        restored_ahead = latest is not None and latest is self._restored
        if latest is not None and not restored_ahead:
            self._restore(latest)
        self._restored = None  # served from here: the pipeline's state is this daemon's own
        for name, (seq, timestamp_ns) in dict(self.published).items():  # a copy: a reader left running adds to it
            ch = pipeline.channels.get(name)
            next_t0 = timestamp_ns + round(1e9 / ch.sample_rate_hz) if ch is not None else None
            if ch is None or ch.last_seq is None or ch.last_seq < seq:
                pipeline.resume_points[name] = ResumePoint(seq, next_t0)
        self.term = term
        self._note_term(term or 0)
        pipeline.set_fencing(Fencing(shard=self.shard_id, term=term) if term is not None else None)
        self.takeovers += succeeds
        history = self._history_needed()
        # Subscribed (and the history asked for) before the new file is written: the query's round
        # trip overlaps the recording's snapshot. Nothing reaches the pipeline before this returns
        # (the intake hands over through this event loop), so the new file still holds every input.
        self._activate(history)
        if self.daemon.recorder is not None:
            self.daemon.recorder.rotate()  # the new file carries this state and term: it replays on its own
        log.warning(
            "cluster: took over shard %s (term %s): %d channel(s) from the snapshot%s%s, %d resume point(s), "
            "history %s block(s) per key, in %.0f ms",
            self.shard_id,
            term,
            len(pipeline.channels),
            "" if latest is None else f" (received {started - latest[2]:.2f} s before)",
            " (restored ahead)" if restored_ahead else "",
            len(pipeline.resume_points),
            "all" if history is None else history,
            (time.monotonic() - started) * 1e3,
        )

    def _history_needed(self) -> int | None:
        """How many of each key's newest blocks a takeover asks the publishers' caches for:
        those since the snapshot it restored (or since it stood down, re-elected on its own
        state), twice over (None, all they hold, with neither).
        The whole cache (1,024 blocks per key by default) would be read, recorded and
        skipped before the first new block is estimated: after a minute of 100 channels at
        10 blocks/s, that held a takeover's first estimate back by seconds under load."""
        latest = self.latest_snapshot
        if latest is not None:
            since_s = time.monotonic() - latest[2] + self.daemon.config.cluster.snapshot_interval_s
        elif self._stepped_down is not None:  # re-elected on its own state (no snapshot came since it stood down)
            since_s = time.monotonic() - self._stepped_down
        else:
            return None
        rates = [  # blocks per second of each channel, from its mean block length
            ch.sample_rate_hz * ch.blocks / ch.samples
            for ch in self.daemon.pipeline.channels.values()
            if ch.blocks and ch.samples
        ]
        if not rates:
            return None
        return 2 * math.ceil(since_s * max(rates)) + 16

    # ---- admin -----------------------------------------------------------------------------------
    def admin_reply(self) -> dict[str, Any]:
        """What this daemon owns (or would take over), for ``sinewatch status``."""
        cfg = self.daemon.config
        if self.role == "active":
            channels = [
                {
                    "channel": ch.name,
                    "key": ch.key,
                    "estimator": ch.estimator.name,
                    "last_seq": ch.last_seq,
                    "last_estimate_ns": None
                    if ch.next_t0_ns is None
                    else ch.next_t0_ns - round(1e9 / ch.sample_rate_hz),
                }
                for ch in self.daemon.pipeline.channels.values()
            ]
        else:  # what it would take over: the channels of the latest snapshot, as last published
            latest = self.latest_snapshot
            snapshot = latest[3] if latest is not None else {"channels": []}
            channels = []
            for item in snapshot["channels"]:
                seq, ts = self.published.get(item["name"], (item["last_seq"], None))
                channels.append(
                    {
                        "channel": item["name"],
                        "key": item["key"],
                        "estimator": item["estimator"]["estimator"],
                        "last_seq": seq,
                        "last_estimate_ns": ts,
                    }
                )
        election = self.election
        return {
            "daemon_id": cfg.daemon_id,
            "shard_id": self.shard_id,
            "shard": str(self.shard) if self.shard else None,
            "input": cfg.keys.input,
            "role": self.role,
            "term": self.term,
            "newest_term": self.newest_term,
            "lease_proven": None if election is None else election.may_publish(),
            "takeovers": self.takeovers,
            "not_owned": self.daemon.intake_counters().not_owned,
            "channels": sorted(channels, key=lambda c: c["channel"]),
        }

    def _on_query(self, query: zenoh.Query) -> None:
        """On the admin thread: the reply is built on the event loop (which owns the pipeline)."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        future = asyncio.run_coroutine_threadsafe(self._admin_json(), loop)
        try:
            payload = future.result(timeout=ADMIN_QUERY_TIMEOUT_S)
        except Exception as exc:  # noqa: BLE001 (a query must never take the daemon down)
            log.warning("cluster: admin query not answered: %s", exc)
            return
        query.reply(self.admin_key, payload, encoding="application/json")

    async def _admin_json(self) -> bytes:
        return json.dumps(self.admin_reply(), separators=(",", ":")).encode()

    # ---- plumbing --------------------------------------------------------------------------------
    def _set_token(self, key: str) -> None:
        if self._token is not None:
            self._token.undeclare()  # type: ignore[no-untyped-call]
        self._token = self._session().liveliness().declare_token(key)

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._done)

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("cluster: task failed", exc_info=task.exception())

    async def close(self) -> None:
        """After the daemon's last estimate: give the shard up (the lease is revoked, so a
        standby takes over at once rather than after the TTL)."""
        self.role = "stopped"
        for task in self._tasks:
            task.cancel()
        self._unwatch()
        if self._queryable is not None:
            self._queryable.undeclare()
        if self._token is not None:
            self._token.undeclare()  # type: ignore[no-untyped-call]
            self._token = None
        if self.election is not None:
            await self.election.close()
