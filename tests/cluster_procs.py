"""Processes of a sinewatch cluster for the cluster tests: an etcd server (the one `make
etcd` installs), a Zenoh router (`sinewatch router`), `sinewatch serve` daemons, a TCP
proxy that can cut one daemon off from etcd, a CPU burner, and a subscriber that records
every estimate with its fencing token and arrival time."""

from __future__ import annotations

import bisect
import contextlib
import datetime
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from sinewatch.clients import BlockPublisher, Fence
from sinewatch.clients.session import free_loopback_port

WAIT = 60.0  # the longest any condition may take on a loaded 2-core machine
DRAIN_BATCH = 1000  # estimates the test's subscriber takes under one hold of its lock
OBSERVER_FIFO = 60_000  # estimates the test's subscriber may fall behind by (a minute of the cluster's)
CHANNELS = [f"ch{i:03d}" for i in range(100)]
FS = 1000.0
BLOCK = 100  # 0.1 s per block: 10 blocks/s per channel, 1,000 blocks/s in all
LOG_TAIL_LINES = 40
# This process's own Zenoh log (the gateway's and subscribers' session): its errors, e.g. a link
# it closed because the router took nothing for `wait_before_close`, on stdout (`pytest -s`)
zenoh.init_log_from_env_or("error")


def log_tails(directory: Path | None, lines: int = LOG_TAIL_LINES) -> str:
    """The last ``lines`` of every daemon's log in ``directory``, for a failed wait's message:
    why a cluster was not served is in its daemons' logs, and a run's temporary directory can
    be gone (pytest keeps the last three) before anyone reads it."""
    if directory is None:
        return ""
    parts = []
    for path in sorted(directory.glob("*.log")):
        tail = path.read_text(errors="replace").splitlines()[-lines:]
        parts.append(f"\n--- {path.name}, last {len(tail)} lines ---\n" + "\n".join(tail))
    return "".join(parts)


def etcd_binary() -> str:
    path = shutil.which("etcd")
    if path is None:
        pytest.fail("no etcd on PATH: `make etcd` installs Debian's etcd-server")
    return path


class Etcd:
    """A single-member etcd on loopback, restartable on the same data and port."""

    def __init__(self, data_dir: Path) -> None:
        self.port = free_loopback_port()
        self.peer_port = free_loopback_port()
        self.data_dir = data_dir
        self.proc: subprocess.Popen[str] | None = None
        self.endpoint = f"127.0.0.1:{self.port}"

    def start(self) -> None:
        url, peer = f"http://127.0.0.1:{self.port}", f"http://127.0.0.1:{self.peer_port}"
        self.proc = subprocess.Popen(
            [etcd_binary(), "--name", "sw", "--data-dir", str(self.data_dir), "--listen-client-urls", url,
             "--advertise-client-urls", url, "--listen-peer-urls", peer, "--initial-advertise-peer-urls", peer,
             "--initial-cluster", f"sw={peer}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert self.proc.stderr is not None
        for line in self.proc.stderr:  # its log, until it serves clients
            if "ready to serve client requests" in line:
                break
        else:
            raise AssertionError(f"etcd ended before serving (exit {self.proc.wait()})")
        threading.Thread(target=self.proc.stderr.read, daemon=True).start()  # keep its pipe drained

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait()


@contextlib.contextmanager
def etcd_server(tmp_path: Path) -> Iterator[Etcd]:
    server = Etcd(tmp_path / "etcd-data")
    server.start()
    try:
        yield server
    finally:
        server.kill()


#: gRPC's own retries for the test's reads of etcd (a read is idempotent): a call waits for the
#: channel to connect (``waitForReady``) and is tried again on ``UNAVAILABLE``, with gRPC's backoff,
#: not failed at once. The chaos test restarts etcd and reads the election key right before the next
#: fault; under load a read failed with "recvmsg:Connection reset by peer" and took the test down,
#: where a daemon's election (``sinewatch.runtime.election``) only tries again.
ETCD_READ_OPTIONS = {
    "grpc.enable_retries": 1,
    "grpc.service_config": json.dumps(
        {
            "methodConfig": [
                {
                    "name": [{"service": "etcdserverpb.KV"}],
                    "waitForReady": True,
                    "retryPolicy": {
                        "maxAttempts": 5,
                        "initialBackoff": "0.2s",
                        "maxBackoff": "2s",
                        "backoffMultiplier": 2,
                        "retryableStatusCodes": ["UNAVAILABLE"],
                    },
                }
            ]
        }
    ),
}


def election_key(endpoint: str, shard_id: str) -> tuple[str, int]:
    """(owner, term) of a shard as etcd has them: the election key's value and create revision."""
    import asyncio

    import aetcd

    async def get() -> tuple[str, int]:
        host, _, port = endpoint.rpartition(":")
        async with aetcd.Client(host, int(port), options=ETCD_READ_OPTIONS) as client:
            kv = await asyncio.wait_for(client.get(f"sinewatch/admin/election/{shard_id}".encode()), 30)
            assert kv is not None, f"no election key for {shard_id}"
            return kv.value.decode(), int(kv.create_revision)

    return asyncio.run(get())


class Router:
    """``sinewatch router`` on a port from the OS, restartable on it; its output (Zenoh's
    log: a link it closed is the record of what it lost in flight) appended to
    ``<logs>/router.log``, whose tail a failed wait shows with the daemons'."""

    def __init__(self, logs: Path | None = None, zenoh: dict[str, Any] | None = None) -> None:
        self.port = free_loopback_port()
        self.logs = logs
        self.zenoh = zenoh or {}  # raw Zenoh config keys (`sinewatch router --zenoh PATH=JSON`)
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> None:
        raw = [arg for path, value in self.zenoh.items() for arg in ("--zenoh", f"{path}={json.dumps(value)}")]
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sinewatch", "router", "--listen", f"tcp/127.0.0.1:{self.port}", *raw],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None
        first = self.proc.stdout.readline()
        assert first.startswith("sinewatch router: listening"), first
        threading.Thread(target=self._drain, args=(self.proc.stdout, first), daemon=True).start()

    def _drain(self, out: Any, first: str) -> None:
        """Keep the router's pipe drained (a full pipe would stop it), into its log file (its
        first line too: the Zenoh id the other processes' logs name it by)."""
        sink = open(self.logs / "router.log", "a") if self.logs is not None else None
        if sink is not None:
            sink.write(first)
        with contextlib.suppress(ValueError, OSError):
            for line in out:
                if sink is not None:
                    sink.write(line)
                    sink.flush()
        if sink is not None:
            sink.close()

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait()


class Proxy:
    """TCP between one daemon and etcd, which the test can sever (every connection closed,
    new ones refused at once) and heal: an owner cut off from etcd but still on Zenoh.
    ``handshake_delay_s`` holds etcd's first bytes on each new connection back that long: a
    connection set up over a slow path, or to a peer on a loaded machine."""

    def __init__(self, target_port: int) -> None:
        self.target = target_port
        self.cut = False
        self.handshake_delay_s = 0.0
        self.refused = threading.Event()  # a connection came while severed, and was closed
        self._lock = threading.Lock()
        self._conns: list[socket.socket] = []
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            with self._lock:
                if self.cut:
                    client.close()
                    self.refused.set()
                    continue
                try:
                    upstream = socket.create_connection(("127.0.0.1", self.target), timeout=2)
                except OSError:
                    client.close()
                    continue
                upstream.settimeout(None)
                self._conns += [client, upstream]
            for a, b, delay in ((client, upstream, 0.0), (upstream, client, self.handshake_delay_s)):
                threading.Thread(target=self._pump, args=(a, b, delay), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket, delay_s: float = 0.0) -> None:
        with contextlib.suppress(OSError):
            first = src.recv(65536)
            if first and delay_s:
                time.sleep(delay_s)  # a slow path's latency, simulated (not a wait for anything)
            if first:
                dst.sendall(first)
            while first and (data := src.recv(65536)):
                dst.sendall(data)
        for s in (src, dst):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)

    def sever(self) -> None:
        with self._lock:
            self.cut = True
            conns, self._conns = self._conns, []
        for s in conns:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()

    def heal(self) -> None:
        with self._lock:
            self.cut = False

    def close(self) -> None:
        self.sever()
        self._listener.close()


def helper_process(kind: str, port: int) -> subprocess.Popen[str]:
    """``python cluster_procs.py <kind> <port>``, commanded a line at a time on its stdin,
    answering on its stdout (:class:`ProxyProcess`, :class:`GatewayProcess`)."""
    return subprocess.Popen(
        [sys.executable, __file__, kind, str(port)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )


class ProxyProcess:
    """A :class:`Proxy` in a process of its own, severed and healed on command: the daemons'
    keep-alives then do not wait for this test process's interpreter, busy with the gateway
    and every estimate (with the proxy's threads in here, owners nobody faulted lost their
    leases when the machine's load average reached 30-40)."""

    def __init__(self, target_port: int) -> None:
        self.proc = helper_process("proxy", target_port)
        assert self.proc.stdout is not None
        self.port = int(self.proc.stdout.readline())

    def _command(self, what: str) -> None:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(what + "\n")
        self.proc.stdin.flush()
        assert self.proc.stdout.readline().strip() == what  # done

    def sever(self) -> None:
        self._command("sever")

    def heal(self) -> None:
        self._command("heal")

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()


def _serve_proxy(target_port: int) -> None:
    proxy = Proxy(target_port)
    print(proxy.port, flush=True)
    for line in sys.stdin:
        getattr(proxy, line.strip())()
        print(line.strip(), flush=True)


def config_head(daemon_id: str, router: str) -> str:
    """The start of a test daemon's config file: its id, a status every 0.5 s, and Zenoh in
    client mode on ``router`` alone (the ``[zenoh]`` table is left open for more keys)."""
    return f"""daemon_id = "{daemon_id}"
status_interval_s = 0.5
[zenoh]
mode = "client"
listen = []
connect = ["{router}"]
"""


def daemon_config(
    tmp_path: Path,
    daemon_id: str,
    shard: str,
    role: str,
    router_port: int,
    etcd: str,
    recovery: bool = True,
    ttl_s: int = 3,
) -> Path:
    cfg = tmp_path / f"{daemon_id}.toml"
    cfg.write_text(
        config_head(daemon_id, f"tcp/127.0.0.1:{router_port}")
        + f"""recovery = {str(recovery).lower()}
[cluster]
shard = "{shard}"
role = "{role}"
snapshot_interval_s = 0.5
etcd = "{etcd}"
lease_ttl_s = {ttl_s}
[recording]
directory = "{tmp_path / daemon_id}"
[limits]  # behind a router, a daemon never stops reading its link; it drops past ~2 min of its inputs (docs/cluster.md)
queue_policy = "drop"
queue_capacity = 65536
[workers]
count = 1  # each daemon one process: the failover of whole daemons (workers: test_workers.py)
[[rules]]  # one estimate per block (the default rule reports on its own grid)
match = "sinewatch/in/**"
estimator = "ipdft"
params = {{ nominal_frequency_hz = 50.0, window_cycles = 10.0 }}
"""
    )
    return cfg


def start_daemon(tmp_path: Path, daemon_id: str, cfg: Path) -> subprocess.Popen[bytes]:
    """``sinewatch serve --config cfg``, its output appended to ``<tmp_path>/<daemon_id>.log``."""
    log = open(tmp_path / f"{daemon_id}.log", "a")
    return subprocess.Popen(
        [sys.executable, "-m", "sinewatch", "serve", "--config", str(cfg)], stdout=log, stderr=subprocess.STDOUT
    )


def stop_all(procs: dict[str, subprocess.Popen[bytes]]) -> None:
    """SIGCONT and SIGINT every daemon still running (each drains and finishes its file), then wait."""
    for p in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGCONT)
            p.send_signal(signal.SIGINT)
    for p in procs.values():
        try:
            p.wait(timeout=WAIT)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


@contextlib.contextmanager
def cpu_burner(n: int | None = None) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``n`` (default: twice the cores) processes spinning at 100 % for the whole block."""
    n = n or 2 * (os.cpu_count() or 1)
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
            p.wait()


class Tokens:
    """The cluster's liveliness tokens as the network sees them (discovery: who is there)."""

    def __init__(self, session: zenoh.Session, logs: Path | None = None) -> None:
        self.present: set[str] = set()
        self.logs = logs  # the daemons' logs, whose tails a failed wait shows
        self._cond = threading.Condition()
        self._sub = session.liveliness().declare_subscriber("sinewatch/admin/shard/**", self._on, history=True)

    def _on(self, sample: zenoh.Sample) -> None:
        name = "/".join(str(sample.key_expr).split("/")[-2:])  # "active/a1"
        with self._cond:
            (self.present.add if sample.kind == zenoh.SampleKind.PUT else self.present.discard)(name)
            self._cond.notify_all()

    def wait_count(self, role: str, n: int, timeout: float = WAIT) -> None:
        with self._cond:
            ok = self._cond.wait_for(lambda: sum(p.startswith(role + "/") for p in self.present) >= n, timeout)
            assert ok, f"{n} {role}: {self.present}{log_tails(self.logs)}"

    def wait_daemons(self, daemon_ids: list[str], timeout: float = WAIT) -> None:
        """Until every one of ``daemon_ids`` has a token, in either role."""
        with self._cond:
            ok = self._cond.wait_for(lambda: set(daemon_ids) <= {p.split("/")[-1] for p in self.present}, timeout)
            assert ok, f"{daemon_ids}: {self.present}{log_tails(self.logs)}"

    def wait_for(self, *names: str, timeout: float = WAIT) -> None:
        with self._cond:
            ok = self._cond.wait_for(lambda: set(names) <= self.present, timeout)
            assert ok, f"{names}: {self.present}{log_tails(self.logs)}"


class Estimates:
    """Every estimate published, in arrival order: raw, and as a fenced reader keeps them."""

    def __init__(self, session: zenoh.Session, logs: Path | None = None) -> None:
        self.logs = logs  # the daemons' logs, whose tails a failed wait shows
        self.raw: list[dict[str, Any]] = []
        self.by_channel: dict[str, list[dict[str, Any]]] = defaultdict(list)  # fenced
        self.fence = Fence()
        self.fenced_off: set[tuple[str, int]] = set()  # (channel, seq) the fence dropped
        self.first_of_term: dict[tuple[str, int], float] = {}  # (shard, term) -> arrival of its first estimate
        # channel -> blocks reported lost in transport for good: the largest `count` of its `unrecovered`
        # ErrorReports (a daemon's count so far; one daemon's, when several owned the channel in turn: a lower
        # bound). The record of a stream's last blocks lost, which no later estimate can flag as a gap.
        self.unrecovered: dict[str, int] = defaultdict(int)
        self._cond = threading.Condition()
        # A deep FIFO drained by a thread of this process, not a callback: Zenoh hands a Python callback
        # its samples through a channel of 256, and when this process (the loaded machine's busiest Python
        # process) fell behind, Zenoh's receiving thread waited on it, the router could not push estimates
        # to this session for its `wait_before_close` (5 s) and closed it (router.log of the 50-fault run)
        self._sub = session.declare_subscriber("sinewatch/est/**", zenoh.handlers.FifoChannel(OBSERVER_FIFO))
        threading.Thread(target=self._drain, args=(self._sub.handler, self._on), daemon=True).start()
        # the ErrorReports too through a FIFO a thread drains: a Python callback waits on Zenoh's thread for the
        # GIL and for the lock the waits hold, and meanwhile this session reads nothing of the estimates
        self._err = session.declare_subscriber("sinewatch/err/**", zenoh.handlers.FifoChannel(OBSERVER_FIFO))
        threading.Thread(target=self._drain, args=(self._err.handler, self._on_error), daemon=True).start()
        print(f"the test's Zenoh session: {session.info.zid()}", flush=True)  # as Zenoh's logs name it

    def _drain(self, handler: Any, on: Any) -> None:
        """What ``handler`` holds, each sample to ``on``, as many as have come at once under one hold of the
        lock and one notify: a wait's condition (over every channel) runs once a notify, and run once an
        estimate (1,000 a second) it kept this loaded process's subscriber behind the cluster."""
        with contextlib.suppress(zenoh.ZError):  # raised once the session closes
            while True:
                samples = [handler.recv()]
                while len(samples) < DRAIN_BATCH and (more := handler.try_recv()) is not None:
                    samples.append(more)
                msgs = [json.loads(s.payload.to_bytes()) for s in samples]
                with self._cond:
                    for msg in msgs:
                        on(msg)
                    self._cond.notify_all()

    def _on_error(self, msg: dict[str, Any]) -> None:
        if msg.get("kind") == "unrecovered":
            channel = msg["key"].rsplit("/", 1)[-1]
            self.unrecovered[channel] = max(self.unrecovered[channel], msg["count"])

    def _on(self, msg: dict[str, Any]) -> None:
        msg["_arrival"] = time.monotonic()
        msg["_wall"] = time.time()
        self.raw.append(msg)
        f = msg.get("fencing")
        if f is not None:
            self.first_of_term.setdefault((f["shard"], f["term"]), msg["_arrival"])
        if self.fence.accept(msg):
            self.by_channel[msg["channel"]].append(msg)
        else:  # a deposed owner's late estimate, after its successor's first: readers drop it
            self.fenced_off.add((msg["channel"], msg["seq"]))

    def wait(self, condition: Any, what: str, timeout: float = WAIT) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: condition(self.by_channel), timeout=timeout), self._failed(what)

    def _failed(self, what: str) -> str:
        """What a failed wait says: the channels not served lately, and the daemons' logs."""
        now = time.monotonic()
        quiet = sorted(c for c in CHANNELS if not any(m["_arrival"] > now - 5 for m in self.by_channel[c][-3:]))
        return f"{what}; channels without an estimate in 5 s: {len(quiet)} {quiet[:8]}{log_tails(self.logs)}"

    def newest_term(self, shard_id: str) -> int | None:
        with self._cond:
            return self.fence.newest.get(shard_id)

    def wait_for_new_term(self, shard_id: str, older: int, what: str) -> int:
        with self._cond:
            ok = self._cond.wait_for(lambda: (self.fence.newest.get(shard_id) or 0) > older, timeout=WAIT)
            assert ok, self._failed(what)
            return self.fence.newest[shard_id]


class Gateway(threading.Thread):
    """``CHANNELS`` of a 50 Hz sine in real time (one block per channel every 0.1 s), on a
    Zenoh session of its own (``router_port``), as a gateway process has: on the test's
    observing session, a router that closed that session for reading too slowly (5 s, Zenoh's
    ``wait_before_close``) closed the gateway's link with it, and every channel lost the
    blocks in flight at once (the untouched shard's losses in the loaded failover runs)."""

    def __init__(self, router_port: int) -> None:
        super().__init__(daemon=True)
        from sinewatch.clients import connect

        self.session = connect([f"tcp/127.0.0.1:{router_port}"])
        self.pub = BlockPublisher(self.session)
        self.sent: dict[str, int] = dict.fromkeys(CHANNELS, 0)
        self.sent_wall: list[float] = []  # wall time round n (every channel's seq n) began to be put
        self.stop = threading.Event()
        self.on_round: Any = None  # called with (n, wall time it began) once round n is put

    def run(self) -> None:
        t = np.arange(BLOCK) / FS
        start = time.monotonic()
        n = 0
        while not self.stop.is_set():
            self.sent_wall.append(time.time())
            for i, ch in enumerate(CHANNELS):
                self.pub.publish(ch, np.sin(2 * np.pi * 50.0 * (t + n * BLOCK / FS) + i), sample_rate_hz=FS)
                self.sent[ch] = n + 1
            if self.on_round is not None:
                self.on_round(n, self.sent_wall[-1])
            n += 1
            self.stop.wait(max(0.0, start + n * BLOCK / FS - time.monotonic()))  # the gateway's real-time pace

    def finish(self, estimates: Estimates, timeout: float = WAIT) -> None:
        """Stop publishing, then wait for every channel's last block's estimate."""
        self.stop.set()
        self.join()
        wait_last_blocks(self.sent, estimates, timeout)

    def close(self) -> None:
        self.stop.set()
        if self.is_alive():
            self.join()
        self.session.close()


def wait_last_blocks(sent: dict[str, int], estimates: Estimates, timeout: float) -> None:
    """Until every channel's last block sent is estimated, or the blocks after its last
    estimate are reported lost in transport for good (no later block can flag them as a gap)."""

    def last(e: dict[str, list[dict[str, Any]]]) -> bool:
        return all(sent[c] - 1 - (e[c][-1]["seq"] if e[c] else -1) <= estimates.unrecovered[c] for c in CHANNELS)

    estimates.wait(last, "the last blocks", timeout)


class GatewayProcess:
    """A :class:`Gateway` in a process of its own (``python cluster_procs.py gateway PORT``),
    with the same ``sent``/``sent_wall``/``finish``/``close``: fed here from its stdout, a
    line a round. In the 50-fault run, gateway and subscriber in this one process, beside
    four CPU burners, fell 15 s behind the estimates from the 20th fault on: the router
    closed this process's link, then the gateway's; in a process apart, the gateway's
    pace does not wait for this interpreter."""

    def __init__(self, router_port: int) -> None:
        self.sent: dict[str, int] = dict.fromkeys(CHANNELS, 0)
        self.sent_wall: list[float] = []
        self._stopped = threading.Event()
        self.proc = helper_process("gateway", router_port)
        assert self.proc.stdout is not None
        for line in self.proc.stdout:  # its session is open once it says so (Zenoh's log may come first)
            if line.strip() == "ready":
                break
            print(line, end="")
        else:
            raise AssertionError(f"the gateway process ended before publishing (exit {self.proc.wait()})")
        self._reader = threading.Thread(target=self._read, args=(self.proc.stdout,), daemon=True)
        self._reader.start()

    def _read(self, out: Any) -> None:
        for line in out:
            words = line.split()
            if len(words) == 3 and words[0] == "round":
                n = int(words[1])
                self.sent_wall.append(float(words[2]))
                for c in CHANNELS:
                    self.sent[c] = n + 1
            elif line.strip() == "stopped":
                self._stopped.set()
            else:
                print(line, end="")  # its Zenoh log
        self._stopped.set()

    def _command(self, what: str) -> None:
        assert self.proc.stdin is not None
        with contextlib.suppress(OSError):  # ended already
            self.proc.stdin.write(what + "\n")
            self.proc.stdin.flush()

    def start(self) -> None:
        self._command("start")

    def finish(self, estimates: Estimates, timeout: float = WAIT) -> None:
        """Stop publishing (every round it put is counted here first), then wait for every
        channel's last block's estimate."""
        self._command("stop")
        assert self._stopped.wait(timeout), "the gateway process did not stop"
        self._reader.join(timeout)
        wait_last_blocks(self.sent, estimates, timeout)

    def close(self) -> None:
        self._command("stop")
        try:
            self.proc.wait(timeout=WAIT)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _serve_gateway(router_port: int) -> None:
    gateway = Gateway(router_port)
    gateway.on_round = lambda n, wall: print(f"round {n} {wall!r}", flush=True)
    print(f"the gateway's Zenoh session: {gateway.session.info.zid()}", flush=True)  # as Zenoh's logs name it
    print("ready", flush=True)
    if sys.stdin.readline().strip() == "start":
        gateway.start()
        sys.stdin.readline()  # "stop", or the test's end (EOF)
    gateway.stop.set()
    if gateway.is_alive():
        gateway.join()
    print("stopped", flush=True)
    gateway.session.close()


def after(msgs: list[dict[str, Any]], t: float) -> list[dict[str, Any]]:
    """The estimates that arrived after monotonic time ``t`` (``msgs`` in arrival order: a binary
    search). A scan of every estimate so far, for each of 100 channels, on every estimate that came
    (the waits' conditions run at each notify, under the lock the subscriber's thread needs) costs
    the test's process more as a 50-fault run goes on (~3,600 estimates a channel by fault 26): a
    subscriber that falls behind holds its Zenoh session back, and the router, pushing it the
    daemons' estimates with ``BLOCK``, stops reading their links ("A querier that reads nothing",
    docs/cluster.md)."""
    return msgs[bisect.bisect_right(msgs, t, key=lambda m: m["_arrival"]) :]


def recorded_estimates(tmp_path: Path, daemon_ids: list[str]) -> dict[str, list[dict[str, Any]]]:
    """What each daemon published, from its own recordings (every file, a killed daemon's
    cut short at its last complete chunk): independent of any subscriber's connection.
    Each estimate gets ``_published_ns``: the wall time its daemon recorded it at, as it
    published it (a subscriber on a loaded machine was seen to get one 5.5 s later)."""
    from sinewatch.runtime.replay import read_recording

    out: dict[str, list[dict[str, Any]]] = {}
    for d in daemon_ids:
        msgs = out[d] = []
        for path in sorted((tmp_path / d).glob("*.mcap")):
            for kind, item in read_recording(path, roles=frozenset({"estimate"})):
                if kind == "message" and item.role == "estimate":
                    msgs.append({**json.loads(item.payload), "_published_ns": item.log_time_ns})
    return out


def published_once_each(
    observed: dict[str, list[dict[str, Any]]],
    recorded: dict[str, list[dict[str, Any]]],
    fenced_off: set[tuple[str, int]] = frozenset(),  # type: ignore[assignment]
) -> dict[str, list[dict[str, Any]]]:
    """Per channel, every estimate a fenced reader keeps (seen by the subscriber, or in a
    recording when the subscriber's own link was down), by seq. Asserts that no (channel,
    seq) was published by two daemons under one term (two owners at once), and that where
    two daemons recorded it under two terms (an owner paused between its gate and its put,
    whose estimate left after its successor had published the same block) the reader kept
    the newer term's only. A recorded estimate the subscriber saw the fence drop, and no
    successor published, is not what readers keep: the successor's gap counts it."""
    copies: dict[tuple[str, int], dict[str, dict[str, Any]]] = defaultdict(dict)
    for d, msgs in recorded.items():
        for m in msgs:
            copies[(m["channel"], m["seq"])].setdefault(d, m)
    union: dict[str, dict[int, dict[str, Any]]] = defaultdict(dict)
    twice, late = {}, []
    for (ch, seq), by_daemon in copies.items():
        terms = sorted(((m.get("fencing") or {}).get("term") or 0, d) for d, m in by_daemon.items())
        if len(terms) > 1 and terms[-2][0] == terms[-1][0]:
            twice[(ch, seq)] = terms
        elif len(terms) > 1:
            late.append((ch, seq, terms))
        elif (ch, seq) in fenced_off:
            continue
        union[ch][seq] = {**by_daemon[terms[-1][1]], "_seen": False}  # until the subscriber is found to have it
    assert not twice, f"published by two daemons under one term: {sorted(twice.items())[:20]}"
    if late:
        print(
            f"{len(late)} block(s) recorded by two daemons under two terms (a reader keeps the newer term's): {late[:10]}"
        )
    for ch, msgs in observed.items():
        for m in msgs:
            known = union[ch].setdefault(m["seq"], m)
            assert known.get("fencing") == m.get("fencing"), f"{ch} seq {m['seq']} kept under an older term"
            known["_seen"] = True
    return {ch: [by_seq[s] for s in sorted(by_seq)] for ch, by_seq in union.items()}


def _late_in_a_gap(msgs: list[dict[str, Any]]) -> set[int]:
    """Seqs of estimates only a recording has (the subscriber never got them) inside a gap a
    newer term flagged: their daemon put them and was paused or cut off before they left it
    (its queue flushed after its successor had published, or never), so no reader had them
    before the successor, and a fenced reader drops them after: the successor's gap is what
    counts them (seen in the 50-fault run: an owner's last estimate before a SIGSTOP, recorded
    at its put, counted again in its successor's gap of 300)."""
    seqs = [m["seq"] for m in msgs]
    late = set()
    for m in msgs:
        if m["diagnostics"]["gap"]:
            term = (m.get("fencing") or {}).get("term") or 0
            lo, hi = (
                bisect.bisect_left(seqs, m["seq"] - m["diagnostics"]["gap_blocks"]),
                bisect.bisect_left(seqs, m["seq"]),
            )
            late |= {
                e["seq"]
                for e in msgs[lo:hi]
                if not e.get("_seen", True) and ((e.get("fencing") or {}).get("term") or 0) < term
            }
    return late


_LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3}) \S+ \S+ ")


def log_events(directory: Path, daemon_id: str, since_wall: float, *needles: str) -> list[tuple[float, str]]:
    """(wall time, text) of each line of ``daemon_id``'s log from ``since_wall`` on that holds one
    of ``needles`` (the logging module stamps local time to the millisecond)."""
    path = directory / f"{daemon_id}.log"
    events = []
    for line in path.read_text(errors="replace").splitlines() if path.exists() else []:
        m = _LOG_TIME.match(line)
        if m is None or not any(n in line for n in needles):
            continue
        t = datetime.datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S").timestamp() + int(m.group(2)) / 1e3
        if t >= since_wall - 1e-3:
            events.append((t, line[m.end() :]))
    return events


def recorded_inputs(tmp_path: Path, daemon_id: str) -> list[tuple[str, int, int]]:
    """(channel, seq, log time ns) of each input block ``daemon_id`` recorded: the time its
    pipeline took the block in (after Zenoh, zenoh-ext's recovery and the intake's queue)."""
    from sinewatch.runtime.replay import read_recording

    out = []
    for path in sorted((tmp_path / daemon_id).glob("*.mcap")):
        for kind, item in read_recording(path, roles=frozenset({"input"})):
            if kind == "message" and item.role == "input" and len(item.payload) >= 16:
                out.append(
                    (item.topic.rsplit("/", 1)[-1], int.from_bytes(item.payload[8:16], "little"), item.log_time_ns)
                )
    return out


def _first_per_channel(msgs: list[dict[str, Any]], key: str, keep: Any) -> dict[str, dict[str, Any]]:
    firsts: dict[str, dict[str, Any]] = {}
    for m in msgs:
        if keep(m) and (m["channel"] not in firsts or m[key] < firsts[m["channel"]][key]):
            firsts[m["channel"]] = m
    return firsts


def _sent(sent_wall: list[float], seq: int) -> str:
    return f"sent {sent_wall[seq]:.3f}" if 0 <= seq < len(sent_wall) else "sent ?"


TAKEOVER_STEPS = ("lease is running out", "owner's key is gone", "won term", "took over shard", "block(s) of history")


def takeover_timeline(
    tmp_path: Path,
    new_owner: str,
    fencing: dict[str, Any],
    fault_wall: float,
    expiry_wall: float,
    recorded: list[dict[str, Any]],
    observed: dict[str, list[dict[str, Any]]],
    sent_wall: list[float],
) -> str:
    """Where a takeover's time went, in seconds from the old owner's lease expiry (at its
    latest): the new owner's log (the lease seen running out, then gone; the election won; the
    takeover's own work; its history query answered), its first estimate of the new term as it
    published it (its recording), the last channel's first, and when this test's subscriber
    got that one (the block each estimate is of, with the gateway's time of sending it)."""
    rel = lambda t: f"{t - expiry_wall:+7.3f} s"
    lines = [
        f"{rel(t)} {new_owner}: {text}" for t, text in log_events(tmp_path, new_owner, fault_wall, *TAKEOVER_STEPS)
    ]
    firsts = _first_per_channel(recorded, "_published_ns", lambda m: m.get("fencing") == fencing)
    if firsts:
        first = min(firsts.values(), key=lambda m: m["_published_ns"])
        last = max(firsts.values(), key=lambda m: m["_published_ns"])
        for what, m in (("first estimate of the term published", first), ("last channel's first published", last)):
            lines.append(
                f"{rel(m['_published_ns'] / 1e9)} {what}: {m['channel']} seq {m['seq']} ({_sent(sent_wall, m['seq'])})"
            )
        seen = [e["_wall"] for e in observed.get(last["channel"], []) if e.get("fencing") == fencing]
        if seen:
            lines.append(f"{rel(min(seen))} ... and drained by this test's subscriber")
    return f"takeover by {new_owner} ({fencing}), lease expiry at {expiry_wall:.3f}:\n  " + "\n  ".join(
        sorted(lines, key=lambda line: float(line.split()[0]))
    )


RESTART_STEPS = ("could not be recovered", "block(s) of history", "keep-alive failed", "standing by", "took over")


def restart_timeline(
    tmp_path: Path,
    daemon_ids: list[str],
    back_wall: float,
    recorded: dict[str, list[dict[str, Any]]],
    observed: dict[str, list[dict[str, Any]]],
    sent_wall: list[float],
) -> str:
    """Where a router restart's time went, in seconds from the router's return (listening
    again): for each daemon, the first block its pipeline took in after it and the first
    estimate it published after it, the last channel's first estimate (as published, and as this
    test's subscriber drained it), and its log's lines on losses and ownership."""
    rel = lambda t: f"{t - back_wall:+7.3f} s"
    back_ns = back_wall * 1e9
    lines = []
    for d in daemon_ids:
        lines += [f"{rel(t)} {d}: {text}" for t, text in log_events(tmp_path, d, back_wall - 5, *RESTART_STEPS)[:5]]
        after_back = [i for i in recorded_inputs(tmp_path, d) if i[2] > back_ns]
        if after_back:
            ch, seq, t_ns = min(after_back, key=lambda i: i[2])
            lines.append(f"{rel(t_ns / 1e9)} {d}: first block taken in: {ch} seq {seq} ({_sent(sent_wall, seq)})")
            live = [i for i in after_back if 0 <= i[1] < len(sent_wall) and sent_wall[i[1]] > back_wall]
            if live:
                ch, seq, t_ns = min(live, key=lambda i: i[2])
                lines.append(
                    f"{rel(t_ns / 1e9)} {d}: first block sent after the return taken in: {ch} seq {seq} ({_sent(sent_wall, seq)})"
                )
        firsts = _first_per_channel(recorded.get(d, []), "_published_ns", lambda m: m["_published_ns"] > back_ns)
        if firsts:
            first = min(firsts.values(), key=lambda m: m["_published_ns"])
            last = max(firsts.values(), key=lambda m: m["_published_ns"])
            lines.append(
                f"{rel(first['_published_ns'] / 1e9)} {d}: first estimate published: {first['channel']} seq {first['seq']}"
            )
            lines.append(
                f"{rel(last['_published_ns'] / 1e9)} {d}: last channel's first published: {last['channel']} seq "
                f"{last['seq']} ({_sent(sent_wall, last['seq'])})"
            )
            seen = [e["_wall"] for e in observed.get(last["channel"], []) if e["_wall"] > back_wall]
            if seen:
                lines.append(f"{rel(min(seen))} {d}: ... and drained by this test's subscriber")
    return f"router back at {back_wall:.3f}:\n  " + "\n  ".join(sorted(lines, key=lambda line: float(line.split()[0])))


def admin(session: zenoh.Session) -> list[dict[str, Any]]:
    return [
        json.loads(r.ok.payload.to_bytes())
        for r in session.get("sinewatch/admin/*/channels", timeout=5.0)
        if r.ok is not None
    ]


def wait_warm(session: zenoh.Session, daemon_id: str, shard_id: str, timeout: float = WAIT) -> None:
    """Until ``daemon_id``, a standby of ``shard_id``, holds a snapshot of its shard (its admin
    reply lists the snapshot's channels), asked at each snapshot its shard's owner puts: a
    standby that has none yet (just restarted) asks the caches for everything they hold at a
    takeover (13,312 blocks, 30 s to its first estimate beside the chaos test's burners)."""
    snapshot = threading.Event()
    sub = session.declare_subscriber(f"sinewatch/admin/shard/{shard_id}/snapshot", lambda _: snapshot.set())
    deadline = time.monotonic() + timeout
    puts, answers = 0, 0  # the owner's snapshots seen here, and the daemon's admin answers to them
    try:
        while snapshot.wait(max(0.0, deadline - time.monotonic())):
            snapshot.clear()
            puts += 1
            replies = [r.ok for r in session.get(f"sinewatch/admin/{daemon_id}/channels", timeout=5.0) if r.ok]
            answers += len(replies)
            if any(json.loads(r.payload.to_bytes())["channels"] for r in replies):
                return
        # what each daemon says of itself, for the failure's message: who owns the shard, whose lease is proven
        roles = [
            {k: a.get(k) for k in ("daemon_id", "role", "term", "lease_proven")} | {"channels": len(a["channels"])}
            for a in admin(session)
        ]
        raise AssertionError(
            f"{daemon_id} holds no snapshot of {shard_id} after {timeout} s: {puts} snapshot(s) of the shard "
            f"seen here, {answers} answer(s) from {daemon_id}; the daemons: {roles}"
        )
    finally:
        sub.undeclare()


def check_channel(msgs: list[dict[str, Any]], sent: int, lost_for_good: int = 0) -> tuple[int, int]:
    """(gaps flagged, blocks lost) of one channel, checked against each other: each (seq)
    at most once, in order, every seq up to ``sent`` either estimated or counted in the
    gap_blocks of the estimate after it; the blocks after the last estimate (none can flag
    them) at most the ``lost_for_good`` the daemons reported (``unrecovered`` ErrorReports)."""
    if late := _late_in_a_gap(msgs):
        print(f"{msgs[0]['channel']}: {len(late)} recorded estimate(s) no reader had before a newer term's gap: {late}")
        msgs = [m for m in msgs if m["seq"] not in late]
    seqs = [m["seq"] for m in msgs]
    assert len(seqs) == len(set(seqs)), f"an estimate published twice: {seqs}"
    assert seqs == sorted(seqs)
    trailing = sent - 1 - (seqs[-1] if seqs else -1)
    assert trailing <= lost_for_good, f"{trailing} last block(s) neither estimated nor reported lost"
    missing = sorted(set(range(sent - trailing)) - set(seqs))
    flagged = [m for m in msgs if m["diagnostics"]["gap"]]
    gaps = [(m["seq"], m["diagnostics"]["gap_blocks"], (m.get("fencing") or {}).get("term")) for m in flagged]
    assert sum(m["diagnostics"]["gap_blocks"] for m in flagged) == len(missing), (
        f"blocks missing {missing}, gaps flagged (seq, gap_blocks, term) {gaps}, "
        f"terms {sorted({(m.get('fencing') or {}).get('term') for m in msgs})}"
    )
    # each gap counts exactly the seqs missing right before it: those between the estimate before it and it
    # (seqs are sorted; every seq in between is missing: linear, where comparing each missing seq with every
    # earlier estimate took the 50-fault run's check ~10 s a channel)
    previous = dict(zip(seqs[1:], seqs[:-1], strict=True))
    for m in flagged:
        assert m["diagnostics"]["gap_blocks"] == m["seq"] - previous.get(m["seq"], -1) - 1, (m["seq"], gaps)
    return len(flagged), len(missing) + trailing


if __name__ == "__main__":  # ``python cluster_procs.py proxy|gateway PORT``: see ProxyProcess, GatewayProcess
    {"proxy": _serve_proxy, "gateway": _serve_gateway}[sys.argv[1]](int(sys.argv[2]))
