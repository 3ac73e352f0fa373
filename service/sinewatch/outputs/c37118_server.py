"""sinewatch as a PMU: an IEEE C37.118.2-2011 server, a pipeline sink (``[c37118]``, off by default).

Each configured station (one or more channels under one ID code) is one PMU data stream: a
phasor data concentrator connects over TCP (or sends command frames over UDP), sends command
frames (turn data on/off, send CFG-1/CFG-2/CFG-3, send the header) and receives data frames at
the station's reporting rate. Frames are built by :mod:`sinewatch.schemas.c37118`.

Data path. The pipeline hands every Estimate to :meth:`C37118Server.on_estimate` on the event
loop. A station collects its channels' estimates by timestamp (the ``pmu`` estimator reports
on the grid k/Fs); a frame is built once every channel has reported that time, or once some
channel is ``max_skew_s`` of data time past it (the missing phasors are then NaN and STAT says
absent data). The frame is written to each subscribed client's connection without waiting
(the transport buffers it) while that client's buffer is below ``client_buffer_bytes``; past
that it goes into the client's bounded queue (``client_queue_frames``), which the client's own
task drains as its socket drains. A client that stops reading fills its socket buffer, its
write buffer and its queue, and then its frames are dropped and counted (``Status.c37118``):
the daemon never waits for a client. UDP sends never wait either (a datagram the OS cannot take
is lost, as UDP is).

STAT (Table 7), per station: data error 00 when every channel's estimate is there, valid and
without a gap; 01 (PMU error, no information about data) when an estimate follows a sequence
gap; 11 (PMU error, do not use) when an estimate says ``valid: false``; 10 (absent data
inserted) when a channel's estimate is missing. Sync (bit 13), unlocked time and the time
quality follow ``time_synchronised`` (sinewatch cannot know whether its gateways' clocks are
UTC-traceable: the operator says so). Data modified (bit 9) is 0: the values are this PMU's
own estimates. Sorting (bit 12) is 0: frames go out in time order.

Malformed command frames (bad SYNC, bad CRC, truncated, an unknown ID code or command) are
rejected: a log line (the first five per reason, then at the 10th, 100th, ...) and a count per
reason; the connection stays open.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import socket
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from sinewatch.clients.subscriber import Fence
from sinewatch.core.pipeline import NullSink
from sinewatch.schemas import c37118 as wire
from sinewatch.schemas.config import C37118Section, C37118Station
from sinewatch.schemas.errors import ConfigError
from sinewatch.schemas.messages import C37118ClientStatus, C37118Status

log = logging.getLogger("sinewatch.c37118")

TIME_QUALITY_LOCKED = 0x0  # Table 4: clock locked to a UTC-traceable source
TIME_QUALITY_FAULT = 0xF  # Table 4: fault, clock failure, time not reliable
PMU_TIME_QUALITY_UNKNOWN = 0b111  # Table 7: estimated maximum time error > 10 ms or unknown
UNLOCKED_OVER_1000_S = 0b11


@dataclass(frozen=True)
class TimeBits:
    """What a data frame says of its time: STAT bit 13 (``in_sync``), STAT bits 8-6 and 5-4,
    and FRACSEC's time quality code (bits 27-24)."""

    in_sync: bool
    pmu_time_quality: int
    unlocked: int
    code: int

    def worse(self, other: TimeBits) -> TimeBits:
        """The frame's bits from two channels': each field at its worse value."""
        return TimeBits(
            self.in_sync and other.in_sync,
            max(self.pmu_time_quality, other.pmu_time_quality),
            max(self.unlocked, other.unlocked),
            max(self.code, other.code),
        )


def unlocked_code(seconds: float) -> int:
    """STAT bits 5-4 (C37.118.2-2011 Table 6): 00 locked or unlocked < 10 s, 01 10 s to
    < 100 s, 10 100 s to 1000 s, 11 over 1000 s."""
    if seconds < 10:
        return 0b00
    if seconds < 100:
        return 0b01
    return 0b10 if seconds <= 1000 else 0b11


def time_quality_bits(tq: dict[str, Any] | None, cfg: C37118Station, unlocked_s: float = 0.0) -> TimeBits:
    """The time bits of one channel's estimate from its ``time_quality`` (Estimate format 5).

    * not stated (null, or an estimate of an earlier format): the operator's
      ``time_synchronised`` declaration: in sync, ``pmu_time_quality``, locked, code 0; or not
      in sync, unknown (Table 7: 111), unlocked over 1000 s, code 0xF (Table 4: clock failure,
      time not reliable).
    * ``global`` (smpSynch 2: locked to a UTC-traceable grandmaster): in sync, code 0 (Table 4:
      locked to a UTC-traceable source); bits 8-6 the station's ``pmu_time_quality``, for
      ``smpSynch`` says that the clock is locked, not how close (IEC 61869-9 leaves the
      accuracy to the synchronisation's class).
    * ``holdover`` (the reference was lost during the stream): not in sync, unknown, the
      unlocked time since the loss (``unlocked_s``, Table 6's ranges), code 0xF.
    * ``local`` or ``none`` (never UTC-traceable in this stream): not in sync, unknown,
      unlocked over 1000 s, code 0xF; a local area clock is no UTC-traceable source."""
    if tq is None:
        if cfg.time_synchronised:
            return TimeBits(True, cfg.pmu_time_quality, 0, TIME_QUALITY_LOCKED)
        return TimeBits(False, PMU_TIME_QUALITY_UNKNOWN, UNLOCKED_OVER_1000_S, TIME_QUALITY_FAULT)
    if tq.get("holdover"):
        return TimeBits(False, PMU_TIME_QUALITY_UNKNOWN, unlocked_code(unlocked_s), TIME_QUALITY_FAULT)
    if tq.get("sync") == "global":
        return TimeBits(True, cfg.pmu_time_quality, 0, TIME_QUALITY_LOCKED)
    return TimeBits(False, PMU_TIME_QUALITY_UNKNOWN, UNLOCKED_OVER_1000_S, TIME_QUALITY_FAULT)


def synchrophasor(est: dict[str, Any], nominal_hz: int) -> tuple[float, float] | None:
    """(RMS magnitude, angle rad referred to the nominal cosine) of an Estimate, or None.

    The ``pmu`` estimator gives both in ``extras``; for any other estimator they follow from
    its amplitude A and instantaneous sine phase psi at t: x = A sin(psi) = A cos(psi - pi/2),
    so the synchrophasor is (A / sqrt 2, psi - pi/2 - 2 pi f0 t), C37.118.1-2011 eq. (1)-(2),
    with 2 pi f0 t reduced modulo 2 pi in integers (t in ns) so it stays exact."""
    extras = est["diagnostics"].get("extras") or {}
    mag, ang = extras.get("synchrophasor_magnitude"), extras.get("synchrophasor_angle_rad")
    if isinstance(mag, float | int) and isinstance(ang, float | int):
        return float(mag), float(ang)
    amp, psi = est["amplitude"][0], est["phase_rad"][0]
    if amp is None or psi is None:
        return None
    cycles_ns = (nominal_hz * est["timestamp_ns"]) % 1_000_000_000
    angle = psi - math.pi / 2 - 2 * math.pi * cycles_ns / 1e9
    return amp / math.sqrt(2), math.remainder(angle, 2 * math.pi)


class Station:
    """One PMU data stream: its configuration frames and the frames built from its channels."""

    def __init__(self, cfg: C37118Station, time_base: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self._clock = clock
        # the last frame built from estimates: its time and when (clock), and how many frames
        # of invalid data have been sent since (keep_rate)
        self._real_t: int | None = None
        self._real_at = 0.0
        self._filled = 0
        self.invalid = 0
        self.id_code = cfg.id_code
        self.time_base = time_base
        self._index = {ch: i for i, ch in enumerate(cfg.channels)}
        self._skew_ns = round(cfg.max_skew_s * 1e9)
        self._pending: dict[int, dict[int, dict[str, Any]]] = {}  # timestamp -> channel index -> estimate
        self._latest: list[int | None] = [None] * len(cfg.channels)
        self._last_sent: int | None = None
        self.built = 0
        self.incomplete = 0
        self.late = 0
        self.time_quality = TIME_QUALITY_LOCKED if cfg.time_synchronised else TIME_QUALITY_FAULT
        # the last time quality an estimate stated (frames without estimates keep it), and the
        # data time of the first frame in holdover since the last one that was not (unlocked time)
        self._stated: list[dict[str, Any]] = []
        self._holdover_since: int | None = None
        names = cfg.phasor_names or [ch.rsplit("/", 1)[-1] for ch in cfg.channels]
        current = cfg.phasor_type == "current"
        self.pmu = wire.PmuConfig(
            station=cfg.name,
            id_code=cfg.id_code,
            format=wire.DataFormat(polar=cfg.phasor_format == "polar"),
            phasor_names=names,
            phunit=[(1 << 24 if current else 0)] * len(names),  # float data: the scale is not used
            nominal_frequency_hz=cfg.nominal_frequency_hz,
            phscale=[wire.PhasorScale(type_code=0b1000 if current else 0)] * len(names),
            service_class="M",
        )
        self.cfg2 = wire.ConfigFrame(wire.FrameType.CFG2, cfg.id_code, time_base, [self.pmu], cfg.data_rate)

    def channel_of(self, channel: str) -> int | None:
        return self._index.get(channel)

    def config_frame(self, frame_type: wire.FrameType, t_ns: int) -> bytes:
        soc, frac = wire.soc_fraction(t_ns, self.time_base)
        cfg = wire.ConfigFrame(
            frame_type,
            self.id_code,
            self.time_base,
            [self.pmu],
            self.cfg.data_rate,
            soc,
            wire.fracsec_word(frac, self.time_quality),
        )
        return wire.encode_config(cfg)

    def header_frame(self, t_ns: int) -> bytes:
        soc, frac = wire.soc_fraction(t_ns, self.time_base)
        text = (
            f"sinewatch PMU {self.cfg.name}: channels {', '.join(self.cfg.channels)}; "
            f"{self.cfg.nominal_frequency_hz} Hz nominal, {self.cfg.data_rate} frames/s; "
            f"phasors RMS, angle referred to the nominal cosine (C37.118.1); FREQ and DFREQ of "
            f"{self.cfg.channels[0]}; clock {'UTC-traceable' if self.cfg.time_synchronised else 'not UTC-traceable'}"
        )
        return wire.encode_header(self.id_code, text, soc, wire.fracsec_word(frac, self.time_quality))

    def add(self, index: int, est: dict[str, Any]) -> list[bytes]:
        """Take one channel's estimate; return the data frames now complete, oldest first."""
        ts = int(est["timestamp_ns"])
        if self._last_sent is not None and ts <= self._last_sent:
            self.late += 1
            return []
        self._pending.setdefault(ts, {})[index] = est
        latest = self._latest[index]
        self._latest[index] = ts if latest is None else max(latest, ts)
        newest = max(t for t in self._latest if t is not None)
        out = []
        for t in sorted(self._pending):
            got = self._pending[t]
            if len(got) < len(self._index) and newest - t <= self._skew_ns:
                break
            del self._pending[t]
            out.append(self._data_frame(t, got))
            self._last_sent = t
        if out:
            self._real_t, self._real_at, self._filled = self._last_sent, self._clock(), 0
        return out

    def keep_rate(self) -> list[bytes]:
        """The frames due while no estimate comes: a PMU keeps its reporting rate when its
        inputs stop, with the data flagged invalid (STAT data error 11). Frame k after the
        last one built from estimates is due k reporting periods plus ``max_skew_s`` after
        it (the wait a late channel gets) and carries its time on the same grid."""
        if self._real_t is None:
            return []
        rate = self.cfg.data_rate
        due = math.floor((self._clock() - self._real_at - self.cfg.max_skew_s) * rate)
        out = []
        while self._filled < due:
            self._filled += 1
            t = self._real_t + round(self._filled * 1e9 / rate)
            if self._last_sent is not None and t <= self._last_sent:
                continue
            for older in sorted(p for p in self._pending if p < t):  # partial frames first, in time order
                out.append(self._data_frame(older, self._pending.pop(older)))
            self._pending.pop(t, None)
            out.append(self._data_frame(t, {}, stopped=True))
            self._last_sent = t
            self.invalid += 1
        return out

    def _data_frame(self, t_ns: int, got: dict[int, dict[str, Any]], stopped: bool = False) -> bytes:
        nan = math.nan
        phasors: list[tuple[float, float]] = []
        error = wire.DataError.GOOD
        missing = False
        for i in range(len(self._index)):
            est = got.get(i)
            ph = None if est is None else synchrophasor(est, self.cfg.nominal_frequency_hz)
            if est is None or ph is None:
                missing = True
                phasors.append((nan, nan))
                continue
            d = est["diagnostics"]
            if not d.get("valid", True):
                error = wire.DataError.PMU_ERROR
            elif d.get("gap") and error is wire.DataError.GOOD:
                error = wire.DataError.PMU_ERROR_NO_INFO
            if self.pmu.format.polar:
                phasors.append(ph)
            else:
                phasors.append((ph[0] * math.cos(ph[1]), ph[0] * math.sin(ph[1])))
        if stopped:  # no input at all: the values are not to be used
            error = wire.DataError.PMU_ERROR
        elif missing:
            error = wire.DataError.TEST_OR_ABSENT
            self.incomplete += 1
        first = got.get(0)
        freq = dfreq = nan
        if first is not None:
            f = first["frequency_hz"][0]
            r = first.get("rocof_hz_per_s")
            freq = nan if f is None else f
            dfreq = nan if not r or r[0] is None else r[0]
        bits = self._time_bits(t_ns, got)
        stat = wire.stat_word(
            error, in_sync=bits.in_sync, pmu_time_quality=bits.pmu_time_quality, unlocked=bits.unlocked
        )
        soc, frac = wire.soc_fraction(t_ns, self.time_base)
        self.built += 1
        self.time_quality = bits.code  # the configuration and header frames say it too
        fracsec = wire.fracsec_word(frac, bits.code)
        return wire.encode_data(self.cfg2, soc, fracsec, [wire.PmuData(stat, phasors, freq, dfreq)])

    def _time_bits(self, t_ns: int, got: dict[int, dict[str, Any]]) -> TimeBits:
        """The frame's time bits: the worst of its channels' stated time qualities (the last
        frame's for a frame without estimates), else the configured declaration."""
        stated = [tq for est in got.values() if (tq := est.get("time_quality")) is not None]
        if got:
            self._stated = stated
        else:
            stated = self._stated
        if any(tq.get("holdover") for tq in stated):
            if self._holdover_since is None:
                self._holdover_since = t_ns
        else:
            self._holdover_since = None
        unlocked_s = 0.0 if self._holdover_since is None else (t_ns - self._holdover_since) / 1e9
        if not stated:
            return time_quality_bits(None, self.cfg)
        bits = time_quality_bits(stated[0], self.cfg, unlocked_s)
        for tq in stated[1:]:
            bits = bits.worse(time_quality_bits(tq, self.cfg, unlocked_s))
        return bits


@dataclass
class Client:
    peer: str
    transport: str  # "tcp" or "udp"
    queue: asyncio.Queue[bytes] | None  # TCP only; UDP sends at once
    streaming: set[int] = field(default_factory=set)
    sent: int = 0
    dropped: int = 0
    addr: tuple[str, int] | None = None  # UDP
    writer: asyncio.StreamWriter | None = None  # TCP

    def status(self) -> C37118ClientStatus:
        return C37118ClientStatus(
            peer=self.peer,
            transport="udp" if self.transport == "udp" else "tcp",
            streaming=sorted(self.streaming),
            frames_sent=self.sent,
            frames_dropped=self.dropped,
            frames_queued=self.queue.qsize() if self.queue is not None else 0,
        )


class _Udp(asyncio.DatagramProtocol):
    def __init__(self, server: C37118Server) -> None:
        self.server = server

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.server.udp_command(data, addr)


class C37118Server(NullSink):
    """The pipeline sink and the sockets: TCP and UDP on one port."""

    sink_name = "c37118"

    def __init__(self, config: C37118Section, clock_ns: Any = None) -> None:
        self.config = config
        self._clock_ns = clock_ns or time.time_ns
        self.stations = {s.id_code: Station(s, config.time_base) for s in config.stations}
        self.fence = Fence()  # the newest election term per shard: frames only from the shard's owner
        self._by_channel: dict[str, list[tuple[Station, int]]] = {}
        for st in self.stations.values():
            for ch in st.cfg.channels:
                idx = st.channel_of(ch)
                assert idx is not None
                self._by_channel.setdefault(ch, []).append((st, idx))
        self.clients: list[Client] = []
        self._udp_clients: dict[tuple[str, int], Client] = {}
        self._spontaneous: list[tuple[str, int]] = [
            (d.rpartition(":")[0], int(d.rpartition(":")[2])) for d in config.udp_destinations
        ]
        self.dropped_total = 0
        self.commands = 0
        self.rejected: Counter[str] = Counter()
        self.port = config.port
        self._tcp: asyncio.Server | None = None
        self._udp: asyncio.DatagramTransport | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()

    # ---- lifecycle ------------------------------------------------------------------------------
    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        where = f"{self.config.host}:{self.config.port}"
        try:
            self._tcp = await asyncio.start_server(self._serve_tcp, self.config.host, self.config.port)
            self.port = int(self._tcp.sockets[0].getsockname()[1])
            where = f"{self.config.host}:{self.port}"
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _Udp(self), local_addr=(self.config.host, self.port)
            )
        except OSError as exc:
            await self.stop()
            raise ConfigError(f"[c37118]: expected to listen on {where} (TCP and UDP), got: {exc.strerror}") from None
        self._udp = transport
        ticker = asyncio.create_task(self._keep_rate(), name="c37118-keep-rate")
        self._tasks.add(ticker)
        log.info(
            "C37.118.2 server on %s:%d (TCP and UDP): stations %s",
            self.config.host,
            self.port,
            ", ".join(
                f"{s.cfg.name} (ID {s.id_code}, {len(s.cfg.channels)} channel(s))" for s in self.stations.values()
            ),
        )

    async def stop(self) -> None:
        if self._tcp is not None:
            self._tcp.close()
        for w in list(self._writers):
            w.close()
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._tcp is not None:
            await self._tcp.wait_closed()
        if self._udp is not None:
            self._udp.close()

    # ---- the sink -------------------------------------------------------------------------------
    def on_estimate(self, key: str, payload: bytes, log_time_ns: int) -> None:
        targets = self._by_channel.get(_channel_of(payload), ())
        if not targets:
            return
        est = json.loads(payload)
        if not self.fence.accept(est):  # an older term than one already served: a deposed owner's
            return
        for station, idx in targets:
            for frame in station.add(idx, est):
                self._broadcast(station.id_code, frame)

    async def _keep_rate(self) -> None:
        """Every reporting period, the frames of invalid data due for stations whose inputs
        stopped (:meth:`Station.keep_rate`)."""
        period = 1.0 / max(s.cfg.data_rate for s in self.stations.values()) if self.stations else 1.0
        while True:
            await asyncio.sleep(period)
            for station in self.stations.values():
                for frame in station.keep_rate():
                    self._broadcast(station.id_code, frame)

    def _broadcast(self, id_code: int, frame: bytes) -> None:
        for c in self.clients:
            if id_code not in c.streaming:
                continue
            if c.queue is None:
                self._sendto(c, frame)
            elif (
                c.writer is not None
                and c.queue.empty()
                and c.writer.transport.get_write_buffer_size() < self.config.client_buffer_bytes
            ):
                c.writer.write(frame)  # never waits: the transport buffers it, the kernel takes it
                c.sent += 1
            else:
                try:
                    c.queue.put_nowait(frame)  # the client's sender writes it once the buffer drains
                except asyncio.QueueFull:
                    c.dropped += 1
                    self.dropped_total += 1
        for addr in self._spontaneous:
            if self._udp is not None:
                self._udp.sendto(frame, addr)

    def _sendto(self, c: Client, frame: bytes) -> None:
        if self._udp is not None and c.addr is not None:
            self._udp.sendto(frame, c.addr)
            c.sent += 1

    # ---- TCP clients ----------------------------------------------------------------------------
    async def _serve_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peername = writer.get_extra_info("peername")
        peer = f"{peername[0]}:{peername[1]}" if peername else "?"
        if len(self.clients) >= self.config.max_clients:
            self._reject("client_limit", peer, f"expected at most {self.config.max_clients} clients: connection closed")
            writer.close()
            return
        client = Client(peer, "tcp", asyncio.Queue(self.config.client_queue_frames), writer=writer)
        limit = self.config.client_buffer_bytes
        sock = writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, limit)
        writer.transport.set_write_buffer_limits(high=limit)
        self.clients.append(client)
        self._writers.add(writer)
        sender = asyncio.create_task(self._send_loop(client, writer), name=f"c37118-send-{peer}")
        self._tasks.add(sender)
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        log.info("C37.118.2 client %s connected", peer)
        splitter = wire.FrameSplitter()
        idle_s = self.config.idle_timeout_s
        try:
            while True:
                if client.streaming:  # a PDC with data on need not say anything more
                    data = await reader.read(4096)
                else:
                    try:
                        data = await asyncio.wait_for(reader.read(4096), idle_s)
                    except TimeoutError:
                        self._reject(
                            "idle", peer, f"expected a command within {idle_s:g} s, got none: connection closed"
                        )
                        break
                if not data:
                    break
                for raw in splitter.feed(data):
                    for reply in self._command(raw, client):
                        self._reply(client, writer, reply)
                self._count_skipped(splitter, peer)
            if splitter.pending:
                self._reject("truncated", peer, f"connection closed {splitter.pending} byte(s) into a frame")
        except (ConnectionError, OSError) as exc:
            log.info("C37.118.2 client %s: %s", peer, exc)
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender
            self._tasks.discard(sender)
            if task is not None:
                self._tasks.discard(task)
            self.clients.remove(client)
            self._writers.discard(writer)
            writer.close()
            log.info("C37.118.2 client %s disconnected (%d sent, %d dropped)", peer, client.sent, client.dropped)

    def _reply(self, client: Client, writer: asyncio.StreamWriter, frame: bytes) -> None:
        """A command's answer (configuration, header): written at once, ahead of queued data."""
        if writer.is_closing():
            return
        if writer.transport.get_write_buffer_size() > 4 * self.config.client_buffer_bytes:
            client.dropped += 1  # a client that sends commands but never reads the answers
            self.dropped_total += 1
            return
        writer.write(frame)
        client.sent += 1

    @staticmethod
    async def _send_loop(client: Client, writer: asyncio.StreamWriter) -> None:
        """Writes the frames that were queued while the client's buffer was full. It never holds
        a frame across an await (drain, then get, then write at once), so a frame written
        directly by :meth:`_broadcast` (only when the queue is empty) never overtakes one queued."""
        assert client.queue is not None
        try:
            while True:
                await writer.drain()
                frame = await client.queue.get()
                writer.write(frame)
                client.sent += 1
        except (ConnectionError, OSError):
            return

    def _count_skipped(self, splitter: wire.FrameSplitter, peer: str) -> None:
        if splitter.skipped:
            self._reject("sync", peer, f"{splitter.skipped} byte(s) that do not start a frame (SYNC 0xAA) skipped")
            splitter.skipped = 0

    # ---- UDP clients ----------------------------------------------------------------------------
    def udp_command(self, data: bytes, addr: tuple[str, int]) -> None:
        client = self._udp_clients.get(addr)
        if client is None:
            client = Client(f"{addr[0]}:{addr[1]}", "udp", None, addr=addr)
        for reply in self._command(bytes(data), client):
            self._sendto(client, reply)
        if client.streaming and addr not in self._udp_clients:
            if len(self.clients) >= self.config.max_clients:
                client.streaming.clear()
                self._reject("client_limit", client.peer, f"expected at most {self.config.max_clients} clients")
                return
            self._udp_clients[addr] = client
            self.clients.append(client)
        elif not client.streaming and addr in self._udp_clients:
            del self._udp_clients[addr]
            self.clients.remove(client)

    # ---- commands -------------------------------------------------------------------------------
    def _command(self, raw: bytes, client: Client) -> list[bytes]:
        """Act on one command frame; return the frames to answer with."""
        try:
            frame = wire.decode_frame(raw)
            cmd, _ = wire.decode_command(frame)
        except wire.FrameError as exc:
            self._reject(exc.kind, client.peer, str(exc))
            return []
        station = self.stations.get(frame.id_code)
        if station is None:
            self._reject(
                "id_code",
                client.peer,
                f"IDCODE: expected one of {sorted(self.stations)}, got {frame.id_code}",
            )
            return []
        now = self._clock_ns()
        replies: list[bytes] = []
        if cmd == wire.Command.DATA_ON:
            client.streaming.add(station.id_code)
        elif cmd == wire.Command.DATA_OFF:
            client.streaming.discard(station.id_code)
        elif cmd == wire.Command.SEND_HDR:
            replies.append(station.header_frame(now))
        elif cmd in (wire.Command.SEND_CFG1, wire.Command.SEND_CFG2, wire.Command.SEND_CFG3):
            kind = {1: wire.FrameType.CFG1, 2: wire.FrameType.CFG2, 3: wire.FrameType.CFG3}[
                cmd - wire.Command.SEND_CFG1 + 1
            ]
            replies.append(station.config_frame(kind, now))
        elif cmd == wire.Command.EXTENDED:
            pass  # user information: nothing to do
        else:
            self._reject("command", client.peer, f"CMD: expected 1-6 or 8 (Table 15), got 0x{cmd:04X}")
            return []
        self.commands += 1
        log.debug("C37.118.2 client %s: command %d for ID %d", client.peer, cmd, station.id_code)
        return replies

    def _reject(self, reason: str, peer: str, message: str) -> None:
        self.rejected[reason] += 1
        n = self.rejected[reason]
        if n <= 5 or math.log10(n).is_integer():
            log.warning(
                "C37.118.2 command frame from %s rejected (%s): %s%s",
                peer,
                reason,
                message,
                f" [{n} so far; further ones logged at powers of ten]" if n >= 5 else "",
            )

    # ---- status ---------------------------------------------------------------------------------
    def status(self) -> C37118Status:
        return C37118Status(
            port=self.port,
            clients=[c.status() for c in self.clients],
            frames_built=sum(s.built for s in self.stations.values()),
            frames_incomplete=sum(s.incomplete for s in self.stations.values()),
            frames_dropped=self.dropped_total,
            frames_late=sum(s.late for s in self.stations.values()),
            commands=self.commands,
            commands_rejected=sum(self.rejected.values()),
            rejected_by_reason=dict(sorted(self.rejected.items())),
        )


def _channel_of(payload: bytes) -> str:
    """The channel of an Estimate payload without parsing all of it (most are not a station's)."""
    i = payload.find(b'"channel":"')
    if i < 0:
        return ""
    j = payload.find(b'"', i + 11)
    return payload[i + 11 : j].decode("utf-8", "replace")


__all__ = ["C37118Server", "Station", "TimeBits", "synchrophasor", "time_quality_bits", "unlocked_code"]
