"""Live view in Foxglove: a pipeline sink that serves the Foxglove WebSocket protocol
(``serve --foxglove PORT``, ``[foxglove]``), made with the official ``foxglove-sdk``.

Open Foxglove, "Open connection", ``ws://HOST:PORT``. Topics (JSON, each with its JSON
Schema, so the Plot panel offers the fields):

* the daemon's outputs on their Zenoh keys, byte for byte what Zenoh carries and MCAP
  records: ``sinewatch/est/<channel>`` (Estimate: plot ``.frequency_hz[0]``,
  ``.amplitude[0]``, ``.offset``, ``.rocof_hz_per_s[0]``), ``sinewatch/err/...``
  (ErrorReport), ``sinewatch/status/<daemon_id>`` (Status) and the power-quality messages;
* ``sinewatch/samples/<channel>`` (``sinewatch.SamplesSummary``), one per input block: its
  time as ``timestamp`` ``{sec, nsec}`` beside ``timestamp_ns``, ``min``, ``max``,
  ``mean`` and ``rms`` of the measurement (column 0; plot them against time for the
  envelope), and ``samples``: every ``stride``-th sample, at most ``input_points`` of them
  (plot ``.samples[:]`` with the x axis on "index" for the latest block's waveform);
* ``sinewatch/log`` (``foxglove.Log``): the daemon's log lines, from a logging handler on
  the ``sinewatch`` logger.

Clients of either subprotocol: the SDK's server (foxglove-sdk 0.30) accepts only
``foxglove.sdk.v1``; Lichtblick, PlotJuggler and Foxglove Studio releases before it ask for
``foxglove.websocket.v1`` (the same protocol under its earlier name). So, unless
``websocket_v1 = false``, the SDK's server listens on an ephemeral loopback port and
:class:`SubprotocolRelay` listens on the configured one: it reads each client's HTTP
upgrade request, names the subprotocol the SDK knows in it (and the client's own in the
answer), then copies bytes both ways (WebSocket frames do not depend on the name).
``make bench-foxglove-relay`` (``python -m sinewatch.apps.bench.foxglove_relay``) measures what the
relay costs against a client of the SDK's own port.

Each message's log time is the time the daemon received its input (the log time the MCAP
recording uses), so a live session and a recording of it line up; the data time is the
message's ``timestamp``.

Cost. Nothing is serialised for a topic no client subscribes to. Outputs are already JSON:
they are handed to the SDK as they are (no re-encoding), and the SDK queues them per
client, at most ``backlog`` messages, dropping the oldest for a client that reads too
slowly: a slow client never slows the daemon. Input summaries need a decode, some numpy
and JSON floats (Python's float formatting: ~1 us a sample, the bulk of their cost), so they
are made on a worker thread, at most ``input_rate_hz`` a second (all channels together;
past it a block is skipped and counted, ``inputs_over_rate``), ``input_points`` samples
each; the event loop only puts the raw payload on a bounded queue (``queue``), and when the
worker falls behind the newest block is dropped and counted (``inputs_dropped``). ``sinewatch bench e2e --foxglove`` measures the daemon with a client
subscribed to everything, against the same run without.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import queue
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import foxglove
import numpy as np
from foxglove.channels import LogChannel
from foxglove.messages import Log, LogLevel, Timestamp
from foxglove.websocket import ServerListener

from sinewatch.core.pipeline import NullSink
from sinewatch.schemas.codec import Block, decode_block
from sinewatch.schemas.config import SinewatchConfig
from sinewatch.schemas.errors import InputError
from sinewatch.schemas.frame import decode_frame, is_frame
from sinewatch.schemas.messages import MESSAGE_MODELS
from sinewatch.schemas.power_quality import PQ_MESSAGE_MODELS

log = logging.getLogger("sinewatch.foxglove")

LOG_TOPIC = "sinewatch/log"
SAMPLES_PREFIX = "sinewatch/samples"
SUMMARY_SCHEMA_NAME = "sinewatch.SamplesSummary"

_TIME_SCHEMA = {
    "type": "object",
    "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}},
    "required": ["sec", "nsec"],
}
SUMMARY_SCHEMA: dict[str, Any] = {
    "title": SUMMARY_SCHEMA_NAME,
    "type": "object",
    "description": "One input block, summarised for plotting: its measurement column's extremes, mean, RMS "
    "and every stride-th sample",
    "properties": {
        "channel": {"type": "string"},
        "seq": {"type": "integer"},
        "timestamp": {**_TIME_SCHEMA, "description": "Time of the block's first sample"},
        "timestamp_ns": {"type": "integer", "description": "Time of the block's first sample, ns since the epoch"},
        "sample_rate_hz": {"type": "number"},
        "n_samples": {"type": "integer"},
        "unit": {"type": ["string", "null"]},
        "min": {"type": "number"},
        "max": {"type": "number"},
        "mean": {"type": "number"},
        "rms": {"type": "number"},
        "stride": {"type": "integer", "description": "samples[i] is the block's sample i * stride"},
        "samples": {"type": "array", "items": {"type": "number"}},
    },
    "required": ["channel", "seq", "timestamp", "timestamp_ns", "sample_rate_hz", "n_samples", "samples"],
}

_LEVELS = (
    (logging.CRITICAL, LogLevel.Fatal),
    (logging.ERROR, LogLevel.Error),
    (logging.WARNING, LogLevel.Warning),
    (logging.INFO, LogLevel.Info),
    (logging.DEBUG, LogLevel.Debug),
)


def summaries(payload: bytes, encoding: str, max_points: int) -> list[dict[str, Any]]:
    """The ``sinewatch/samples/<channel>`` messages of one input: one for a block, one per
    readable channel of a multi-channel frame (a NaN column is left out, as the pipeline
    rejects that channel's block); InputError when nothing in it is readable."""
    if not is_frame(payload, encoding):
        return [summarise(payload, encoding, max_points)]
    frame = decode_frame(payload, encoding)
    out = []
    for c in range(frame.n_channels):
        try:
            out.append(_summary(frame.block(c), max_points))
        except InputError:
            continue
    if not out:
        raise InputError("samples: expected a finite channel in the frame, got none")
    return out


def summarise(payload: bytes, encoding: str, max_points: int) -> dict[str, Any]:
    """The ``sinewatch/samples/<channel>`` message for one input block (raises
    :class:`InputError` for a block the pipeline rejects as well)."""
    return _summary(decode_block(payload, encoding), max_points)


def _summary(block: Block, max_points: int) -> dict[str, Any]:
    x = block.samples if block.samples.ndim == 1 else block.samples[:, 0]
    if x.size == 0 or not np.isfinite(x).all():
        raise InputError("samples: expected finite values, got none or non-finite ones")
    stride = max(1, math.ceil(x.size / max_points))
    sec, nsec = divmod(block.t0_ns, 1_000_000_000)
    x64 = x.astype(np.float64, copy=False)
    return {
        "channel": block.channel,
        "seq": block.seq,
        "timestamp": {"sec": sec, "nsec": nsec},
        "timestamp_ns": block.t0_ns,
        "sample_rate_hz": block.sample_rate_hz,
        "n_samples": block.n_samples,
        "unit": block.unit,
        "min": float(x64.min()),
        "max": float(x64.max()),
        "mean": float(x64.mean()),
        "rms": float(np.sqrt(np.mean(x64 * x64))),
        "stride": stride,
        "samples": x64[::stride].tolist(),
    }


@dataclass
class FoxgloveCounters:
    input_summaries: int = 0  # published
    inputs_dropped: int = 0  # the summary queue was full
    inputs_over_rate: int = 0  # past input_rate_hz
    inputs_unreadable: int = 0  # not a valid block (the pipeline reports those)
    topics_refused: int = 0  # past max_topics
    log_lines: int = 0
    subscriptions: int = 0  # client subscriptions, ever

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class FoxgloveLogHandler(logging.Handler):
    """Forwards log records to a ``foxglove.Log`` channel (nothing is built while no client
    subscribes to it). Safe from any thread: the SDK's channels are."""

    def __init__(self, channel: LogChannel, counters: FoxgloveCounters, level: int = logging.INFO) -> None:
        super().__init__(level)
        self._channel = channel
        self._counters = counters
        self.setFormatter(logging.Formatter("%(message)s"))  # the message, and a traceback if any

    def emit(self, record: logging.LogRecord) -> None:
        if not self._channel.has_sinks():
            return
        try:
            ns = round(record.created * 1e9)
            sec, nsec = divmod(ns, 1_000_000_000)
            level = next((lv for threshold, lv in _LEVELS if record.levelno >= threshold), LogLevel.Unknown)
            message = Log(
                timestamp=Timestamp(sec, nsec),
                level=level,
                message=self.format(record),
                name=record.name,
                file=record.pathname,
                line=record.lineno or 0,
            )
            self._channel.log(message, log_time=ns)
            self._counters.log_lines += 1
        except Exception:  # noqa: BLE001 (logging's own contract: report through handleError, never raise)
            self.handleError(record)


class _Subscriptions(ServerListener):
    """The server's listener: which topics clients subscribe to (Foxglove calls it on its
    own thread); ``wait`` lets a caller (a test, a bench) know a subscription took effect."""

    def __init__(self, counters: FoxgloveCounters) -> None:
        self._counters = counters
        self._active: dict[str, int] = {}
        self._changed = threading.Condition()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._changed:
            self._active[channel.topic] = self._active.get(channel.topic, 0) + 1
            self._counters.subscriptions += 1
            self._changed.notify_all()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._changed:
            self._active[channel.topic] = max(0, self._active.get(channel.topic, 0) - 1)
            self._changed.notify_all()

    def wait(self, topics: list[str], timeout: float) -> bool:
        """True once every topic has a subscriber (False after ``timeout`` seconds)."""
        with self._changed:
            return self._changed.wait_for(lambda: all(self._active.get(t, 0) > 0 for t in topics), timeout)


SDK_SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
_PROTOCOL_HEADER = re.compile(rb"(?im)^sec-websocket-protocol:[ \t]*([^\r\n]*)\r\n")
_MAX_HANDSHAKE = 64 * 1024


def offered_subprotocols(request: bytes) -> list[str]:
    """The subprotocols an HTTP upgrade request offers (every Sec-WebSocket-Protocol header)."""
    return [p.strip() for m in _PROTOCOL_HEADER.finditer(request) for p in m.group(1).decode("latin-1").split(",")]


def _rename_subprotocol(head: bytes, old: str, new: str) -> bytes:
    """``head`` with each Sec-WebSocket-Protocol header naming ``new`` where it named ``old``."""

    def rename(m: re.Match[bytes]) -> bytes:
        names = [p.strip() for p in m.group(1).decode("latin-1").split(",")]
        return b"Sec-WebSocket-Protocol: " + ", ".join(new if p == old else p for p in names).encode() + b"\r\n"

    return _PROTOCOL_HEADER.sub(rename, head)


class SubprotocolRelay:
    """A TCP listener in front of the SDK's WebSocket server, on a thread of its own (its
    own event loop: the daemon's never carries a client's bytes). A client that offers
    ``foxglove.websocket.v1`` and not ``foxglove.sdk.v1`` has its upgrade request renamed to
    ``foxglove.sdk.v1`` and the server's answer renamed back; every other request goes as it
    is (the SDK answers it as it would). After the handshake the bytes are copied unchanged."""

    def __init__(self, host: str, port: int, upstream_port: int) -> None:
        self._upstream = upstream_port
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.Server | None = None
        self._connections: set[asyncio.Task[None]] = set()
        self.legacy_clients = 0  # connections that asked for foxglove.websocket.v1
        started: asyncio.Future[int] = self._loop.create_future()
        self._thread = threading.Thread(target=self._run, args=(host, port, started), daemon=True,
                                        name="sinewatch-foxglove-relay")  # fmt: skip
        self._thread.start()
        self.port = asyncio.run_coroutine_threadsafe(self._wait(started), self._loop).result()

    @staticmethod
    async def _wait(started: asyncio.Future[int]) -> int:
        return await started

    def _run(self, host: str, port: int, started: asyncio.Future[int]) -> None:
        asyncio.set_event_loop(self._loop)

        async def listen() -> None:
            try:
                self._server = await asyncio.start_server(self._connection, host, port, limit=_MAX_HANDSHAKE)
            except OSError as exc:
                started.set_exception(exc)
                return
            started.set_result(self._server.sockets[0].getsockname()[1])

        self._loop.run_until_complete(listen())
        self._loop.run_forever()

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._connections.add(task)
        upstream: asyncio.StreamWriter | None = None
        try:
            request = await reader.readuntil(b"\r\n\r\n")
            offered = offered_subprotocols(request)
            legacy = LEGACY_SUBPROTOCOL in offered and SDK_SUBPROTOCOL not in offered
            if legacy:
                self.legacy_clients += 1
                request = _rename_subprotocol(request, LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL)
            up_reader, upstream = await asyncio.open_connection("127.0.0.1", self._upstream, limit=_MAX_HANDSHAKE)
            upstream.write(request)
            answer = await up_reader.readuntil(b"\r\n\r\n")
            if legacy:
                answer = _rename_subprotocol(answer, SDK_SUBPROTOCOL, LEGACY_SUBPROTOCOL)
            writer.write(answer)
            await asyncio.gather(self._copy(reader, upstream), self._copy(up_reader, writer))
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError) as exc:
            log.debug("foxglove relay: a connection ended: %s", exc)
        finally:
            for w in (writer, upstream):
                if w is not None:
                    w.close()
            self._connections.discard(task)

    @staticmethod
    async def _copy(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
        try:
            while data := await src.read(256 * 1024):
                dst.write(data)
                await dst.drain()  # a slow reader holds its own connection back, and no other
        finally:
            if dst.can_write_eof():
                dst.write_eof()

    def close(self) -> None:
        async def stop() -> None:
            if self._server is not None:
                self._server.close()
            for task in list(self._connections):
                task.cancel()
            await asyncio.gather(*self._connections, return_exceptions=True)

        asyncio.run_coroutine_threadsafe(stop(), self._loop).result()
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join()
        self._loop.close()


class FoxgloveSink(NullSink):
    """The pipeline sink behind ``--foxglove``: starts the WebSocket server on creation."""

    sink_name = "foxglove"

    def __init__(self, config: SinewatchConfig) -> None:
        self.section = config.foxglove
        port = self.section.port if self.section.port is not None else 0
        self.counters = FoxgloveCounters()
        self._context = foxglove.Context()  # this daemon's own channels, not the SDK's global ones
        self._topics: dict[str, foxglove.Channel] = {}
        self._samples_by_key: dict[str, foxglove.Channel] = {}
        self._queue: queue.Queue[tuple[str, bytes, str, int] | None] = queue.Queue(self.section.queue)
        self.subscriptions = _Subscriptions(self.counters)
        self._tokens = self.section.input_rate_hz  # a token bucket: input_rate_hz, one second's burst
        self._refilled = time.monotonic()
        relayed = self.section.websocket_v1
        self.server = foxglove.start_server(
            name=f"sinewatch {config.daemon_id}",
            host="127.0.0.1" if relayed else self.section.host,
            port=0 if relayed else port,
            context=self._context,
            message_backlog_size=self.section.backlog,
            server_listener=self.subscriptions,
        )
        self.relay: SubprotocolRelay | None = None
        if relayed:
            try:
                self.relay = SubprotocolRelay(self.section.host, port, self.server.port)
            except OSError:
                self.server.stop()
                raise
        self.port = self.relay.port if self.relay is not None else self.server.port
        self._log_channel = LogChannel(LOG_TOPIC, context=self._context)
        self._handler = FoxgloveLogHandler(self._log_channel, self.counters)
        logging.getLogger("sinewatch").addHandler(self._handler)
        self._worker: threading.Thread | None = None
        if self.section.inputs:
            self._worker = threading.Thread(target=self._summaries, name="sinewatch-foxglove", daemon=True)
            self._worker.start()
        log.info(
            "foxglove: ws://%s:%d (Foxglove: Open connection; subprotocols %s)",
            self.section.host,
            self.port,
            f"{SDK_SUBPROTOCOL} and {LEGACY_SUBPROTOCOL}" if relayed else SDK_SUBPROTOCOL,
        )

    # ---- topics ----------------------------------------------------------------------------
    def _topic(self, topic: str, schema_name: str, schema: Callable[[], dict[str, Any]]) -> foxglove.Channel | None:
        ch = self._topics.get(topic)
        if ch is None:
            if len(self._topics) >= self.section.max_topics:
                self.counters.topics_refused += 1
                return None
            data = json.dumps(schema()).encode()
            fox_schema = foxglove.Schema(name=schema_name, encoding="jsonschema", data=data)
            ch = foxglove.Channel(topic, schema=fox_schema, message_encoding="json", context=self._context)
            self._topics[topic] = ch
        return ch

    def _publish(self, key: str, name: str, payload: bytes, log_time_ns: int) -> None:
        model = MESSAGE_MODELS[name] if name in MESSAGE_MODELS else PQ_MESSAGE_MODELS[name]
        ch = self._topic(key, f"sinewatch.{name}", model.model_json_schema)
        if ch is not None:
            ch.log(payload, log_time=log_time_ns)

    # ---- the sink --------------------------------------------------------------------------
    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._publish(key, "Estimate", payload, log_time_ns)

    def on_error(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._publish(key, "ErrorReport", payload, log_time_ns)

    def on_status(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self._publish(key, "Status", payload, log_time_ns)

    def on_output(self, kind: str, key: str, payload: bytes, log_time_ns: int) -> None:
        self._publish(key, kind, payload, log_time_ns)

    def on_input(self, key: str, payload: bytes, encoding: str, log_time_ns: int) -> None:
        """On the event loop: at most a dict lookup, a subscription check, a token and a
        bounded put."""
        if self._worker is None:
            return
        ch = self._samples_by_key.get(key)
        if ch is not None and not ch.has_sinks():
            return
        rate = self.section.input_rate_hz
        now = time.monotonic()
        self._tokens = min(rate, self._tokens + (now - self._refilled) * rate)
        self._refilled = now
        if self._tokens < 1.0:
            self.counters.inputs_over_rate += 1
            return
        self._tokens -= 1.0
        try:
            self._queue.put_nowait((key, payload, encoding, log_time_ns))
        except queue.Full:
            self.counters.inputs_dropped += 1

    def _summaries(self) -> None:
        """The worker: decode, summarise, publish; a key's topic is made on its first
        readable block (so that a client can subscribe to it)."""
        while (item := self._queue.get()) is not None:
            key, payload, encoding, log_time_ns = item
            try:
                msgs = summaries(payload, encoding, self.section.input_points)
            except InputError:
                self.counters.inputs_unreadable += 1
                continue
            except Exception:  # a bug here must not end the worker: close() waits for it
                self.counters.inputs_unreadable += 1
                if self.counters.inputs_unreadable <= 5:
                    log.exception("foxglove: input summary of %s failed", key)
                continue
            for msg in msgs:
                self._publish_summary(key if len(msgs) == 1 else f"{key}\n{msg['channel']}", msg, log_time_ns)

    def _publish_summary(self, slot: str, msg: dict[str, Any], log_time_ns: int) -> None:
        """One channel's summary on its topic (``slot``: the input key, and for a frame's
        channel the channel's name after it)."""
        ch = self._samples_by_key.get(slot)
        if ch is None:
            ch = self._topic(f"{SAMPLES_PREFIX}/{msg['channel']}", SUMMARY_SCHEMA_NAME, SUMMARY_SCHEMA.copy)
            if ch is None:
                return
            self._samples_by_key[slot] = ch
        if ch.has_sinks():
            ch.log(json.dumps(msg, separators=(",", ":")).encode(), log_time=log_time_ns)
            self.counters.input_summaries += 1

    def close(self) -> None:
        logging.getLogger("sinewatch").removeHandler(self._handler)
        if self._worker is not None:
            self._queue.put(None)  # after everything queued: the last summaries still go out
            self._worker.join()
            self._worker = None
        if self.relay is not None:
            self.relay.close()
            self.relay = None
        self.server.stop()


__all__ = [
    "LEGACY_SUBPROTOCOL",
    "LOG_TOPIC",
    "SAMPLES_PREFIX",
    "SDK_SUBPROTOCOL",
    "FoxgloveLogHandler",
    "FoxgloveSink",
    "SubprotocolRelay",
    "offered_subprotocols",
    "summaries",
    "summarise",
]
