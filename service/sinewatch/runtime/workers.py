"""Worker processes: ``sinewatch serve --workers N``.

One Python process runs its estimators on one core. With ``workers.count`` (or ``serve
--workers``) above one, ``serve`` is a *supervisor*:

* it hosts the configured Zenoh endpoints (``zenoh.listen``) in a router session, so
  publishers and subscribers connect to the same address as before, and routing runs in
  Zenoh's own threads, outside any Python lock;
* it starts N worker processes, each a whole daemon (:class:`sinewatch.runtime.daemon.Daemon`):
  a Zenoh client session on a private loopback endpoint of that router, the intake, the
  estimators, the publisher and its own MCAP recording (``<daemon_id>.w<i>-...mcap``).
  Each worker keeps the input keys :func:`sinewatch.runtime.cluster.worker_of` assigns it (a
  stable CRC-32 of the key) and drops the others before copying them, so each channel's
  state lives in one process and its estimates stay in order. Sample data are copied
  once into each worker (Zenoh's delivery) and never between processes; replay reads the
  workers' files as separate runs, so it is bit-exact whatever N was;
* it watches them: each worker's systemd notifications (``READY``, ``WATCHDOG``,
  ``STOPPING``; :mod:`sinewatch.runtime.sdnotify`) go to the supervisor's own datagram socket, so
  it knows when all are serving (then tells systemd, if it runs under it) and notices a
  worker whose event loop stopped turning (``workers.stall_s``: killed, then restarted
  like a dead one);
* it restarts a worker that dies from the last state that worker published (the
  cluster snapshot, every ``cluster.snapshot_interval_s``): the new process restores it,
  takes the blocks Zenoh brings again up to there as already known, and flags the blocks
  nobody received as a gap on each channel's next estimate.

Signals, as the single daemon: SIGINT/SIGTERM drain every worker (each finishes its
queue and its MCAP file), a second SIGINT forces them. The workers run in their own
process group, so a terminal's Ctrl-C reaches them only through the supervisor, once.

The C37.118 server streams one PMU data frame for all its stations at once: with
``[c37118]`` on, the estimators run in one process. ``foxglove.port`` and ``metrics.port``
(when not 0) are worker 1's; worker i listens on the port + i - 1.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import socket
import struct
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from sinewatch.clients.session import free_loopback_port, open_session
from sinewatch.runtime.cluster import shard_id_of
from sinewatch.runtime.sdnotify import Notifier
from sinewatch.runtime.signals import shutdown_signals
from sinewatch.schemas.config import ENV_PREFIX, SinewatchConfig, ZenohSection

log = logging.getLogger("sinewatch.runtime.workers")

WORKER_WATCHDOG_USEC = 2_000_000  # workers ping at least every second (half of it)
EARLY_DEATH_S = 10.0  # a worker that dies sooner than this after its start is restarted after a backoff
MAX_BACKOFF_S = 30.0
FORCE_KILL_S = 10.0  # after a forced exit, a worker still running this long after is killed


def worker_count(config: SinewatchConfig, requested: int | None = None) -> int:
    """``serve --workers`` (or ``workers.count``; 0 means one per core); one process when
    this already is a worker or when the C37.118 server is on."""
    if config.workers.index is not None or config.c37118.enabled:
        return 1
    count = requested if requested is not None else config.workers.count
    return count if count > 0 else max(1, len(os.sched_getaffinity(0)))


@dataclass
class Worker:
    """One worker slot: its process (the current one), and what the supervisor knows of it."""

    index: int
    config_path: Path
    shard_id: str
    process: asyncio.subprocess.Process | None = None
    started_at: float = 0.0
    ready: bool = False
    last_beat: float = 0.0
    restarts: int = 0
    backoff_s: float = 0.0
    snapshot: bytes | None = None  # the last state it published (set on a Zenoh thread)
    exit_codes: list[int] = field(default_factory=list)

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None else None


class Supervisor:
    """Runs and watches the worker processes (see the module docstring)."""

    def __init__(self, config: SinewatchConfig, count: int, *, install_signal_handlers: bool = True) -> None:
        self.config = config
        self.count = count
        self.install_signal_handlers = install_signal_handlers
        self.should_exit = asyncio.Event()
        self.force_exit = False
        self.failed_to_start = False
        self.all_ready = asyncio.Event()
        self.notifier = Notifier()
        self.workers: list[Worker] = []
        self._tmp = Path(tempfile.mkdtemp(prefix="sinewatch-workers-"))
        self._sessions: list[zenoh.Session] = []  # the inner router (or the config's session), then the outer
        self._subscribers: list[Any] = []
        self._notify_sock: socket.socket | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._worker_zenoh = self._zenoh_for_workers()

    # ---- configuration -------------------------------------------------------------------------
    def _zenoh_for_workers(self) -> ZenohSection:
        """The workers' sessions: clients of this process's router on a private loopback
        port when the config listens; otherwise the config's own (e.g. clients of a router)."""
        z = self.config.zenoh
        if not z.listen:
            return z.model_copy(deep=True)
        self._private_endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        return ZenohSection(
            mode="client",
            listen=[],
            connect=[self._private_endpoint],
            shared_memory=z.shared_memory,
            recovery=z.recovery,
            raw=dict(z.raw),
        )

    def _inner_section(self) -> ZenohSection:
        """The workers' router: on the private endpoint only, so that nobody outside reaches
        a worker before all of them have subscribed."""
        return ZenohSection(mode="router", listen=[self._private_endpoint], connect=[], recovery=False)

    def _outer_section(self) -> ZenohSection:
        """The configured endpoints, opened once every worker has subscribed: a router that
        reaches the workers through the inner one. A publisher that connects sees the
        subscription of the inner router, which has every worker's already: no worker's first
        blocks go to nobody (the bare race: `feed` starts when the first worker subscribed)."""
        z = self.config.zenoh
        return z.model_copy(update={"mode": "router", "connect": [*z.connect, self._private_endpoint]})

    def worker_config(self, index: int, resume_from: Path | None = None) -> SinewatchConfig:
        """Worker ``index``'s config: the supervisor's, with its id, session, share of the keys
        and (when restarted) the state to resume from."""
        cfg = self.config.model_copy(deep=True)
        cfg.daemon_id = f"{self.config.daemon_id}.w{index}"
        cfg.zenoh = self._worker_zenoh.model_copy(deep=True)
        cfg.workers.count = self.count
        cfg.workers.index = index
        cfg.workers.resume_from = str(resume_from) if resume_from is not None else None
        for section in (cfg.foxglove, cfg.metrics):
            if section.port:  # 0 (any free port) stays 0
                section.port += index - 1
        return cfg

    def _write_config(self, index: int, resume_from: Path | None) -> Path:
        path = self._tmp / f"worker-{index}.json"
        path.write_text(json.dumps(self.worker_config(index, resume_from).model_dump(mode="json")))
        return path

    def _worker_env(self) -> dict[str, str]:
        # The worker's config file is complete: environment overrides were applied to it already.
        env = {k: v for k, v in os.environ.items() if not k.upper().startswith(ENV_PREFIX)}
        env["NOTIFY_SOCKET"] = str(self._tmp / "notify")
        env["WATCHDOG_USEC"] = str(WORKER_WATCHDOG_USEC)
        env.pop("WATCHDOG_PID", None)
        return env

    # ---- processes -----------------------------------------------------------------------------
    async def _spawn(self, worker: Worker, resume_from: Path | None = None) -> None:
        worker.config_path = self._write_config(worker.index, resume_from)
        worker.ready = False
        worker.process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "sinewatch",
            "serve",
            "--config",
            str(worker.config_path),
            env=self._worker_env(),
            start_new_session=True,  # Ctrl-C reaches the workers through the supervisor only
        )
        worker.started_at = worker.last_beat = time.monotonic()
        log.info("worker %d: pid %d%s", worker.index, worker.process.pid, " (resuming)" if resume_from else "")

    async def _watch(self, worker: Worker) -> None:
        """Wait for the worker's exit; restart it unless the supervisor is stopping."""
        while True:
            assert worker.process is not None
            code = await worker.process.wait()
            worker.exit_codes.append(code)
            if self.should_exit.is_set():
                return
            if code == 2 and not worker.ready:  # it refused its configuration (a port in use...): so would a restart
                log.error("worker %d could not start (exit 2, its error above): stopping", worker.index)
                self.failed_to_start = True
                self.handle_signal(signal.SIGTERM)
                return
            lived = time.monotonic() - worker.started_at
            worker.backoff_s = (
                min(MAX_BACKOFF_S, max(self.config.workers.restart_backoff_s, 2 * worker.backoff_s))
                if lived < EARLY_DEATH_S
                else 0.0
            )
            resume = self._resume_file(worker)
            log.error(
                "worker %d (pid %s) exited with %s after %.1f s; restarting%s%s",
                worker.index,
                worker.pid,
                code,
                lived,
                " from its last published state" if resume else " afresh (it had published no state)",
                f" in {worker.backoff_s:g} s" if worker.backoff_s else "",
            )
            if worker.backoff_s:
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self.should_exit.wait(), worker.backoff_s)
                if self.should_exit.is_set():
                    return
            worker.restarts += 1
            await self._spawn(worker, resume)

    def _resume_file(self, worker: Worker) -> Path | None:
        snapshot = worker.snapshot
        if snapshot is None:
            return None
        path = self._tmp / f"worker-{worker.index}-state.json"
        path.write_bytes(snapshot)
        return path

    # ---- what the workers say --------------------------------------------------------------------
    def _on_snapshot(self, sample: zenoh.Sample) -> None:
        """On a Zenoh thread: keep each worker's latest state (one reference assignment)."""
        shard_id = str(sample.key_expr).rsplit("/", 2)[-2]
        for worker in self.workers:
            if worker.shard_id == shard_id:
                worker.snapshot = sample.payload.to_bytes()

    def _open_notify_socket(self, loop: asyncio.AbstractEventLoop) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK)
        sock.bind(str(self._tmp / "notify"))
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)  # the sender's pid comes with each datagram
        self._notify_sock = sock
        loop.add_reader(sock.fileno(), self._read_notifications)

    def _read_notifications(self) -> None:
        assert self._notify_sock is not None
        while True:
            try:
                data, ancdata, _, _ = self._notify_sock.recvmsg(4096, socket.CMSG_SPACE(12))
            except BlockingIOError:
                return
            pid = next(
                (
                    struct.unpack("iII", cdata[:12])[0]
                    for level, kind, cdata in ancdata
                    if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS
                ),
                None,
            )
            worker = next((w for w in self.workers if w.pid == pid), None)
            if worker is not None:
                self._notified(worker, data.decode(errors="replace").split("\n"))

    def _notified(self, worker: Worker, lines: list[str]) -> None:
        worker.last_beat = time.monotonic()
        if "READY=1" in lines and not worker.ready:
            worker.ready = True
            log.info("worker %d: serving", worker.index)
            if all(w.ready for w in self.workers):
                self.all_ready.set()

    async def _heartbeat(self) -> None:
        """Tell systemd's watchdog while every worker's loop turns; kill a stalled worker
        (its exit is then handled as a death)."""
        stall_s = self.config.workers.stall_s
        period = min(0.5, stall_s / 4, *([self.notifier.watchdog_s / 2] if self.notifier.watchdog_s else []))
        while True:
            await asyncio.sleep(period)
            now = time.monotonic()
            for worker in self.workers:
                process = worker.process
                if worker.ready and process is not None and process.returncode is None:
                    if now - worker.last_beat > stall_s:
                        log.error(
                            "worker %d (pid %d): no heartbeat for %.1f s: killing it",
                            worker.index,
                            process.pid,
                            now - worker.last_beat,
                        )
                        worker.ready = False
                        process.kill()
            self.notifier.watchdog()

    # ---- lifecycle ---------------------------------------------------------------------------------
    def handle_signal(self, sig: int) -> None:
        if sig == signal.SIGINT and self.should_exit.is_set():
            log.warning("second SIGINT: forcing the workers to exit (their MCAP files are still finished)")
            self.force_exit = True
            self._signal_workers(signal.SIGINT)
            # a worker that does not end even then (stuck in a kernel) is killed
            asyncio.get_running_loop().call_later(FORCE_KILL_S, self._signal_workers, signal.SIGKILL)
            return
        log.info("%s received: draining %d workers", signal.Signals(sig).name, len(self.workers))
        self.should_exit.set()
        # SIGTERM drains a worker as SIGINT does, and ends one still starting (its handlers not
        # installed yet) at once, where SIGINT would raise KeyboardInterrupt wherever it is;
        # a SIGINT after it forces a draining worker.
        self._signal_workers(signal.SIGTERM)

    def _signal_workers(self, sig: int) -> None:
        for worker in self.workers:
            if worker.process is not None and worker.process.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    worker.process.send_signal(sig)

    async def run(self) -> int:
        """Serve until SIGINT/SIGTERM; 0, or 130 when forced, or 1 when a worker failed to drain."""
        loop = asyncio.get_running_loop()
        with shutdown_signals(self.handle_signal, enabled=self.install_signal_handlers):
            try:
                hosting = bool(self.config.zenoh.listen)
                inner = open_session(self._inner_section() if hosting else self.config.zenoh)
                self._sessions.append(inner)
                admin = self.config.keys.admin_prefix.rstrip("/")
                self._subscribers.append(inner.declare_subscriber(f"{admin}/shard/*/snapshot", self._on_snapshot))
                self._open_notify_socket(loop)
                for i in range(1, self.count + 1):
                    worker = Worker(i, self._tmp / f"worker-{i}.json", shard_id_of(self.worker_config(i)))
                    self.workers.append(worker)
                    await self._spawn(worker)
                self._tasks = [asyncio.create_task(self._watch(w)) for w in self.workers]
                self._tasks.append(asyncio.create_task(self._heartbeat()))
                ready = asyncio.create_task(self.all_ready.wait())
                stop = asyncio.create_task(self.should_exit.wait())
                await asyncio.wait([ready, stop], return_when=asyncio.FIRST_COMPLETED)
                ready.cancel()
                if not self.should_exit.is_set():
                    if hosting:
                        self._sessions.append(open_session(self._outer_section()))
                    self.notifier.ready(f"{self.count} workers serving {self.config.keys.input}")
                    log.info(
                        "sinewatch supervisor %s: %d workers serving, zenoh router listen=%s connect=%s",
                        self.config.daemon_id,
                        self.count,
                        self.config.zenoh.listen,
                        self.config.zenoh.connect,
                    )
                await stop
                self.notifier.stopping(f"draining {self.count} workers")
                await asyncio.gather(*(w.process.wait() for w in self.workers if w.process is not None))
            finally:
                self._close(loop)
        codes = [w.exit_codes[-1] for w in self.workers if w.exit_codes]
        if self.failed_to_start:
            return 2
        if self.force_exit:
            return 130
        return 0 if all(code == 0 for code in codes) else 1

    def _close(self, loop: asyncio.AbstractEventLoop) -> None:
        for task in self._tasks:
            task.cancel()
        self._signal_workers(signal.SIGKILL)  # only those still running after a failure above
        for sub in self._subscribers:
            sub.undeclare()
        if self._notify_sock is not None:
            loop.remove_reader(self._notify_sock.fileno())
            self._notify_sock.close()
        for session in reversed(self._sessions):  # the outer router first: no new input meanwhile
            session.close()  # type: ignore[no-untyped-call]
        for path in self._tmp.iterdir():
            path.unlink()
        self._tmp.rmdir()


def end_with_parent() -> None:
    """In a worker: the kernel sends it SIGTERM when its supervisor dies (even by SIGKILL),
    so no worker outlives it (``prctl(PR_SET_PDEATHSIG)``, Linux)."""
    import ctypes

    pr_set_pdeathsig = 1
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)
    if os.getppid() == 1:  # the supervisor died before the call: nobody would send it
        os.kill(os.getpid(), signal.SIGTERM)


def supervise(config: SinewatchConfig, count: int) -> int:
    """``sinewatch serve`` with ``count`` worker processes, in the foreground until SIGINT/SIGTERM."""

    async def main() -> int:
        return await Supervisor(config, count).run()

    return asyncio.run(main())


__all__ = ["Supervisor", "Worker", "end_with_parent", "supervise", "worker_count"]
