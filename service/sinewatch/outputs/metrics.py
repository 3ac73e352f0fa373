"""Prometheus metrics and a health endpoint (``serve --metrics PORT``, ``[metrics]``).

One small HTTP server on its own thread (so a stuck event loop cannot stall a scrape, and
``/healthz`` can say the loop is stuck):

* ``GET /metrics``: the Prometheus text format, made by ``prometheus-client`` from a
  collector that reads the daemon's own counters at scrape time, so counting costs the data
  path nothing beyond what the daemon counts anyway (one histogram bucket per input for
  latency). Names (all prefixed ``sinewatch_``): ``blocks_received_total`` (intake),
  ``blocks_processed_total`` (through the pipeline), ``estimates_total``,
  ``rejections_total{kind}``, ``dropped_total``, ``backpressure_waits_total``,
  ``unrecovered_total``, ``queue_depth``, ``channels``, ``latency_seconds`` (histogram:
  receive to outputs handed to the sinks), ``recording_bytes`` (this run's MCAP files on
  disk), ``recording_messages_total``, ``sink_up{sink}``, ``sink_failures_total{sink}``,
  ``sink_skipped_total{sink}``, ``worker_cpu_seconds_total{worker}`` (process CPU time; one
  worker, ``"0"``, today), ``uptime_seconds``, ``event_loop_age_seconds`` (since the loop
  last turned), ``foxglove_*`` when ``--foxglove`` is on; plus prometheus-client's standard
  ``process_*`` metrics.
* ``GET /healthz``: JSON, 200 when the daemon is running, its event loop turned within
  ``stall_s`` and every sink is ok; 503 otherwise (``status`` says which: ``starting``,
  ``stopping``, ``stalled``, ``sink_failed``).
"""

from __future__ import annotations

import bisect
import json
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from prometheus_client import CollectorRegistry, ProcessCollector, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from prometheus_client.registry import Collector

log = logging.getLogger("sinewatch.outputs.metrics")

# receive -> outputs handed to the sinks, seconds: 50 us .. 10 s
LATENCY_BUCKETS_S = (
    5e-5,
    1e-4,
    2.5e-4,
    5e-4,
    1e-3,
    2.5e-3,
    5e-3,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
    5.0,
    10.0,
)


class LatencyHistogram:
    """Counts per bucket, written by the event loop only (no lock: one writer; a scrape
    reads a copy and derives ``count`` from the buckets so the exposition is consistent)."""

    def __init__(self, bounds_s: tuple[float, ...] = LATENCY_BUCKETS_S) -> None:
        self.bounds_ns = [round(b * 1e9) for b in bounds_s]
        self.bounds_s = bounds_s
        self.counts = [0] * (len(bounds_s) + 1)  # the last one: above every bound (+Inf)
        self.sum_ns = 0

    def observe_ns(self, ns: int) -> None:
        self.counts[bisect.bisect_left(self.bounds_ns, ns)] += 1
        self.sum_ns += ns

    def cumulative(self) -> tuple[list[tuple[str, float]], float]:
        counts = list(self.counts)
        total = 0
        buckets: list[tuple[str, float]] = []
        for bound, n in zip((*self.bounds_s, float("inf")), counts, strict=True):
            total += n
            buckets.append(("+Inf" if bound == float("inf") else repr(bound), total))
        return buckets, self.sum_ns / 1e9


@dataclass
class Snapshot:
    """What the daemon reports at a scrape (read on the HTTP thread)."""

    blocks_received: int
    blocks_processed: int
    estimates: int
    rejections_by_kind: dict[str, int]
    dropped: int
    backpressure_waits: int
    unrecovered: int
    queue_depth: int
    channels: int
    recording_bytes: int
    recording_messages: int
    sinks: list[dict[str, Any]]
    cpu_seconds_by_worker: dict[str, float]
    uptime_s: float
    loop_age_s: float
    latency: LatencyHistogram
    foxglove: dict[str, int] = field(default_factory=dict)


@dataclass
class Health:
    ok: bool
    body: dict[str, Any]


def health(*, running: bool, stopping: bool, loop_age_s: float, stall_s: float, sinks: list[dict[str, Any]]) -> Health:
    """The verdict of ``/healthz``: the first thing wrong, in the order a reader cares."""
    failed = [s["name"] for s in sinks if not s["ok"]]
    if not running:
        status = "starting"
    elif stopping:
        status = "stopping"
    elif loop_age_s > stall_s:
        status = "stalled"
    elif failed:
        status = "sink_failed"
    else:
        status = "ok"
    body = {
        "status": status,
        "event_loop_age_s": round(loop_age_s, 6),
        "stall_s": stall_s,
        "sinks": [{k: s[k] for k in ("name", "ok", "failures", "last_error")} for s in sinks],
    }
    return Health(status == "ok", body)


class DaemonCollector(Collector):
    """Turns a :class:`Snapshot` into Prometheus metric families at each scrape."""

    def __init__(self, snapshot: Callable[[], Snapshot]) -> None:
        self._snapshot = snapshot

    def collect(self) -> list[Metric]:
        s = self._snapshot()

        def counter(name: str, doc: str, value: float) -> CounterMetricFamily:
            return CounterMetricFamily(f"sinewatch_{name}", doc, value=value)

        def gauge(name: str, doc: str, value: float) -> GaugeMetricFamily:
            return GaugeMetricFamily(f"sinewatch_{name}", doc, value=value)

        out: list[Metric] = [
            counter("blocks_received", "Input blocks received from Zenoh", s.blocks_received),
            counter("blocks_processed", "Input blocks taken through the pipeline", s.blocks_processed),
            counter("estimates", "Estimates published", s.estimates),
            counter("dropped", "Input blocks dropped by the intake queue (queue_policy drop)", s.dropped),
            counter(
                "backpressure_waits", "Times the intake waited for room (queue_policy block)", s.backpressure_waits
            ),
            counter("unrecovered", "Blocks Zenoh reported missed for good", s.unrecovered),
            gauge("queue_depth", "Input blocks waiting for the pipeline", s.queue_depth),
            gauge("channels", "Channels with an estimator", s.channels),
            gauge("recording_bytes", "Bytes of this run's MCAP files on disk", s.recording_bytes),
            counter("recording_messages", "Messages written to MCAP", s.recording_messages),
            gauge("uptime_seconds", "Seconds since the daemon started", s.uptime_s),
            gauge("event_loop_age_seconds", "Seconds since the event loop last turned", s.loop_age_s),
        ]
        rejections = CounterMetricFamily(
            "sinewatch_rejections", "Rejected inputs (ErrorReports) by kind", labels=["kind"]
        )
        for kind, n in sorted(s.rejections_by_kind.items()):
            rejections.add_metric([kind], n)
        out.append(rejections)
        up = GaugeMetricFamily("sinewatch_sink_up", "1 while the sink works, 0 while it is failed", labels=["sink"])
        failures = CounterMetricFamily("sinewatch_sink_failures", "Failures of each sink", labels=["sink"])
        skipped = CounterMetricFamily("sinewatch_sink_skipped", "Outputs a failed sink skipped", labels=["sink"])
        for sink in s.sinks:
            up.add_metric([sink["name"]], 1.0 if sink["ok"] else 0.0)
            failures.add_metric([sink["name"]], sink["failures"])
            skipped.add_metric([sink["name"]], sink["skipped"])
        out += [up, failures, skipped]
        cpu = CounterMetricFamily("sinewatch_worker_cpu_seconds", "CPU time of each worker process", labels=["worker"])
        for worker, seconds in sorted(s.cpu_seconds_by_worker.items()):
            cpu.add_metric([worker], seconds)
        out.append(cpu)
        buckets, total_s = s.latency.cumulative()
        out.append(
            HistogramMetricFamily(
                "sinewatch_latency_seconds",
                "Input received to its outputs handed to the sinks",
                buckets=buckets,
                sum_value=total_s,
            )
        )
        for name, value in sorted(s.foxglove.items()):
            out.append(counter(f"foxglove_{name}", f"Foxglove live view: {name.replace('_', ' ')}", value))
        return out


class MetricsServer:
    """``/metrics`` and ``/healthz`` on ``host:port`` (port 0: any free one; see ``port``)."""

    def __init__(self, host: str, port: int, snapshot: Callable[[], Snapshot], check: Callable[[], Health]) -> None:
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(DaemonCollector(snapshot))
        ProcessCollector(registry=self.registry)
        registry, check_ = self.registry, check

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                path = self.path.split("?", 1)[0]
                if path == "/metrics":
                    self._send(200, CONTENT_TYPE_LATEST, generate_latest(registry))
                elif path == "/healthz":
                    verdict = check_()
                    self._send(200 if verdict.ok else 503, "application/json", json.dumps(verdict.body).encode())
                else:
                    self._send(404, "text/plain; charset=utf-8", b"not found: try /metrics or /healthz\n")

            def _send(self, code: int, content_type: str, body: bytes) -> None:
                self.send_response(code)
                self.send_header("Content-Type", content_type)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: Any) -> None:  # scrapes are not news
                log.debug("%s " + format, self.address_string(), *args)

        self._server = ThreadingHTTPServer((host, port), Handler)
        self._server.daemon_threads = True
        self.port: int = self._server.server_address[1]
        self._thread = threading.Thread(target=self._server.serve_forever, name="sinewatch-metrics", daemon=True)

    def start(self) -> None:
        self._thread.start()
        log.info("metrics on http://%s:%d/metrics, health on /healthz", *self._server.server_address[:2])

    def close(self) -> None:
        if self._thread.is_alive():
            self._server.shutdown()
            self._thread.join()
        self._server.server_close()


__all__ = ["LATENCY_BUCKETS_S", "Health", "LatencyHistogram", "MetricsServer", "Snapshot", "health"]
