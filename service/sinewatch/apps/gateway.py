"""IEC 61850-9-2 sampled values in, multi-channel SampleFrames out (``sinewatch gateway sv``).

A merging unit publishes one ASDU per sampling instant: in the 9-2LE profile (UCA
International Users Group, "Implementation guideline for digital interface to instrument
transformers using IEC 61850-9-2", 2004) eight INT32 values, each followed by a 32-bit
quality word, in the order IA IB IC IN VA VB VC VN; currents count 1 mA and voltages 10 mV;
``smpCnt`` counts the samples of the current second and wraps at the sampling rate
(4000/s at 50 Hz, 4800/s at 60 Hz: 80 samples a cycle). The Ethernet/BER decoding is the
``open61850`` library's (:mod:`open61850.sv`, :mod:`open61850.pcap`); this module turns the
decoded ASDUs of each stream (one per svID) into frames of ``n`` consecutive samples:

* **Time.** Sample ``smpCnt`` of UTC second ``s`` was taken at ``s + smpCnt / rate``
  (the merging-unit convention). With ``smpSynch = 2`` (global: the merging unit is locked
  to a grandmaster) the second is the one the sample's arrival falls in (arrival minus
  ``smpCnt / rate``, rounded), so frames are aligned to the UTC second. Otherwise (none or
  local) nothing ties the counter to UTC: the stretch is timed from the gateway's clock at
  its first sample (the capture's timestamp for a pcap file) and counted as unsynchronised.
* **Gaps.** Consecutive samples advance ``smpCnt`` by one (``rate - 1`` -> 0 is the wrap,
  not a gap); whole seconds missing are told from the arrival times. A lost sample, a
  repeated or backwards counter (the repeat is dropped) and a change of ``smpSynch`` (the
  time base jumps) each end the frame being filled and make the next frame's ``seq`` skip,
  so the daemon flags the next estimate of every channel ``gap = true`` with
  ``gap_blocks = ceil(lost / n)`` (1 for a repeat or a synchronisation change). The exact
  counts are in :class:`StreamStats`.
* **Quality.** A sample whose quality word's validity (bits 0-1) is not good (invalid,
  reserved or questionable) is never a value: it is NaN in its channel's column, so the
  daemon refuses that channel's block of the frame (a ``non_finite`` error, counted) and
  flags the channel's next block as a gap of one; the other channels go on.
* **Time quality.** Every frame carries its stream's time quality (SampleFrame format
  version 2, :class:`sinewatch.schemas.messages.TimeQuality`), taken from ``smpSynch``
  (IEC 61850-9-2 Ed. 2.1 and IEC 61869-9: 0 not synchronised, 1 a local area clock, 2 a
  global area clock, 5-254 a local clock identified by that number; 3, 4 and 255 reserved,
  taken as not synchronised). A frame holds one time quality: any change ends the frame, as
  above. ``holdover`` is set when the synchronisation drops during the stream (global to
  local or none, local to none: the merging unit's clock runs free since) and cleared when it
  rises again. The daemon passes it to every Estimate of the frame's channels and to the
  C37.118.2 STAT word; each change is logged.

The counts and each stream's time quality also go on a status key,
``sinewatch/gateway/sv/<svID>``, once a second and at the end.
"""

from __future__ import annotations

import math
import re
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from sinewatch.schemas.codec import SYNC_NAMES, TQ_HOLDOVER, TQ_NOT_STATED, TQ_SYNC_MASK, time_quality_byte
from sinewatch.schemas.errors import ConfigError
from sinewatch.schemas.frame import Frame

DEFAULT_CHANNELS = ("IA", "IB", "IC", "IN", "VA", "VB", "VC", "VN")
# 9-2LE: currents in 1 mA, voltages in 10 mV per count
LE_SCALES = (0.001, 0.001, 0.001, 0.001, 0.01, 0.01, 0.01, 0.01)
SMP_SYNCH_NONE, SMP_SYNCH_LOCAL, SMP_SYNCH_GLOBAL = 0, 1, 2
ETHERTYPE_SV = 0x88BA
_VALIDITY_MASK = 0x3  # 9-2LE quality bits 0-1: 00 good, 01 invalid, 10 reserved, 11 questionable
_NAME_BAD = re.compile(r"[^A-Za-z0-9_.-]")


class GatewayError(ConfigError):
    """A gateway option that cannot be used (says what was expected)."""


def sync_code(smp_synch: int) -> int:
    """The sync code (0 none, 1 local, 2 global) of an ``smpSynch`` value: IEC 61850-9-2
    Ed. 2.1 gives 0 not synchronised, 1 local area clock, 2 global area clock, 5-254 a local
    clock identified by its number; 3, 4 and 255 are reserved and taken as not synchronised."""
    if smp_synch == SMP_SYNCH_GLOBAL:
        return SMP_SYNCH_GLOBAL
    if smp_synch == SMP_SYNCH_LOCAL or 5 <= smp_synch <= 254:
        return SMP_SYNCH_LOCAL
    return SMP_SYNCH_NONE


def describe_time_quality(byte: int) -> dict[str, Any] | None:
    """A time-quality byte as the status key and the summary show it (the Estimate's form)."""
    if byte == TQ_NOT_STATED:
        return None
    return {"sync": SYNC_NAMES[byte & TQ_SYNC_MASK], "holdover": bool(byte & TQ_HOLDOVER)}


def channel_prefix(sv_id: str) -> str:
    """The svID as one chunk of a channel name (characters outside [A-Za-z0-9_.-] -> '_')."""
    return _NAME_BAD.sub("_", sv_id) or "_"


@dataclass
class StreamStats:
    """What happened to one stream, in samples (ASDUs) unless named otherwise."""

    sv_id: str
    samples: int = 0  # accepted into frames
    frames: int = 0
    lost: int = 0  # samples missing (counter jumped forward)
    lost_events: int = 0
    repeated: int = 0  # repeated or backwards counters, dropped
    bad_quality: int = 0  # channel values sent as NaN
    unsynchronised: int = 0  # samples taken while smpSynch was not global
    synch_changes: int = 0
    rejected: int = 0  # ASDUs that could not be used (sample length, smpCnt out of range)


@dataclass
class StreamSpec:
    """How one svID is published: its channel names (the data set order) and the frame size."""

    sv_id: str
    channels: tuple[str, ...] = ()
    scales: tuple[float, ...] = LE_SCALES

    def names(self) -> tuple[str, ...]:
        base = channel_prefix(self.sv_id)
        return tuple(f"{base}/{c}" for c in (self.channels or DEFAULT_CHANNELS))


class SvStreamDecoder:
    """One stream's ASDUs -> Frames of ``n_samples`` consecutive samples (the module docstring
    says how time, gaps and quality are handled). Pure: no I/O; ``push`` returns the frames
    it completed."""

    def __init__(self, spec: StreamSpec, *, rate: int, n_samples: int) -> None:
        names = spec.names()
        if len(names) != len(spec.scales):
            raise GatewayError(f"channels of {spec.sv_id}: expected {len(spec.scales)} names, got {len(names)}")
        if rate < 1 or n_samples < 1:
            raise GatewayError(f"rate and samples per frame: expected >= 1, got {rate} and {n_samples}")
        self.spec, self.rate, self.n = spec, rate, n_samples
        self.names = names
        self.stats = StreamStats(spec.sv_id)
        self._scales = np.asarray(spec.scales, dtype=np.float64)
        # the raw (value, quality) pairs of the frame being filled, copied as they come and
        # scaled once per frame: one numpy call per frame, not per sample
        self._width = 8 * len(names)
        self._raw = bytearray(n_samples * self._width)
        self._fill = 0
        self._t0_ns = 0
        self._seq = 0
        self._skip = 0  # seq numbers to leave out before the next frame (a gap for the daemon)
        self._last_cnt: int | None = None
        self._last_arrival_ns = 0
        self._synced = False
        self._sync: int | None = None  # the sync code of the current stretch (sync_code)
        self._holdover = False
        # the time base of the current stretch (see _start_stretch) and the samples since
        # (integers: a float of ns since the epoch has a 256-ns step)
        self._base_ns = 0
        self._k = 0

    # ---- per ASDU ------------------------------------------------------------------------
    def push(self, arrival_ns: int, smp_cnt: int, smp_synch: int, sample: bytes) -> list[Frame]:
        n_ch = len(self.names)
        if len(sample) != 8 * n_ch or not 0 <= smp_cnt < self.rate:
            self.stats.rejected += 1
            return []
        code = sync_code(smp_synch)
        synced = code == SMP_SYNCH_GLOBAL
        out: list[Frame] = []
        step = self._step(arrival_ns, smp_cnt)
        if step is not None and step <= 0:
            self.stats.repeated += 1
            self._break(out)
            return out
        if step is not None and step > 1:
            self.stats.lost += step - 1
            self.stats.lost_events += 1
            self._break(out, lost=step - 1)
        if step is None or code != self._sync:
            if step is not None and self._sync is not None:
                self.stats.synch_changes += 1
                self._break(out)  # a frame holds one time quality
                self._holdover = code < self._sync  # a drop: the reference was lost; a rise: regained
            self._sync, self._synced = code, synced
            self._start_stretch(arrival_ns, smp_cnt)
        else:
            self._k += step
        t_ns = self._time_ns(arrival_ns, smp_cnt)
        self._last_cnt, self._last_arrival_ns = smp_cnt, arrival_ns
        if not synced:
            self.stats.unsynchronised += 1
        if self._fill == 0:
            self._t0_ns = t_ns
        at = self._fill * self._width
        self._raw[at : at + self._width] = sample
        self._fill += 1
        self.stats.samples += 1
        if self._fill == self.n:
            out.append(self._emit())
        return out

    @property
    def synchronised(self) -> bool:
        """Whether the last sample said smpSynch = 2 (global)."""
        return self._synced

    @property
    def time_quality(self) -> int:
        """The time-quality byte of the current stretch (0 before the first sample)."""
        if self._sync is None:
            return TQ_NOT_STATED
        return time_quality_byte(self._sync, self._holdover)

    def flush(self) -> list[Frame]:
        """The partly filled frame, if any (at the end of a capture)."""
        return [self._emit()] if self._fill else []

    def _step(self, arrival_ns: int, smp_cnt: int) -> int | None:
        """Samples from the last one to this one (1 = the next; <= 0 a repeat or a step back;
        None for the first). The counter gives it modulo ``rate``; the arrival times give
        the whole seconds the counter cannot show."""
        if self._last_cnt is None:
            return None
        delta = (smp_cnt - self._last_cnt) % self.rate
        elapsed = (arrival_ns - self._last_arrival_ns) * self.rate / 1e9
        return delta + round((elapsed - delta) / self.rate) * self.rate

    def _start_stretch(self, arrival_ns: int, smp_cnt: int) -> None:
        """The time base of a stretch of one synchronisation state: synchronised, the UTC
        second of its first sample (its arrival less its offset in the second, rounded: the
        arrival must be within half a second of the sample); else the arrival itself. From
        there the counter alone times the stretch, so a gateway running behind (a backlog in
        the socket buffer) does not shift it."""
        self._k = 0
        if self._synced:
            offset_ns = round(smp_cnt * 1e9 / self.rate)
            second = (arrival_ns - offset_ns + 500_000_000) // 1_000_000_000
            self._base_ns = second * self.rate + smp_cnt  # in samples since the epoch
        else:
            self._base_ns = arrival_ns

    def _time_ns(self, arrival_ns: int, smp_cnt: int) -> int:
        if not self._synced:
            return self._base_ns + round(self._k * 1e9 / self.rate)
        second, index = divmod(self._base_ns + self._k, self.rate)
        return second * 1_000_000_000 + round(index * 1e9 / self.rate)

    def _break(self, out: list[Frame], lost: int = 0) -> None:
        """End the frame being filled; the next frame's seq skips ceil(lost / n) (at least 1)."""
        if self._fill:
            out.append(self._emit())
        self._skip = max(self._skip, 1, math.ceil(lost / self.n))

    def _emit(self) -> Frame:
        self._seq += self._skip
        self._skip = 0
        raw = np.frombuffer(self._raw, dtype=">i4", count=self._fill * self._width // 4)
        pairs = raw.reshape(self._fill, len(self.names), 2)
        samples = pairs[:, :, 0] * self._scales
        bad = (pairs[:, :, 1] & _VALIDITY_MASK) != 0
        if bad.any():
            samples[bad] = np.nan
            self.stats.bad_quality += int(np.count_nonzero(bad))
        frame = Frame(self.names, self._seq, self._t0_ns, float(self.rate), samples, self.time_quality)
        self._seq += 1
        self._fill = 0
        self.stats.frames += 1
        return frame


# ---- the gateway: filters, streams, a source of Ethernet frames ----------------------------
@dataclass
class GatewayOptions:
    rate: int = 4000
    samples: int = 80
    sv_ids: tuple[str, ...] = ()
    app_ids: tuple[int, ...] = ()
    dst_macs: tuple[str, ...] = ()
    channels: dict[str, tuple[str, ...]] = field(default_factory=dict)  # per svID


class SvGateway:
    """Ethernet frames in (``feed``), Frames out through ``emit(frame_name, frame)``. A
    frame that is not SV, or not decodable, is counted, never raised. A change of a
    stream's time quality goes to ``on_time_quality(svID, old byte, new byte, arrival_ns)``
    (default: :func:`log_time_quality`, a warning)."""

    def __init__(
        self,
        options: GatewayOptions,
        emit: Callable[[str, Frame], None],
        on_time_quality: Callable[[str, int, int, int], None] | None = None,
    ) -> None:
        from open61850 import sv  # the optional extra ``sinewatch[sv]``

        self._sv = sv
        self.options = options
        self.emit = emit
        self.streams: dict[str, SvStreamDecoder] = {}
        self.not_sv = 0
        self.undecodable = 0
        self.filtered = 0
        self._macs = {m.lower().replace("-", ":") for m in options.dst_macs}
        self.on_time_quality = on_time_quality or log_time_quality

    def feed(self, raw: bytes, arrival_ns: int) -> None:
        try:
            decoded = self._sv.decode_sv_frame(raw)
        except ValueError:  # SvDecodeError (a BerError, a ValueError): a malformed PDU
            self.undecodable += 1
            return
        if decoded is None:
            self.not_sv += 1
            return
        eth, pdu = decoded
        o = self.options
        if (o.app_ids and eth.app_id not in o.app_ids) or (self._macs and eth.dst_mac not in self._macs):
            self.filtered += 1
            return
        for i, asdu in enumerate(pdu.asdus):
            if o.sv_ids and asdu.sv_id not in o.sv_ids:
                self.filtered += 1
                continue
            stream = self.streams.get(asdu.sv_id) or self._stream(asdu.sv_id)
            # several ASDUs in one frame (IEC 61869-9) were sampled 1/rate apart; the frame
            # left with its last one, so the earlier ones "arrived" that much before it
            t = arrival_ns - round((len(pdu.asdus) - 1 - i) * 1e9 / o.rate)
            before = stream.time_quality
            for frame in stream.push(t, asdu.smp_cnt, asdu.smp_synch, asdu.sample):
                self.emit(channel_prefix(asdu.sv_id), frame)
            if stream.time_quality != before:
                self.on_time_quality(asdu.sv_id, before, stream.time_quality, t)

    def _stream(self, sv_id: str) -> SvStreamDecoder:
        spec = StreamSpec(sv_id, self.options.channels.get(sv_id, ()))
        stream = self.streams[sv_id] = SvStreamDecoder(spec, rate=self.options.rate, n_samples=self.options.samples)
        return stream

    def flush(self) -> None:
        for sv_id, stream in self.streams.items():
            for frame in stream.flush():
                self.emit(channel_prefix(sv_id), frame)

    def summary(self) -> dict[str, Any]:
        return {
            "streams": [
                {**asdict(s.stats), "time_quality": describe_time_quality(s.time_quality)}
                for s in self.streams.values()
            ],
            "not_sv": self.not_sv,
            "undecodable": self.undecodable,
            "filtered": self.filtered,
        }


def log_time_quality(sv_id: str, old: int, new: int, arrival_ns: int) -> None:
    """A change of a stream's time quality, as one log line (a warning: shown by default, for
    the operator must know when the time stamps stop, or start again, being traceable)."""
    import logging

    was, now = describe_time_quality(old), describe_time_quality(new)
    logging.getLogger("sinewatch.apps.gateway").warning(
        "stream %s: time quality %s -> %s at %d ns",
        sv_id,
        was,
        now,
        arrival_ns,
    )


# ---- sources --------------------------------------------------------------------------------
def pcap_frames(path: str, *, realtime: bool, stop: threading.Event) -> Iterator[tuple[bytes, int]]:
    """(frame bytes, capture time in ns) from a pcap/pcapng file; with ``realtime`` each
    frame waits for its capture time relative to the first (an Event wait, no busy loop)."""
    from open61850 import pcap

    start_wall = first = None
    for captured in pcap.read_pcap(path):
        t_ns = round(captured.timestamp * 1e9)
        if realtime:
            if first is None:
                first, start_wall = t_ns, time.monotonic_ns()
            assert start_wall is not None
            due = start_wall + (t_ns - first)
            wait = due - time.monotonic_ns()
            if wait > 0 and stop.wait(wait / 1e9):
                return
        if stop.is_set():
            return
        yield captured.data, t_ns


#: Linux's SO_RCVBUFFORCE (not exported by Python's socket module): SO_RCVBUF beyond
#: net.core.rmem_max, for a process with CAP_NET_ADMIN
_SO_RCVBUFFORCE = 33


def _large_receive_buffer(sock: socket.socket, size: int) -> None:
    """A receive buffer of ``size`` bytes, to absorb the bursts of a gateway that is late on a
    loaded machine. SO_RCVBUF alone is capped at net.core.rmem_max (208 KiB on many
    distributions); a process allowed to (root, or CAP_NET_ADMIN, as a capture usually is)
    forces the size past it."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, size)
    except OSError:  # not permitted: the largest the system allows
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)


def iface_frames(
    iface: str, *, stop: threading.Event, on_ready: Callable[[], None] | None = None, idle_s: float = 0.0
) -> Iterator[tuple[bytes, int]]:
    """(frame bytes, receive time in ns) of the frames on a network interface (Linux
    AF_PACKET; root or CAP_NET_RAW), until ``stop`` is set or, with ``idle_s``, the bus has
    been silent that long after a first frame (what is still in the socket's buffer is read
    first, so nothing received is left behind)."""
    eth_p_all = 0x0003
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(eth_p_all))
    try:
        _large_receive_buffer(sock, 32 * 1024 * 1024)
        sock.bind((iface, 0))
        sock.settimeout(0.2)  # how often ``stop`` and ``idle_s`` are looked at while silent
        if on_ready is not None:
            on_ready()
        last = None
        while not stop.is_set():
            try:
                data, addr = sock.recvfrom(65535)
            except TimeoutError:
                if idle_s and last is not None and time.monotonic() - last > idle_s:
                    return
                continue
            last = time.monotonic()
            if addr[2] == socket.PACKET_OUTGOING:
                continue
            yield data, time.time_ns()
    finally:
        sock.close()


def run(source: Iterable[tuple[bytes, int]], gateway: SvGateway) -> None:
    for raw, arrival_ns in source:
        gateway.feed(raw, arrival_ns)
    gateway.flush()


def serve(args: Any) -> int:
    """``sinewatch gateway sv``: a source (pcap file or interface) through the gateway to
    Zenoh; prints the per-stream counts as one JSON object on stdout at the end."""
    import json
    import logging

    from sinewatch.clients import BlockPublisher, connect

    log = logging.getLogger("sinewatch.apps.gateway")
    if bool(args.pcap) == bool(args.iface):
        raise GatewayError("gateway sv: expected exactly one of --pcap FILE or --iface NAME")
    try:
        from open61850.pcap import PcapError
    except ImportError:
        raise GatewayError(
            "gateway sv: expected the open61850 package (pip install 'sinewatch[sv]'), got none"
        ) from None
    options = GatewayOptions(
        rate=args.rate,
        samples=args.samples,
        sv_ids=tuple(args.sv_id or ()),
        app_ids=tuple(args.app_id or ()),
        dst_macs=tuple(parse_mac(m) for m in args.dst_mac or ()),
        channels=parse_channels(args.channels or []),
    )
    stop = threading.Event()
    with connect(args.connect, timeout_s=args.wait) as session:
        pub = BlockPublisher(session, prefix=args.key_prefix, dtype="float64")
        waited: set[str] = set()

        def emit(name: str, frame: Frame) -> None:
            if name not in waited:  # the first frame of a stream waits (once) for the daemon
                waited.add(name)
                if not pub.wait_for_frame_subscriber(name, args.wait):
                    log.warning("no subscriber on %s after %s s: publishing anyway", pub.key(name), args.wait)
            pub.publish_frame_raw(name, pub.encode_frame(frame), pub.frame_encoding(frame))

        gateway = SvGateway(options, emit)
        status = threading.Thread(
            target=_status_loop, args=(session, args.status_prefix, gateway, stop), name="sv-status", daemon=True
        )
        status.start()
        if args.duration:
            timer = threading.Timer(args.duration, stop.set)
            timer.daemon = True
            timer.start()
        if args.pcap:
            source = pcap_frames(args.pcap, realtime=args.realtime, stop=stop)
        else:
            source = iface_frames(args.iface, stop=stop, on_ready=_say(f"listening on {args.iface}"), idle_s=args.idle)
        failed: str | None = None
        try:
            run(source, gateway)
        except KeyboardInterrupt:
            gateway.flush()
        except PcapError as exc:  # a cut capture: what was complete is published, then the error
            gateway.flush()
            failed = f"--pcap {args.pcap}: expected a pcap or pcapng capture of Ethernet frames, got {exc}"
        finally:
            stop.set()
        status.join()
        _put_status(session, args.status_prefix, gateway)  # the final counts
        _settle(session)
        pub.close()
    summary = gateway.summary()
    summary["published"] = pub.published
    print(json.dumps(summary), file=sys.stdout, flush=True)
    if failed is not None:
        raise GatewayError(failed)
    return 0


def _put_status(session: Any, prefix: str, gateway: SvGateway) -> None:
    """Each stream's counts and whether it is synchronised now, as JSON on PREFIX/<svID>:
    the operator's live view of what the frames cannot carry (time quality)."""
    import json

    for sv_id, stream in list(gateway.streams.items()):
        msg = {
            **asdict(stream.stats),
            "synchronised": stream.synchronised,
            "time_quality": describe_time_quality(stream.time_quality),
        }
        session.put(f"{prefix}/{channel_prefix(sv_id)}", json.dumps(msg).encode())


def _status_loop(session: Any, prefix: str, gateway: SvGateway, stop: threading.Event) -> None:
    while not stop.wait(1.0):  # once a second while running
        _put_status(session, prefix, gateway)


def _say(text: str) -> Callable[[], None]:
    def say() -> None:
        print(f"gateway sv: {text}", file=sys.stderr, flush=True)

    return say


def _settle(session: Any, timeout_s: float = 5.0) -> None:
    """A round trip to the daemons' admin queryables before the session closes: frames still
    in the session's send queue would be lost with it, and the reply comes after them."""
    for _ in session.get("sinewatch/admin/*/channels", timeout=timeout_s):
        pass


def parse_channels(items: list[str]) -> dict[str, tuple[str, ...]]:
    """``SVID=IA,IB,...`` (repeatable) -> {svID: names}."""
    out: dict[str, tuple[str, ...]] = {}
    for item in items:
        sv_id, sep, names = item.partition("=")
        parts = tuple(n.strip() for n in names.split(",") if n.strip())
        if not sep or not sv_id or len(parts) != len(DEFAULT_CHANNELS) or any(_NAME_BAD.search(n) for n in parts):
            raise GatewayError(
                f"--channels: expected SVID=NAME,... with {len(DEFAULT_CHANNELS)} names (9-2LE) of "
                f"[A-Za-z0-9_.-], got {item!r}"
            )
        out[sv_id] = parts
    return out


def parse_mac(text: str) -> str:
    parts = text.replace("-", ":").split(":")
    if len(parts) != 6 or not all(re.fullmatch(r"[0-9A-Fa-f]{2}", p) for p in parts):
        raise GatewayError(f"--dst-mac: expected six hex octets like 01:0c:cd:04:00:01, got {text!r}")
    return ":".join(parts).lower()


__all__ = [
    "DEFAULT_CHANNELS",
    "LE_SCALES",
    "GatewayError",
    "GatewayOptions",
    "StreamSpec",
    "StreamStats",
    "SvGateway",
    "SvStreamDecoder",
    "channel_prefix",
    "describe_time_quality",
    "iface_frames",
    "log_time_quality",
    "parse_channels",
    "parse_mac",
    "pcap_frames",
    "run",
    "sync_code",
]
