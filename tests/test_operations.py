"""Operating the daemon: Prometheus ``/metrics`` and ``/healthz`` (``serve --metrics PORT``),
and systemd's notification protocol (READY, WATCHDOG, STOPPING) over a real unix datagram
socket. Real daemons on loopback Zenoh, real HTTP on 127.0.0.1."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from conftest import TIMEOUT, make_config, publishing, run_daemon, take

prometheus_client = pytest.importorskip("prometheus_client", reason="the metrics extra (pip install '.[metrics]')")
from prometheus_client.parser import text_string_to_metric_families  # noqa: E402

from sinewatch.clients import BlockPublisher, connect, subscribe_errors, subscribe_estimates  # noqa: E402
from sinewatch.clients.session import free_loopback_port  # noqa: E402
from sinewatch.outputs.metrics import LATENCY_BUCKETS_S, LatencyHistogram, health  # noqa: E402
from sinewatch.runtime.sdnotify import Notifier  # noqa: E402
from sinewatch.schemas.codec import Block, encode_block_binary  # noqa: E402
from sinewatch.schemas.config import MetricsSection, RecordingSection  # noqa: E402


def _get(url: str) -> tuple[int, str, str]:
    """(status, content type, body) of a GET, 4xx/5xx included."""
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT) as r:
            return r.status, r.headers["Content-Type"], r.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers["Content-Type"], exc.read().decode()


def _samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """{(sample name, sorted labels): value} of a Prometheus text exposition."""
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def _blocks(n: int, fs: float = 10_000.0, size: int = 500) -> list[Block]:
    t = np.arange(n * size) / fs
    x = np.sin(2 * np.pi * 50.0 * t)
    return [Block("m/a", i, 1_000_000_000 + i * 50_000_000, fs, x[i * size : (i + 1) * size]) for i in range(n)]


def _on_loop(daemon, fn):
    """Run ``fn`` on the daemon's event loop (from the client's thread) and wait for it."""
    loop = daemon.intake._loop

    async def call():
        return fn()

    return asyncio.run_coroutine_threadsafe(call(), loop).result(TIMEOUT)


def test_metrics_count_what_the_daemon_did_and_healthz_says_ok(tmp_path):
    port = free_loopback_port()
    config = make_config(tmp_path, metrics=MetricsSection(port=port))
    blocks = _blocks(20)
    nan_block = Block("m/a", 20, blocks[-1].t0_ns + 50_000_000, 10_000.0, np.array([0.1, np.nan]))

    def client(daemon, ep):
        with publishing(ep, "m/a", subscribe_estimates, subscribe_errors) as (pub, [est, err]):
            for blk in blocks:
                pub.publish_raw("m/a", encode_block_binary(blk))
            pub.publish_raw("m/a", encode_block_binary(nan_block))  # non_finite
            pub.publish_raw("m/a", encode_block_binary(blocks[-1]))  # duplicate
            got, errors = take(est, len(blocks)), take(err, 2)
            _on_loop(daemon, daemon.pipeline.flush_sinks)  # the recording's bytes reach the disk
            on_disk = sum(p.stat().st_size for p in daemon.recording_paths)
            cpu_before = time.process_time()
            metrics = _get(f"http://127.0.0.1:{port}/metrics")
            cpu_after = time.process_time()
            healthz = _get(f"http://127.0.0.1:{port}/healthz")
            missing = _get(f"http://127.0.0.1:{port}/nothing")
            return got, errors, on_disk, (cpu_before, cpu_after), metrics, healthz, missing

    (got, errors, on_disk, cpu_span, metrics, healthz, missing), _daemon, code = run_daemon(config, client)
    assert code == 0 and len(got) == 20 and sorted(e["kind"] for e in errors) == ["duplicate", "non_finite"]

    status, ctype, text = metrics
    assert status == 200 and ctype.startswith("text/plain; version=")
    m = _samples(text)
    assert m[("sinewatch_blocks_received_total", ())] == 22
    assert m[("sinewatch_blocks_processed_total", ())] == 22
    assert m[("sinewatch_estimates_total", ())] == 20
    assert m[("sinewatch_rejections_total", (("kind", "non_finite"),))] == 1
    assert m[("sinewatch_rejections_total", (("kind", "duplicate"),))] == 1
    assert m[("sinewatch_dropped_total", ())] == 0
    assert m[("sinewatch_queue_depth", ())] == 0
    assert m[("sinewatch_channels", ())] == 1
    # one latency observation per input, in buckets that add up
    assert m[("sinewatch_latency_seconds_count", ())] == 22
    assert m[("sinewatch_latency_seconds_bucket", (("le", "+Inf"),))] == 22
    buckets = [m[("sinewatch_latency_seconds_bucket", (("le", repr(b)),))] for b in LATENCY_BUCKETS_S]
    assert buckets == sorted(buckets) and 0 < m[("sinewatch_latency_seconds_sum", ())] < 22 * 10.0
    assert m[("sinewatch_recording_bytes", ())] >= on_disk > 0
    assert m[("sinewatch_recording_messages_total", ())] >= 22 + 20 + 2  # inputs, estimates, errors (+ status)
    assert m[("sinewatch_sink_up", (("sink", "mcap"),))] == 1 and m[("sinewatch_sink_up", (("sink", "zenoh"),))] == 1
    cpu = m[("sinewatch_worker_cpu_seconds_total", (("worker", "0"),))]
    assert cpu_span[0] <= cpu <= cpu_span[1]  # the daemon's process (this one) CPU time, read at the scrape
    assert ("process_cpu_seconds_total", ()) in m  # prometheus-client's process collector

    status, ctype, body = healthz
    assert status == 200 and ctype == "application/json"
    verdict = json.loads(body)
    assert verdict["status"] == "ok" and verdict["event_loop_age_s"] < verdict["stall_s"]
    assert {s["name"] for s in verdict["sinks"]} == {"zenoh", "mcap"}
    assert missing[0] == 404


def test_healthz_is_503_while_a_sink_is_failed(tmp_path):
    """A recorder that cannot open its file (its directory is a file) fails at start and
    stays failed (retry in an hour): estimation goes on, health says sink_failed."""
    (tmp_path / "not-a-dir").write_text("")
    port = free_loopback_port()
    config = make_config(
        tmp_path,
        metrics=MetricsSection(port=port),
        recording=RecordingSection(directory=tmp_path / "not-a-dir" / "rec"),
        sink_retry_s=3600.0,
    )

    def client(_daemon, _ep):
        status, _, body = _get(f"http://127.0.0.1:{port}/healthz")
        metrics = _samples(_get(f"http://127.0.0.1:{port}/metrics")[2])
        return status, json.loads(body), metrics

    (status, body, metrics), _daemon, code = run_daemon(config, client)
    assert code == 0 and status == 503 and body["status"] == "sink_failed"
    [mcap] = [s for s in body["sinks"] if s["name"] == "mcap"]
    assert not mcap["ok"] and "NotADirectoryError" in mcap["last_error"]
    assert metrics[("sinewatch_sink_up", (("sink", "mcap"),))] == 0
    assert metrics[("sinewatch_sink_failures_total", (("sink", "mcap"),))] == 1


def test_health_verdicts_in_order():
    ok = {"name": "zenoh", "ok": True, "failures": 0, "last_error": None}
    bad = {"name": "mcap", "ok": False, "failures": 1, "last_error": "OSError: full"}
    args = dict(running=True, stopping=False, loop_age_s=0.1, stall_s=5.0, sinks=[ok])
    assert health(**args).ok and health(**args).body["status"] == "ok"
    assert health(**{**args, "running": False}).body["status"] == "starting"
    assert health(**{**args, "stopping": True}).body["status"] == "stopping"
    assert health(**{**args, "loop_age_s": 5.1}).body["status"] == "stalled"
    assert health(**{**args, "sinks": [ok, bad]}).body["status"] == "sink_failed"
    assert not health(**{**args, "loop_age_s": 5.1, "sinks": [bad]}).ok


def test_latency_histogram_buckets_are_upper_inclusive():
    h = LatencyHistogram((1e-3, 1e-2))
    for ns in (0, 1_000_000, 1_000_001, 10_000_000, 10_000_001):
        h.observe_ns(ns)
    buckets, total_s = h.cumulative()
    assert buckets == [("0.001", 2), ("0.01", 4), ("+Inf", 5)]
    assert total_s == pytest.approx(0.022000002)


# ---- systemd ------------------------------------------------------------------------------
@pytest.fixture
def notify_socket(tmp_path, monkeypatch):
    """A unix datagram socket standing in for systemd's, named in NOTIFY_SOCKET."""
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(TIMEOUT)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    monkeypatch.setenv("WATCHDOG_USEC", "100000")  # 0.1 s: the daemon pings every 0.05 s
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    yield sock
    sock.close()


def _datagram(sock: socket.socket) -> dict[str, str]:
    return dict(line.split("=", 1) for line in sock.recv(4096).decode().splitlines())


def test_systemd_ready_watchdog_and_stopping(tmp_path, notify_socket):
    config = make_config(tmp_path, recording=RecordingSection(enabled=False))

    def client(daemon, ep):
        first = _datagram(notify_socket)  # READY comes once the daemon is subscribed
        with connect([ep]) as s:
            pub = BlockPublisher(s)
            subscribed = pub.wait_for_subscriber("n/a", TIMEOUT)
        pings = [_datagram(notify_socket) for _ in range(3)]  # from the event loop, every 0.05 s
        return first, subscribed, pings

    (first, subscribed, pings), _daemon, code = run_daemon(config, client)
    assert code == 0
    assert first["READY"] == "1" and first["MAINPID"] == str(os.getpid()) and "sinewatch/in/**" in first["STATUS"]
    assert subscribed
    assert pings == [{"WATCHDOG": "1"}] * 3
    rest = []
    notify_socket.settimeout(0)  # the daemon has exited: everything it sent is queued
    while True:
        try:
            rest.append(_datagram(notify_socket))
        except BlockingIOError:
            break
    stopping = [d for d in rest if "STOPPING" in d]
    assert len(stopping) == 1 and stopping[0]["STOPPING"] == "1" and "draining" in stopping[0]["STATUS"]


def test_notifier_reads_the_environment_as_sd_notify_does(tmp_path):
    assert not Notifier({}).enabled and not Notifier({}).notify("READY=1")
    abstract = Notifier({"NOTIFY_SOCKET": "@sinewatch-test", "WATCHDOG_USEC": "2000000"})
    assert abstract.address == "\0sinewatch-test" and abstract.watchdog_s == 2.0
    other_pid = Notifier({"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"})
    assert other_pid.watchdog_s is None and not other_pid.watchdog()  # the watchdog is another process's
    gone = Notifier({"NOTIFY_SOCKET": str(Path(tmp_path) / "missing.sock")})
    assert not gone.notify("READY=1") and gone.sent == 0  # logged, never raised


def test_serve_flags_turn_on_metrics_and_foxglove_as_the_config_would(tmp_path):
    """``sinewatch serve --metrics PORT --foxglove PORT`` as a user runs it: the flags set
    ``[metrics] port`` and ``[foxglove] port``; both answer once the daemon says it is up."""
    pytest.importorskip("foxglove")
    websockets = pytest.importorskip("websockets.sync.client")
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f'[zenoh]\nlisten = ["tcp/127.0.0.1:{free_loopback_port()}"]\n[recording]\nenabled = false\n'
        '[[rules]]\nestimator = "ipdft"\n'
    )
    mport, fport = free_loopback_port(), free_loopback_port()
    serve = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sinewatch",
            "serve",
            "--config",
            str(cfg),
            "--metrics",
            str(mport),
            "--foxglove",
            str(fport),
            "--workers",
            "1",  # the flags in one process (ports per worker: test_workers.py)
        ],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert serve.stderr is not None
        lines = []
        while not (line := serve.stderr.readline()).count("sinewatch daemon"):  # start() logs it last
            assert line, "".join(lines)
            lines.append(line)
        status, _, body = _get(f"http://127.0.0.1:{mport}/healthz")
        with websockets.connect(f"ws://127.0.0.1:{fport}", subprotocols=["foxglove.sdk.v1"]) as ws:
            info = json.loads(ws.recv(timeout=TIMEOUT))
            advertised = json.loads(ws.recv(timeout=TIMEOUT))
        metrics = _samples(_get(f"http://127.0.0.1:{mport}/metrics")[2])
    finally:
        serve.send_signal(signal.SIGINT)
        _, err = serve.communicate(timeout=60)
    assert serve.returncode == 0, err
    assert status == 200 and json.loads(body)["status"] == "ok"
    assert info["op"] == "serverInfo" and info["name"] == "sinewatch sinewatch"
    assert [c["topic"] for c in advertised["channels"]] == ["sinewatch/log"]
    assert metrics[("sinewatch_foxglove_subscriptions_total", ())] == 0
    assert metrics[("sinewatch_blocks_received_total", ())] == 0
