"""The asyncio daemon: Zenoh intake -> pipeline -> Zenoh publisher + MCAP recorder.

Threading model. Zenoh delivers samples on its own threads into a bounded FIFO channel
(never blocking a Zenoh callback on Python work). One *pump* thread drains that channel
in batches (a blocking ``recv`` then ``try_recv`` up to ``limits.intake_batch``) and
hands each batch to the event loop with one ``call_soon_threadsafe`` (a call per message
would wake the loop once per message, which caps the intake well below what Zenoh
delivers; ``sinewatch bench e2e`` measures the whole path). The event loop runs the
pipeline, so estimator state is only ever touched by one thread.

Backpressure. A counting semaphore bounds the inputs in flight (``limits.queue_capacity``).
With ``queue_policy = "block"`` (default) the pump waits for room, so the Zenoh FIFO
fills and Zenoh pushes back to publishers that use ``CongestionControl.BLOCK``: nothing
is lost, and every wait is counted. With ``"drop"`` the newest input is dropped, counted
and reported as a ``queue_overflow`` ErrorReport.

Shutdown, as uvicorn does it: SIGINT/SIGTERM set ``should_exit``; the daemon stops
intake (undeclares the subscriber, so the pump drains Zenoh's FIFO and ends), processes
everything already accepted, publishes a last Status and finishes the MCAP file. A
second SIGINT sets ``force_exit``: processing stops at the next input, the MCAP file is
still finished, and ``run`` returns 130.

Operations (each off unless configured): ``[foxglove]`` adds a sink that serves the
Foxglove WebSocket protocol (:mod:`sinewatch.outputs.foxglove_live`); ``[metrics]`` serves
Prometheus metrics and ``/healthz`` from a thread (:mod:`sinewatch.outputs.metrics`). Under systemd
(``Type=notify``, :mod:`sinewatch.runtime.sdnotify`) the daemon sends ``READY=1`` once it is
subscribed, ``WATCHDOG=1`` from a heartbeat task on the event loop (a stuck loop stops
it, and systemd restarts the service), and ``STOPPING=1`` when it starts to drain. The
same heartbeat is the "event loop turned" time that ``/healthz`` checks.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import zenoh
import zenoh.ext

from sinewatch.clients.session import open_session
from sinewatch.core.pipeline import Pipeline, ResumePoint, Sink, sanitize_log_time
from sinewatch.outputs.c37118_server import C37118Server
from sinewatch.outputs.publisher import ZenohPublisherSink
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.runtime.cluster import ClusterMember
from sinewatch.runtime.intake import Intake, IntakeCounters, Item, KeyTurns
from sinewatch.runtime.sdnotify import Notifier
from sinewatch.runtime.signals import shutdown_signals
from sinewatch.schemas.codec import encode_status
from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.errors import ConfigError
from sinewatch.schemas.messages import ChannelStatus, SinkStatus, Status

if TYPE_CHECKING:
    from sinewatch.estimators.base import Estimator
    from sinewatch.outputs.foxglove_live import FoxgloveSink
    from sinewatch.outputs.metrics import Health, LatencyHistogram, MetricsServer, Snapshot

log = logging.getLogger("sinewatch.runtime.daemon")

HEARTBEAT_S = 0.5  # the event loop's heartbeat (and systemd watchdog ping), at most this far apart


def _warm_up_rule(cls: type[Estimator[Any]], params: dict[str, Any]) -> None:
    """One rule's kernels: the estimator's on whole blocks and on the last sample only, the
    presence detector's, and for a one-input estimator a frame's (its bank kernel, the
    presence detectors' bank)."""
    from sinewatch.core.estimate_bytes import warm_up_bank_payloads
    from sinewatch.core.float_repr import repr_floats
    from sinewatch.estimators.bank import bank_of, update_bank
    from sinewatch.estimators.base import kernel_samples
    from sinewatch.estimators.presence import SignalPresence, update_presence_bank
    from sinewatch.estimators.presence import _fast_usable as fast_usable

    rate = cls.example_sample_rate_hz
    try:
        cls(rate, params)
    except ValueError:  # ParameterError, or pydantic's ValidationError: valid at another rate only
        params = dict(cls.example_params)
    est = cls(rate, params)
    signal_ = cls.example_signal(64)
    if signal_.ndim == 1 and est.n_inputs > 1:  # e.g. I/Q: the kernel's types, not a meaningful signal
        signal_ = np.column_stack([signal_] * est.n_inputs)
    # one kind of samples: the pipeline hands every kernel float64, C-contiguous, writable
    # arrays whatever the payload's sample type (``kernel_samples``), so one call compiles
    # (or loads) the signature every block of this rule will use
    x = kernel_samples(signal_)
    est.update(x)
    est.update(x, last_only=True)
    SignalPresence(rate).update(est.presence_samples(x))  # a single block's detector (a frame's: below)
    fast_usable(0.0, 0.0, 1.0)  # what the hold (on by default) asks of a detector per block, from Python
    repr_floats(np.array([0.5]))  # every Estimate's floats
    if est.n_inputs == 1:
        warm_up_bank_payloads()  # a bank's Estimates in one call
        frame = kernel_samples(np.stack([signal_, signal_], axis=1))
        if bank_of(cls) is not None:
            update_bank([cls(rate, params), cls(rate, params)], frame, last_only=True)
        detectors = [SignalPresence(rate) for _ in range(2)]
        update_presence_bank(detectors, frame, [0, 1])


class Daemon:
    def __init__(self, config: SinewatchConfig, *, install_signal_handlers: bool = True) -> None:
        self.config = config
        self.install_signal_handlers = install_signal_handlers
        self.should_exit = asyncio.Event()
        self.force_exit = threading.Event()
        self.ready = asyncio.Event()
        self._session: zenoh.Session | None = None
        self._pipeline: Pipeline | None = None
        self.recorder: McapRecorder | None = None
        self.c37118: C37118Server | None = None  # [c37118]: sinewatch as a PMU
        self._intake: Intake | None = None
        self._queue: asyncio.Queue[list[Item] | None] = asyncio.Queue()
        self._queued = 0
        # each input key with inputs received and not processed yet -> its last one's receive
        # time (release_idle: a channel whose next block waits in the queue is not idle)
        self._arrived: dict[str, int] = {}
        self._started = time.monotonic()
        self._last_log_time = 0
        self.cluster: ClusterMember | None = None
        self.handed_over = 0  # inputs received while owning a shard, left to the successor (lost the lease)
        self.notifier = Notifier()
        self.foxglove: FoxgloveSink | None = None
        self.metrics: MetricsServer | None = None
        self._latency: LatencyHistogram | None = None
        self._beat = time.monotonic()  # the event loop's last heartbeat
        self._running = False

    # ---- what start() creates ------------------------------------------------------------------
    @property
    def session(self) -> zenoh.Session:
        return _started(self._session, "session")

    @property
    def pipeline(self) -> Pipeline:
        return _started(self._pipeline, "pipeline")

    @property
    def intake(self) -> Intake:
        return _started(self._intake, "intake")

    # ---- signals -------------------------------------------------------------------------------
    def handle_signal(self, sig: int) -> None:
        if sig == signal.SIGINT and self.should_exit.is_set():
            log.warning("second SIGINT: forcing exit (MCAP file is still finished)")
            self.force_exit.set()
            return
        log.info("%s received: stopping intake, draining", signal.Signals(sig).name)
        self.should_exit.set()

    # ---- intake -> pipeline ---------------------------------------------------------------------
    def enqueue(self, batch: list[Item]) -> None:
        self._queued += len(batch)
        arrived = self._arrived
        for item in batch:
            arrived[item[0]] = item[3]
        self._queue.put_nowait(batch)

    def report_drops(self, dropped: Counter[str]) -> None:
        """Inputs the intake dropped (drop policy), per key: one ErrorReport each, whose
        ``count`` advances by the number dropped; the gap shows on the next estimate."""
        for key, n in dropped.items():
            message = f"intake queue full: {n} input(s) dropped"
            self.pipeline.report_error(key, "queue_overflow", message, self._log_time(), count=n)

    def report_unrecovered(self, key: str, n: int) -> None:
        """``n`` blocks of ``key`` lost in transport that Zenoh's recovery could not fetch again:
        one ErrorReport whose ``count`` advances by ``n``."""
        message = f"{n} block(s) lost in transport and not in the publisher's cache: a gap on the next estimate"
        self.pipeline.report_error(key, "unrecovered", message, self._log_time(), count=n)

    def _log_time(self) -> int:
        self._last_log_time = sanitize_log_time(self._last_log_time, time.time_ns())
        return self._last_log_time

    async def _consume(self) -> None:
        size = self.config.limits.intake_batch
        turns = KeyTurns()  # a backlog of more than a batch (a router's return, a catch-up): the keys in turn
        ending = False
        while True:
            batches: list[list[Item]] = []
            if not turns:
                if ending:
                    return
                first = await self._queue.get()
                if first is None:
                    return
                batches.append(first)
            while not ending and not self._queue.empty():
                batch = self._queue.get_nowait()
                if batch is None:
                    ending = True
                else:
                    batches.append(batch)
            if not turns and sum(map(len, batches)) <= size:  # no backlog: in arrival order
                for batch in batches:
                    await self._consume_batch(batch)
                continue
            for batch in batches:
                turns.add(batch)
            await self._consume_batch(turns.take(size))

    async def _consume_batch(self, batch: list[Item]) -> None:
        try:
            await self._process_gated(batch)
        except Exception:  # the pipeline isolates faults; this is the last line of defence
            log.exception("batch of %d inputs not fully processed", len(batch))
        finally:
            self._queued -= len(batch)
            arrived = self._arrived
            for item in batch:  # a key's inputs are taken in order: its last one taken leaves nothing waiting
                if arrived.get(item[0]) == item[3]:
                    del arrived[item[0]]
            if self._intake is not None:
                intake = self._intake
                intake.release(sum(intake.weight(item[1]) for item in batch))
        # Queue.get() does not yield while batches wait: without this, a backlog would keep
        # the heartbeat, status and flush timers from running until it is gone (a watchdog
        # or a supervisor would then take the busy daemon for a stuck one).
        await asyncio.sleep(0)

    async def _process_gated(self, batch: list[Item]) -> None:
        """Process the batch, block by block, while this daemon may publish (an elected
        owner: while its lease is proven alive). When the gate shuts, the rest waits for it
        to open again; if the shard is lost meanwhile, the rest is the successor's."""
        done = 0
        cluster = self.cluster
        while done < len(batch):
            if cluster is not None and not cluster.may_publish():
                if not await cluster.wait_gate():
                    self.handed_over += len(batch) - done
                    return
            done += self._process(batch, done)
            if self.force_exit.is_set():
                return

    def _process(self, batch: list[Item], start: int = 0) -> int:
        """Process ``batch[start:]`` until its end or the gate shuts; return how many."""
        cluster = self.cluster
        gated = cluster is not None and cluster.election is not None
        n = 0
        for key, payload, encoding, received in batch[start:]:
            if self.force_exit.is_set() or (gated and not cluster.may_publish()):  # type: ignore[union-attr]
                break
            n += 1
            self.pipeline.process(key, payload, encoding, self._log_time(), received)
            if self._latency is not None:
                self._latency.observe_ns(time.monotonic_ns() - received)
        return n

    # ---- periodic tasks -------------------------------------------------------------------------
    def intake_counters(self) -> IntakeCounters:
        return self._intake.counters if self._intake else IntakeCounters()

    def status_payload(self) -> bytes:
        c = self.intake_counters()
        p = self.pipeline
        status = Status(
            daemon_id=self.config.daemon_id,
            uptime_s=round(time.monotonic() - self._started, 3),
            blocks_received=c.received,
            blocks_processed=p.counters.inputs,
            dropped=c.dropped,
            backpressure_waits=c.backpressure_waits,
            unrecovered=c.unrecovered,
            errors=p.counters.errors,
            errors_by_kind=dict(sorted(p.counters.by_kind.items())),
            queue_depth=self._queued,
            recording=str(self.recorder.path) if self.recorder and self.recorder.path else None,
            sinks=[SinkStatus(**s) for s in p.sink_status()],
            channels=[ChannelStatus(**c) for c in p.channel_status()],
            c37118=self.c37118.status() if self.c37118 is not None else None,
        )
        return encode_status(status)

    def publish_status(self) -> None:
        key = f"{self.config.keys.status_key}/{self.config.daemon_id}"
        payload = self.status_payload()
        for sink in self.pipeline.sinks:
            sink.on_status(key, payload, self._log_time())

    def heartbeat(self) -> None:
        """The event loop is turning: note it (``/healthz``) and tell systemd's watchdog."""
        self._beat = time.monotonic()
        self.notifier.watchdog()

    def _heartbeat_s(self) -> float:
        periods = [HEARTBEAT_S, self.config.metrics.stall_s / 4]
        if self.notifier.watchdog_s is not None:
            periods.append(self.notifier.watchdog_s / 2)  # sd_watchdog_enabled(3): ping at half the timeout
        return min(periods)

    # ---- metrics and health (read on the metrics server's thread) -----------------------------
    def metrics_snapshot(self) -> Snapshot:
        from sinewatch.outputs.metrics import LatencyHistogram, Snapshot

        c = self._intake.counters if self._intake else IntakeCounters()
        p = self._pipeline
        rec = self.recorder
        return Snapshot(
            blocks_received=c.received,
            blocks_processed=p.counters.inputs if p else 0,
            estimates=p.counters.estimates if p else 0,
            rejections_by_kind=dict(p.counters.by_kind) if p else {},
            dropped=c.dropped,
            backpressure_waits=c.backpressure_waits,
            unrecovered=c.unrecovered,
            queue_depth=self._queued,
            channels=len(p.channels) if p else 0,
            recording_bytes=sum(_size(path) for path in list(rec.paths)) if rec else 0,
            recording_messages=rec.messages_written if rec else 0,
            sinks=p.sink_status() if p else [],
            cpu_seconds_by_worker={"0": time.process_time()},  # one process today; workers come later
            uptime_s=time.monotonic() - self._started,
            loop_age_s=time.monotonic() - self._beat,
            latency=self._latency or LatencyHistogram(),
            foxglove=self.foxglove.counters.as_dict() if self.foxglove else {},
        )

    def health(self) -> Health:
        from sinewatch.outputs.metrics import health

        p = self._pipeline
        return health(
            running=self._running,
            stopping=self.should_exit.is_set(),
            loop_age_s=time.monotonic() - self._beat,
            stall_s=self.config.metrics.stall_s,
            sinks=p.sink_status() if p else [],
        )

    def release_idle(self) -> None:
        """Publish, not valid, what the channels without a block for ``idle_release_s`` hold
        back (``hold_estimates``): a feed that pauses or ends gets its last estimates within
        1.5 ``idle_release_s``, not at the daemon's stop. Judged by the blocks' arrival at the
        intake, so that a backlog does not make a streaming channel look paused: a channel whose
        next block waits in the queue is not idle. Only while this daemon serves its shard
        (:meth:`ClusterMember.may_release_held`): a standby's held estimates, and a new owner's before
        its takeover has run, carry another term."""
        if self.cluster is not None and not self.cluster.may_release_held():
            return
        self.pipeline.release_idle(time.monotonic_ns(), log_time_ns=self._log_time(), waiting=self._arrived)

    async def _every(self, seconds: float, fn: Callable[[], None]) -> None:
        while True:
            await asyncio.sleep(seconds)
            try:
                fn()
            except Exception:  # a failed tick must not end the timer
                log.exception("periodic %s failed", getattr(fn, "__name__", fn))

    # ---- lifecycle ------------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Load (or compile) the kernels every configured rule will run now, so that a
        channel's first block does not wait ~0.3-0.8 s for numba (seconds on a busy machine).

        Each rule's own params, not the estimator's example ones: a param can choose another
        kernel (differential-rls with ``input = "iq"`` runs its I/Q kernel, on two columns).
        The sample rate is the estimator's example one (a block brings the real one; the
        kernels' types do not depend on it); params that are invalid there fall back to the
        example params (the rule's kernel then compiles on its first block, as it would)."""
        from sinewatch.estimators import check_rules, get

        check_rules(self.config.rules)
        warmed: set[tuple[str, str]] = set()
        for rule in self.config.rules:
            key = (rule.estimator, json.dumps(rule.params, sort_keys=True, default=str))
            if key not in warmed:
                warmed.add(key)
                _warm_up_rule(get(rule.estimator), rule.params)

    def start(self) -> None:
        """Open the session and sinks and start intake (call from the event loop)."""
        cfg = self.config
        self.warm_up()
        self._start_operations()  # before Zenoh: a port in use or a missing extra fails first
        self._session = open_session(cfg.zenoh)
        sinks: list[Sink] = [ZenohPublisherSink(self._session)]
        if cfg.recording.enabled:
            self.recorder = McapRecorder(cfg, snapshot=lambda: self.pipeline.snapshot())
            sinks.append(self.recorder)
        if self.foxglove is not None:
            sinks.append(self.foxglove)
        if cfg.c37118.enabled:
            self.c37118 = C37118Server(cfg.c37118)
            sinks.append(self.c37118)
        self._pipeline = Pipeline(cfg, sinks)
        if cfg.workers.resume_from:  # a worker process restarted by its supervisor
            self._resume(Path(cfg.workers.resume_from))
        self._pipeline.open_sinks()  # a recorder that cannot open is reported; estimation starts anyway
        self.cluster = ClusterMember(self)
        self.cluster.start(asyncio.get_running_loop())  # active: start_intake() now; standby: at takeover
        self._beat = time.monotonic()
        self._running = True  # serving or standing by: /healthz says ok from here
        log.info(
            "sinewatch daemon %s: zenoh %s %s listen=%s connect=%s, input %s, estimates %s/*",
            cfg.daemon_id,
            cfg.zenoh.mode,
            self._session.info.zid(),  # the id Zenoh's own log (a router's included) names this session by
            cfg.zenoh.listen,
            cfg.zenoh.connect,
            cfg.keys.input,
            cfg.keys.estimates_prefix,
        )

    def _resume(self, path: Path) -> None:
        """Restore the state a dead predecessor published last (``serve --workers``): each
        channel resumes after its last block in that state. Blocks Zenoh brings again up to
        there are taken as already in the state; later ones are estimated and published (those
        between the snapshot and the death a second time, with the same bytes); blocks nobody
        received are flagged as a gap on the channel's next estimate. The recording's first
        file carries this state, so it replays on its own."""
        snapshot = json.loads(path.read_text())
        pipeline = self.pipeline
        pipeline.restore(snapshot)
        for ch in pipeline.channels.values():
            if ch.last_seq is not None:
                pipeline.resume_points[ch.name] = ResumePoint(ch.last_seq, ch.next_t0_ns)
        # The resume points count every block of that state published; so are its held estimates
        # (hold_estimates): its next block or its idle release published them, unless it died
        # within that (then they are lost with it). Dropped, not published a second time.
        pipeline.drop_held()
        if self.recorder is not None:
            self.recorder.attach_first_snapshot = True
        log.warning("resumed %d channel(s) from the state in %s", len(pipeline.channels), path)

    def start_intake(self, history_blocks: int | None = None) -> None:
        """Subscribe to the inputs (at start, or when a standby takes over: then the
        publishers' history is asked for its newest ``history_blocks`` per key only)."""
        if self._intake is None:
            # the state's held estimates were made under its previous owner's term: those it
            # published are dropped, the rest carry this daemon's (set before this is called)
            self.pipeline.take_over_held(self.cluster.published if self.cluster is not None else {})
            self._intake = Intake(self, asyncio.get_running_loop(), history_blocks)

    async def stop_intake(self) -> None:
        """Unsubscribe from the inputs (an owner that lost its shard): what is queued is
        dropped by the consumer (the gate no longer opens), counted in ``handed_over``."""
        if self._intake is not None:
            await self._intake.stop()  # the consumer releases the room of what it drops meanwhile
            self._intake = None
        self.pipeline.drop_held()  # made under the lost term: the successor's to publish, never ours

    def _start_operations(self) -> None:
        """The Foxglove server and the metrics server, when configured."""
        fox, met = self.config.foxglove, self.config.metrics
        if fox.port is not None:
            module = _foxglove_module()
            try:
                self.foxglove = module.FoxgloveSink(self.config)
            except Exception as exc:  # noqa: BLE001 (the SDK's errors have no common base: say what failed)
                raise ConfigError(f"foxglove: expected to listen on {fox.host}:{fox.port}, got {exc}") from None
        if met.port is not None:
            module = _metrics_module()
            self._latency = module.LatencyHistogram()
            try:
                self.metrics = module.MetricsServer(met.host, met.port, self.metrics_snapshot, self.health)
            except OSError as exc:
                raise ConfigError(f"metrics: expected to listen on {met.host}:{met.port}, got {exc}") from None
            self.metrics.start()

    async def run(self) -> int:
        """Run until a signal (or ``should_exit``); return the exit code (0, or 130 if forced)."""
        with shutdown_signals(self.handle_signal, enabled=self.install_signal_handlers):
            try:
                self.start()
                if self.c37118 is not None:
                    await self.c37118.start()
            except BaseException:
                self._close()  # what start() opened before it failed (ports, session)
                raise
            consumer = asyncio.create_task(self._consume(), name="sinewatch-consumer")
            periodic = [asyncio.create_task(self._every(self.config.status_interval_s, self.publish_status))]
            beat = asyncio.create_task(self._every(self._heartbeat_s(), self.heartbeat), name="sinewatch-heartbeat")
            if self.config.hold_estimates:  # a paused feed's held estimates (Pipeline.release_idle)
                periodic.append(asyncio.create_task(self._every(self.config.idle_release_s / 2, self.release_idle)))
            if self.recorder is not None:
                periodic.append(
                    asyncio.create_task(self._every(self.config.recording.flush_interval_s, self.pipeline.flush_sinks))
                )
            self._beat = time.monotonic()  # the heartbeat task pings systemd from here on
            self.ready.set()
            self.notifier.ready(f"subscribed to {self.config.keys.input}")
            try:
                await self.should_exit.wait()
                await self._shutdown(consumer, periodic)  # the heartbeat goes on while it drains
            finally:
                beat.cancel()
                if self.c37118 is not None:
                    await self.c37118.stop()
                self._close()
        return 130 if self.force_exit.is_set() else 0

    async def _shutdown(self, consumer: asyncio.Task[None], periodic: list[asyncio.Task[None]]) -> None:
        self.notifier.stopping("draining: intake stopped, finishing the queue and the recording")
        for task in periodic:
            task.cancel()
        if self._intake is not None:
            await self._intake.stop()  # no new inputs; the pump has handed over all it had
        self._queue.put_nowait(None)  # the consumer ends after everything before it
        await consumer
        if self.cluster is None or self.cluster.may_release_held():
            self.pipeline.release_held(time.time_ns())  # hold_estimates: the inputs' end, publish what waits
        else:  # a standby (its state restored ahead) or a deposed owner: not its term to publish under
            self.pipeline.drop_held()
        self.publish_status()
        if self.cluster is not None:  # only now: a standby takes over after our last estimate
            await self.cluster.close()
        c = self.pipeline.counters
        log.info(
            "%s: %d inputs, %d estimates, %d errors",
            "forced exit" if self.force_exit.is_set() else "drained",
            c.inputs,
            c.estimates,
            c.errors,
        )

    def _close(self) -> None:
        if self._pipeline is not None:
            self._pipeline.close_sinks()
        elif self.foxglove is not None:  # started, but the pipeline never was
            self.foxglove.close()
        if self._session is not None:
            self._session.close()
        if self.metrics is not None:  # last: /healthz says "stopping" until the end
            self.metrics.close()

    @property
    def recording_paths(self) -> list[Path]:
        return list(self.recorder.paths) if self.recorder else []


_T = TypeVar("_T")


def _size(path: Path) -> int:
    """Bytes on disk (0 for a file gone meanwhile: a scrape must not fail on it)."""
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _optional(module: str, package: str, dist: str, extra: str, what: str) -> Any:
    """The module ``module`` (its full dotted path, so that it reads as an import), which needs
    ``package`` from the ``extra`` extra: a missing package is one clear line (a ConfigError),
    not a traceback."""
    import importlib

    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name != package and not (exc.name or "").startswith(f"{package}."):
            raise
        raise ConfigError(
            f"{what} needs the {extra!r} extra: pip install 'sinewatch[{extra}]' "
            f"(expected the {dist} package, got no module {package!r})"
        ) from None


def _foxglove_module() -> Any:
    return _optional(
        "sinewatch.outputs.foxglove_live", "foxglove", "foxglove-sdk", "foxglove", "--foxglove / [foxglove]"
    )


def _metrics_module() -> Any:
    return _optional(
        "sinewatch.outputs.metrics", "prometheus_client", "prometheus-client", "metrics", "--metrics / [metrics]"
    )


def check_extras(config: SinewatchConfig) -> None:
    """Raise ConfigError (one line) when ``[foxglove]`` or ``[metrics]`` is on without its
    extra: ``serve --workers`` checks it before it starts any worker."""
    if config.foxglove.port is not None:
        _foxglove_module()
    if config.metrics.port is not None:
        _metrics_module()


def _started(value: _T | None, what: str) -> _T:
    if value is None:
        raise RuntimeError(f"daemon {what}: expected a started daemon (call start() or run() first)")
    return value


def serve(config: SinewatchConfig) -> int:
    """Run the daemon in the foreground until SIGINT/SIGTERM."""

    async def main() -> int:
        return await Daemon(config).run()

    return asyncio.run(main())
