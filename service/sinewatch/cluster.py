"""Beyond one daemon: key-space shards, an admin queryable, and hot standby over Zenoh.

Shards. A daemon owns the input keys of ``keys.input``, optionally cut by
``cluster.shard = "i/N"``: it keeps the keys whose CRC-32 (of the UTF-8 key) modulo N is
i - 1 (:class:`Shard`), so N daemons with ``1/N`` .. ``N/N`` split the channels with no
overlap and no gap, whatever the keys are. Every daemon answers the queryable
``<admin>/<daemon_id>/channels`` (:meth:`ClusterMember.admin_reply`): its shard, its role
and each channel it serves, with the time of its last estimate; ``sinewatch status`` asks
them all.

Hot standby. The daemons of one shard share a ``shard_id``. The active one holds the
liveliness token ``<admin>/shard/<shard_id>/active/<daemon_id>`` and puts the state of its
channels (the pipeline snapshot a rotated MCAP file starts with) on
``<admin>/shard/<shard_id>/snapshot`` every ``snapshot_interval_s``. A standby holds
``.../standby/<daemon_id>``, keeps the latest snapshot, notes the last estimate the active
published per channel, and watches the active token. When it goes away (the daemon died,
or its session did) and the standby still reaches the Zenoh network, the standby takes
over: it restores the snapshot, marks where the active left each channel
(:class:`sinewatch.pipeline.ResumePoint`), starts a new MCAP file (which carries that
state, so it replays on its own) and subscribes to the inputs. Blocks Zenoh's history
brings again up to the last published one update the state without being published a
second time; the first block after it is published, its ``gap_blocks`` counting the
blocks nobody estimated (none when the publishers' caches covered the outage). A daemon
that starts while its shard already has an active one stands by, so a daemon that comes
back after a failover never publishes beside its successor.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import threading
import time
import zlib
from dataclasses import dataclass
from typing import Any, Protocol

import zenoh

from sinewatch.pipeline import Pipeline, ResumePoint
from sinewatch.recorder import McapRecorder
from sinewatch.schemas.config import SinewatchConfig

log = logging.getLogger("sinewatch.cluster")

ADMIN_QUERY_TIMEOUT_S = 2.0
TAKEOVER_RECHECK_S = 0.25  # while the network is unreachable, how often a standby looks again
RECONNECT_GRACE_S = 5.0  # after that, how long it waits for the active daemon to come back too


class IntakeCount(Protocol):
    not_owned: int


class Host(Protocol):
    """What a cluster member needs of its daemon (:class:`sinewatch.daemon.Daemon`)."""

    config: SinewatchConfig
    recorder: McapRecorder | None

    @property
    def session(self) -> zenoh.Session: ...
    @property
    def pipeline(self) -> Pipeline: ...
    def start_intake(self) -> None: ...
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


class ClusterMember:
    """One daemon's part in the cluster (see the module docstring). Created and driven by
    :class:`sinewatch.daemon.Daemon` on its event loop; Zenoh callbacks only hand over."""

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
        self.active_expr = f"{base}/active/*"
        self.standby_expr = f"{base}/standby/*"
        self.snapshot_key = f"{base}/snapshot"
        self.role = "starting"
        self.takeovers = 0
        self.latest_snapshot: bytes | None = None  # set on a Zenoh thread (one reference assignment)
        self.published: dict[str, tuple[int, int]] = {}  # channel -> (seq, timestamp_ns) the active published
        self._loop: asyncio.AbstractEventLoop | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._watch: list[Any] = []  # the standby's subscribers
        self._queryable: Any = None
        self._checking = False
        self._tasks: set[asyncio.Task[None]] = set()
        self._actives_seen: set[str] = set()  # active tokens of the shard, as the standby's subscriber saw them
        self._lock = threading.Lock()  # _actives_seen: written on a Zenoh thread

    # ---- start ---------------------------------------------------------------------------------
    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._queryable = self.daemon.session.declare_queryable(self.admin_key, self._on_query)
        if self.daemon.config.cluster.role == "standby" or self._other_active():
            self._stand_by()
        else:
            self._activate()

    def _session(self) -> zenoh.Session:
        return self.daemon.session

    def _other_active(self) -> str | None:
        """The daemon id of another active daemon of this shard, if the network knows one:
        from the tokens the liveliness subscriber saw come and go, and from a liveliness
        query (both: either alone was seen to miss a live token in a freshly opened session)."""
        with self._lock:
            seen = sorted(self._actives_seen - {self.active_key})
        if seen:
            return seen[0].rsplit("/", 1)[-1]
        for reply in self._session().liveliness().get(self.active_expr, timeout=ADMIN_QUERY_TIMEOUT_S):
            if reply.ok is not None and str(reply.ok.key_expr) != self.active_key:
                return str(reply.ok.key_expr).rsplit("/", 1)[-1]
        return None

    def _reachable(self) -> bool:
        info = self._session().info
        return bool(list(info.routers_zid()) or list(info.peers_zid()))

    # ---- active ----------------------------------------------------------------------------------
    def _activate(self) -> None:
        # Subscribed first: the token says "serving", and a publisher that sees it may send at once.
        self.daemon.start_intake()
        self._set_token(self.active_key)
        self.role = "active"
        self._spawn(self._publish_snapshots())
        log.info("cluster: active for shard %s (%s)", self.shard_id, self.shard or self.daemon.config.keys.input)

    async def _publish_snapshots(self) -> None:
        """Every ``snapshot_interval_s``, the state of every channel for whoever takes over
        from this daemon: a standby, or the supervisor of a worker. None listening, none is
        built: at 1,000 channels a snapshot took ~7 % of the event loop's time, tens of
        milliseconds at a time (py-spy on the daemon during ``sinewatch bench e2e --channels
        1000``)."""
        interval = self.daemon.config.cluster.snapshot_interval_s
        publisher = self._session().declare_publisher(self.snapshot_key, encoding=zenoh.Encoding("application/json"))
        try:
            while self.role == "active":
                await asyncio.sleep(interval)
                try:
                    if not publisher.matching_status.matching:  # type: ignore[attr-defined]
                        continue
                    # What the state covers is on disk first: a restart from it loses no recorded input.
                    self.daemon.pipeline.flush_sinks()
                    payload = json.dumps(self.daemon.pipeline.snapshot(), separators=(",", ":")).encode()
                    publisher.put(payload)
                except Exception:  # a failed put (session closing) must not end the timer
                    log.exception("cluster: snapshot not published")
        finally:
            with contextlib.suppress(zenoh.ZError):
                publisher.undeclare()  # type: ignore[no-untyped-call]

    # ---- standby ---------------------------------------------------------------------------------
    def _stand_by(self) -> None:
        session = self._session()
        self._set_token(self.standby_key)
        self.role = "standby"
        self._watch = [
            session.declare_subscriber(self.snapshot_key, self._on_snapshot),
            session.declare_subscriber(f"{self.daemon.config.keys.estimates_prefix}/**", self._on_estimate),
            session.liveliness().declare_subscriber(self.active_expr, self._on_active_token, history=True),
        ]
        log.info("cluster: standby for shard %s", self.shard_id)
        if self._loop is not None:  # no active daemon at all: after a grace (it may be starting), take over
            self._loop.call_later(2 * self.daemon.config.cluster.snapshot_interval_s, self._check_takeover)

    def _on_snapshot(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        try:  # only a daemon may put here (the router's access control); still, keep only snapshots
            ok = isinstance(json.loads(payload).get("channels"), list)
        except (ValueError, AttributeError):
            ok = False
        if ok:
            self.latest_snapshot = payload
        else:
            log.warning("cluster: %d bytes on %s are not a snapshot: ignored", len(payload), self.snapshot_key)

    def _on_estimate(self, sample: zenoh.Sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
            self.published[msg["channel"]] = (int(msg["seq"]), int(msg["timestamp_ns"]))
        except (ValueError, KeyError, TypeError):
            return  # not an Estimate: nothing to note

    def _on_active_token(self, sample: zenoh.Sample) -> None:
        with self._lock:
            (self._actives_seen.add if sample.kind == zenoh.SampleKind.PUT else self._actives_seen.discard)(
                str(sample.key_expr)
            )
        if sample.kind == zenoh.SampleKind.DELETE:
            log.warning("cluster: active daemon %s of shard %s is gone", str(sample.key_expr), self.shard_id)
            self._call(self._check_takeover)

    def _check_takeover(self) -> None:
        if self.role == "standby" and not self._checking:
            self._checking = True
            self._spawn(self._takeover_when_alone())

    async def _takeover_when_alone(self) -> None:
        """Take over once the network is reachable and has no active daemon for the shard;
        standbys ranked by id go in turn, so only one of several takes over. After the
        network was unreachable (a router restart), wait a grace period first: the active
        daemon's token comes back with its session, not at once."""
        # Zenoh retries a lost link after 1, 2, 4, 4 ... s: the active daemon may reach the
        # network again up to 4 s after this one, with its token.
        grace = max(2 * self.daemon.config.cluster.snapshot_interval_s, RECONNECT_GRACE_S)
        was_cut_off = False
        try:
            while self.role == "standby":
                if not await asyncio.to_thread(self._reachable):
                    was_cut_off = True
                    await asyncio.sleep(TAKEOVER_RECHECK_S)
                    continue
                if was_cut_off:
                    was_cut_off = False
                    await asyncio.sleep(grace)
                    continue  # look again: still reachable?
                if await asyncio.to_thread(self._other_active) is not None:
                    return  # the active daemon is there (back, or never gone)
                rank = await asyncio.to_thread(self._standby_rank)
                if rank == 0:
                    self.take_over()
                    return
                await asyncio.sleep(rank * self.daemon.config.cluster.snapshot_interval_s)
        finally:
            self._checking = False

    def _standby_rank(self) -> int:
        ids = sorted(
            str(r.ok.key_expr).rsplit("/", 1)[-1]
            for r in self._session().liveliness().get(self.standby_expr, timeout=ADMIN_QUERY_TIMEOUT_S)
            if r.ok is not None
        )
        me = self.daemon.config.daemon_id
        return ids.index(me) if me in ids else 0

    def take_over(self) -> None:
        """Restore the latest snapshot, mark where the active daemon left each channel,
        start a new recording file and serve the shard."""
        started = time.monotonic()
        for sub in self._watch:
            sub.undeclare()
        self._watch = []
        pipeline = self.daemon.pipeline
        if self.latest_snapshot is not None:
            try:
                pipeline.restore(json.loads(self.latest_snapshot))
            except Exception:  # a snapshot that does not restore must not stop the takeover
                log.exception("cluster: the snapshot of shard %s does not restore; serving from scratch", self.shard_id)
                pipeline.channels.clear()
                pipeline.resume_points.clear()
        for name, (seq, timestamp_ns) in self.published.items():
            ch = pipeline.channels.get(name)
            next_t0 = timestamp_ns + round(1e9 / ch.sample_rate_hz) if ch is not None else None
            if ch is None or ch.last_seq is None or ch.last_seq < seq:
                pipeline.resume_points[name] = ResumePoint(seq, next_t0)
        if self.daemon.recorder is not None:
            self.daemon.recorder.rotate()  # the new file carries this state: it replays on its own
        self.takeovers += 1
        self._activate()
        log.warning(
            "cluster: took over shard %s: %d channel(s) from the snapshot, %d resume point(s), in %.0f ms",
            self.shard_id,
            len(pipeline.channels),
            len(pipeline.resume_points),
            (time.monotonic() - started) * 1e3,
        )

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
            snapshot = json.loads(self.latest_snapshot) if self.latest_snapshot is not None else {"channels": []}
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
        return {
            "daemon_id": cfg.daemon_id,
            "shard_id": self.shard_id,
            "shard": str(self.shard) if self.shard else None,
            "input": cfg.keys.input,
            "role": self.role,
            "takeovers": self.takeovers,
            "not_owned": self.daemon.intake_counters().not_owned,
            "channels": sorted(channels, key=lambda c: c["channel"]),
        }

    def _on_query(self, query: zenoh.Query) -> None:
        """On a Zenoh thread: the reply is built on the event loop (which owns the pipeline)."""
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

    def _call(self, fn: Any) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(fn)

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def close(self) -> None:
        self.role = "stopped"
        for task in self._tasks:
            task.cancel()
        for sub in self._watch:
            sub.undeclare()
        self._watch = []
        if self._queryable is not None:
            self._queryable.undeclare()
        if self._token is not None:
            self._token.undeclare()  # type: ignore[no-untyped-call]
            self._token = None
