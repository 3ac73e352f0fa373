"""IEEE C37.118.2-2011 frames (synchrophasor data transfer): encode and decode, by hand.

The frame layer shared by the daemon's PMU server (:mod:`sinewatch.outputs.c37118_server`) and the
reader in the client library (:mod:`sinewatch.clients.c37118`); pure Python (``struct``),
no I/O. Why not a PyPI package: see docs/c37118.md (the candidates were evaluated; none is
sound enough to put on the wire). Clause and table numbers below are the standard's.

Every frame (clause 6.2, Table 2), big-endian ("network order"):

====  ==========  =====================================================================
off   field       size and meaning
====  ==========  =====================================================================
0     SYNC        2: 0xAA, then bit 7 reserved (0), bits 6-4 frame type (000 data,
                  001 header, 010 CFG-1, 011 CFG-2, 101 CFG-3, 100 command), bits 3-0
                  version: 2 for CFG-3 (added in 2011), 1 for the frames defined in
                  C37.118-2005, which "shall remain version 1" (clause 6.2.1)
2     FRAMESIZE   2: bytes in the frame, SYNC to CHK inclusive
4     IDCODE      2: data stream ID (the PMU/PDC's; in a command, the destination's)
6     SOC         4: seconds since 1970-01-01 UTC (unsigned)
10    FRACSEC     4: bits 31-24 message time quality (Table 3: bit 31 reserved, 30 leap
                  second direction, 29 leap second occurred, 28 leap second pending,
                  27-24 time quality code, Table 4), bits 23-0 fraction of second as an
                  integer count of 1/TIME_BASE s
14    ...         the frame's own words (Tables 5, 8, 10, 13, 14)
-2    CHK         2: CRC-CCITT (polynomial x^16 + x^12 + x^5 + 1, initial 0xFFFF, no
                  final XOR, no reflection) of every byte before it
====  ==========  =====================================================================

Data frame words (clause 6.3, Tables 5 and 6), per PMU block: STAT 2 (Table 6), PHASORS
4 or 8 each, FREQ 2 or 4, DFREQ 2 or 4, ANALOG 2 or 4 each, DIGITAL 2 each. FORMAT
(Table 9) bit 0: phasors polar (1) or rectangular (0); bit 1: phasors float (1) or 16-bit
integer (0); bit 2: analogs float; bit 3: FREQ/DFREQ float. As floats FREQ is the
frequency in Hz and DFREQ the ROCOF in Hz/s; as integers FREQ is the deviation from nominal
in mHz and DFREQ the ROCOF in Hz/s x 100. Integer phasors are scaled by PHUNIT (10^-5 V or A
per bit; polar angle in rad x 10^4).

Configuration frames 1 and 2 (clause 6.4, Table 8): TIME_BASE 4, NUM_PMU 2, then per PMU
STN 16, IDCODE 2, FORMAT 2, PHNMR 2, ANNMR 2, DGNMR 2, CHNAM 16 x (PHNMR + ANNMR +
16 DGNMR), PHUNIT 4 x PHNMR, ANUNIT 4 x ANNMR, DIGUNIT 4 x DGNMR, FNOM 2 (bit 0: 1 = 50 Hz,
0 = 60 Hz), CFGCNT 2; after the PMUs DATA_RATE 2 (signed: > 0 frames per second, < 0
seconds per frame). Configuration frame 3 (Table 10): CONT_IDX 2 before TIME_BASE; names
are length-prefixed (1-255 bytes, Table 12); per PMU after IDCODE a 16-byte G_PMU_ID; PHSCALE
12 per phasor (flags 2, type 1, user 1, scale float, angle offset float); ANSCALE 8 per analog
(scale float, offset float); DIGUNIT 4; then PMU_LAT, PMU_LON, PMU_ELEV (float), SVC_CLASS
(1 ASCII byte, M or P), WINDOW (int32, us), GRP_DLY (int32, us), FNOM 2, CFGCNT 2.

Command frame (clause 6.6): CMD 2 (1 turn off transmission of data frames, 2 turn on,
3 send HDR, 4 send CFG-1, 5 send CFG-2, 6 send CFG-3, 8 extended frame), then EXTFRAME
(optional, up to 65518 bytes). Header frame (clause 6.5): ASCII text.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from sinewatch.schemas.errors import DecodeError

SYNC_BYTE = 0xAA
VERSION_2005 = 1
VERSION_2011 = 2
HEADER_SIZE = 14  # SYNC, FRAMESIZE, IDCODE, SOC, FRACSEC
MIN_FRAME_SIZE = HEADER_SIZE + 2  # ... and CHK
MAX_FRAME_SIZE = 65535
NAME_SIZE = 16  # CFG-1/2 names: 16 ASCII bytes, space padded


class FrameError(DecodeError):
    """Bytes that are not a valid C37.118.2 frame. ``kind`` says why: ``sync`` (no 0xAA),
    ``size`` (FRAMESIZE too small), ``truncated`` (fewer bytes than the frame or its words
    need), ``crc`` (CHK does not match), ``type`` (not the frame type expected), ``content``."""

    kind = "content"


class FrameType(IntEnum):
    """SYNC bits 6-4 (Table 2)."""

    DATA = 0
    HEADER = 1
    CFG1 = 2
    CFG2 = 3
    CMD = 4
    CFG3 = 5


class Command(IntEnum):
    """CMD word of a command frame (clause 6.6)."""

    DATA_OFF = 0x0001
    DATA_ON = 0x0002
    SEND_HDR = 0x0003
    SEND_CFG1 = 0x0004
    SEND_CFG2 = 0x0005
    SEND_CFG3 = 0x0006
    EXTENDED = 0x0008


class DataError(IntEnum):
    """STAT bits 15-14 (Table 6)."""

    GOOD = 0b00  # good measurement data, no errors
    PMU_ERROR_NO_INFO = 0b01  # PMU error, no information about data
    TEST_OR_ABSENT = 0b10  # PMU in test mode, or absent data tags inserted (do not use values)
    PMU_ERROR = 0b11  # PMU error (do not use values)


# ---- CRC-CCITT (clause 6.2, CHK) ----------------------------------------------------------------
def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc_ccitt(data: bytes) -> int:
    """CRC-CCITT as C37.118.2 specifies it: polynomial 0x1021, initial 0xFFFF, MSB first, no
    final XOR (the "CCITT-FALSE" variant: ``crc_ccitt(b"123456789") == 0x29B1``)."""
    crc = 0xFFFF
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]
    return crc


# ---- time (clause 6.2.2) -------------------------------------------------------------------------
def fracsec_word(
    fraction: int,
    time_quality: int = 0,
    *,
    leap_direction_negative: bool = False,
    leap_occurred: bool = False,
    leap_pending: bool = False,
) -> int:
    """FRACSEC: bits 23-0 the fraction count, 27-24 the time quality code (Table 4), 28 leap
    second pending, 29 leap second occurred, 30 leap second direction (1: delete)."""
    if not 0 <= fraction < 1 << 24:
        raise ValueError(f"FRACSEC fraction: expected 0 <= fraction < 2^24, got {fraction}")
    if not 0 <= time_quality <= 15:
        raise ValueError(f"time quality code: expected 0..15, got {time_quality}")
    flags = (leap_direction_negative << 6) | (leap_occurred << 5) | (leap_pending << 4) | time_quality
    return (flags << 24) | fraction


def split_fracsec(word: int) -> tuple[int, int]:
    """(fraction count, time quality code) of a FRACSEC word."""
    return word & 0xFFFFFF, (word >> 24) & 0x0F


def soc_fraction(t_ns: int, time_base: int) -> tuple[int, int]:
    """SOC and fraction count (1/TIME_BASE s, rounded half up) of a time in ns since the epoch."""
    soc, nsec = divmod(t_ns, 1_000_000_000)
    fraction = (nsec * time_base + 500_000_000) // 1_000_000_000
    if fraction >= time_base:  # rounded up to the next second
        soc, fraction = soc + 1, fraction - time_base
    if not 0 <= soc < 1 << 32:
        raise ValueError(f"SOC: expected a time between 1970 and 2106, got {t_ns} ns")
    return soc, fraction


def time_ns(soc: int, fraction: int, time_base: int) -> int:
    """The time in ns since the epoch of SOC + fraction / TIME_BASE (rounded half up to 1 ns)."""
    return soc * 1_000_000_000 + (fraction * 1_000_000_000 * 2 + time_base) // (2 * time_base)


# ---- the common frame ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Frame:
    """One frame, checked (SYNC, FRAMESIZE, CRC) but its body not yet interpreted."""

    frame_type: FrameType
    version: int
    id_code: int
    soc: int
    fracsec: int  # the whole FRACSEC word (time quality flags and fraction)
    body: bytes  # the words between FRACSEC and CHK

    @property
    def fraction(self) -> int:
        return self.fracsec & 0xFFFFFF

    @property
    def time_quality(self) -> int:
        return (self.fracsec >> 24) & 0x0F


_HEADER = struct.Struct(">BBHHII")


def encode_frame(
    frame_type: FrameType, id_code: int, soc: int, fracsec: int, body: bytes, version: int | None = None
) -> bytes:
    """SYNC, FRAMESIZE, IDCODE, SOC, FRACSEC, the body, CHK. ``version`` None: 2 for CFG-3, else 1."""
    if version is None:
        version = VERSION_2011 if frame_type is FrameType.CFG3 else VERSION_2005
    size = MIN_FRAME_SIZE + len(body)
    if size > MAX_FRAME_SIZE:
        raise ValueError(f"FRAMESIZE: expected at most {MAX_FRAME_SIZE} bytes, got {size}")
    if not 1 <= version <= 15:
        raise ValueError(f"version: expected 1..15, got {version}")
    head = _HEADER.pack(SYNC_BYTE, (int(frame_type) << 4) | version, size, id_code, soc, fracsec)
    out = head + body
    return out + crc_ccitt(out).to_bytes(2, "big")


def frame_size(head: bytes) -> int:
    """FRAMESIZE from the first 4 bytes of a frame, after checking the SYNC byte."""
    if len(head) < 4:
        raise FrameError(
            f"truncated frame: expected at least 4 bytes (SYNC, FRAMESIZE), got {len(head)}", kind="truncated"
        )
    if head[0] != SYNC_BYTE:
        raise FrameError(f"SYNC: expected first byte 0xAA, got 0x{head[0]:02X}", kind="sync")
    size = int.from_bytes(head[2:4], "big")
    if size < MIN_FRAME_SIZE:
        raise FrameError(f"FRAMESIZE: expected at least {MIN_FRAME_SIZE}, got {size}", kind="size")
    return size


def decode_frame(data: bytes) -> Frame:
    """Check SYNC, FRAMESIZE (equal to ``len(data)``), the frame type and CHK; split the header."""
    size = frame_size(data)
    if size != len(data):
        raise FrameError(
            f"FRAMESIZE: the frame says {size} bytes, got {len(data)}", kind="truncated" if len(data) < size else "size"
        )
    want = crc_ccitt(data[:-2])
    got = int.from_bytes(data[-2:], "big")
    if want != got:
        raise FrameError(f"CHK: expected CRC-CCITT 0x{want:04X}, got 0x{got:04X}", kind="crc")
    _, type_version, _, id_code, soc, fracsec = _HEADER.unpack_from(data)
    code = (type_version >> 4) & 0x07
    try:
        frame_type = FrameType(code)
    except ValueError:
        raise FrameError(f"frame type: expected 0-5, got {code}", kind="type") from None
    return Frame(frame_type, type_version & 0x0F, id_code, soc, fracsec, bytes(data[HEADER_SIZE:-2]))


class FrameSplitter:
    """Splits a byte stream (TCP) into frames. A stream that does not start with SYNC is
    resynchronised on the next 0xAA (``skipped`` counts the bytes dropped)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.skipped = 0

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        out: list[bytes] = []
        while len(self._buf) >= 4:
            if self._buf[0] != SYNC_BYTE or int.from_bytes(self._buf[2:4], "big") < MIN_FRAME_SIZE:
                nxt = self._buf.find(SYNC_BYTE, 1)
                drop = len(self._buf) if nxt < 0 else nxt
                self.skipped += drop
                del self._buf[:drop]
                continue
            size = int.from_bytes(self._buf[2:4], "big")
            if len(self._buf) < size:
                break
            out.append(bytes(self._buf[:size]))
            del self._buf[:size]
        return out

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)


# ---- command and header frames (clauses 6.5, 6.6) -------------------------------------------------
def encode_command(
    id_code: int, command: int, soc: int = 0, fracsec: int = 0, extframe: bytes = b"", version: int | None = None
) -> bytes:
    return encode_frame(FrameType.CMD, id_code, soc, fracsec, command.to_bytes(2, "big") + extframe, version)


def decode_command(frame: Frame) -> tuple[int, bytes]:
    """(CMD, EXTFRAME) of a command frame."""
    if frame.frame_type is not FrameType.CMD:
        raise FrameError(f"expected a command frame, got {frame.frame_type.name}", kind="type")
    if len(frame.body) < 2:
        raise FrameError(f"command frame: expected a 2-byte CMD word, got {len(frame.body)} byte(s)", kind="truncated")
    return int.from_bytes(frame.body[:2], "big"), frame.body[2:]


def encode_header(id_code: int, text: str, soc: int, fracsec: int, version: int | None = None) -> bytes:
    return encode_frame(FrameType.HEADER, id_code, soc, fracsec, text.encode("ascii", "replace"), version)


# ---- configuration frames (clause 6.4) -----------------------------------------------------------
@dataclass(frozen=True)
class DataFormat:
    """FORMAT (Table 9)."""

    polar: bool = True
    phasor_float: bool = True
    analog_float: bool = True
    freq_float: bool = True

    @property
    def word(self) -> int:
        return self.polar | (self.phasor_float << 1) | (self.analog_float << 2) | (self.freq_float << 3)

    @classmethod
    def of(cls, word: int) -> DataFormat:
        return cls(bool(word & 1), bool(word & 2), bool(word & 4), bool(word & 8))


@dataclass(frozen=True)
class PhasorScale:
    """CFG-3 PHSCALE (12 bytes): flags, phasor type (bit 3: 1 current; bits 2-0: component,
    0 zero sequence, 1 positive, 2 negative, 4 phase A, 5 B, 6 C), user byte, scale, angle offset."""

    flags: int = 0
    type_code: int = 0
    user: int = 0
    scale: float = 1.0
    angle_offset: float = 0.0


@dataclass(frozen=True)
class PmuConfig:
    """One PMU (data stream) of a configuration frame."""

    station: str
    id_code: int
    format: DataFormat
    phasor_names: list[str]
    analog_names: list[str] = field(default_factory=list)
    digital_names: list[str] = field(default_factory=list)  # 16 per digital word
    phunit: list[int] = field(default_factory=list)  # CFG-1/2: byte 3 type (0 V, 1 A), bytes 2-0 scale, 1e-5/bit
    anunit: list[int] = field(default_factory=list)
    digunit: list[int] = field(default_factory=list)
    nominal_frequency_hz: int = 50
    cfgcnt: int = 0
    # CFG-3 only
    g_pmu_id: bytes = bytes(16)
    phscale: list[PhasorScale] = field(default_factory=list)
    anscale: list[tuple[float, float]] = field(default_factory=list)
    latitude: float = math.nan
    longitude: float = math.nan
    elevation: float = math.nan
    service_class: str = "M"
    window_us: int = 0
    group_delay_us: int = 0

    @property
    def n_digital(self) -> int:
        return len(self.digital_names) // 16

    def block_size(self) -> int:
        """Bytes of this PMU's block in a data frame."""
        f = self.format
        return (
            2
            + len(self.phasor_names) * (8 if f.phasor_float else 4)
            + 2 * (4 if f.freq_float else 2)
            + len(self.analog_names) * (4 if f.analog_float else 2)
            + 2 * self.n_digital
        )


@dataclass(frozen=True)
class ConfigFrame:
    frame_type: FrameType  # CFG1, CFG2 or CFG3
    id_code: int
    time_base: int
    pmus: list[PmuConfig]
    data_rate: int
    soc: int = 0
    fracsec: int = 0
    cont_idx: int = 0  # CFG-3 continuation index (0: the only frame)
    version: int | None = None  # None: as the standard says (2 for CFG-3, else 1)

    def data_block_size(self) -> int:
        return sum(p.block_size() for p in self.pmus)


def _name16(name: str) -> bytes:
    raw = name.encode("ascii", "replace")[:NAME_SIZE]
    return raw.ljust(NAME_SIZE, b" ")


def _name_var(name: str) -> bytes:
    raw = name.encode("utf-8")[:255]
    return bytes([len(raw)]) + raw


def encode_config(cfg: ConfigFrame) -> bytes:
    if cfg.frame_type not in (FrameType.CFG1, FrameType.CFG2, FrameType.CFG3):
        raise ValueError(f"expected CFG1, CFG2 or CFG3, got {cfg.frame_type.name}")
    cfg3 = cfg.frame_type is FrameType.CFG3
    parts = [struct.pack(">H", cfg.cont_idx)] if cfg3 else []
    parts.append(struct.pack(">IH", cfg.time_base & 0xFFFFFF, len(cfg.pmus)))
    for p in cfg.pmus:
        _check_pmu(p, cfg3)
        name = _name_var if cfg3 else _name16
        parts.append(name(p.station))
        parts.append(struct.pack(">H", p.id_code))
        if cfg3:
            parts.append(p.g_pmu_id)
        parts.append(struct.pack(">HHHH", p.format.word, len(p.phasor_names), len(p.analog_names), p.n_digital))
        parts += [name(n) for n in (*p.phasor_names, *p.analog_names, *p.digital_names)]
        if cfg3:
            parts += [struct.pack(">HBBff", s.flags, s.type_code, s.user, s.scale, s.angle_offset) for s in p.phscale]
            parts += [struct.pack(">ff", scale, offset) for scale, offset in p.anscale]
        else:
            parts += [struct.pack(">I", u) for u in p.phunit]
            parts += [struct.pack(">I", u) for u in p.anunit]
        parts += [struct.pack(">I", u) for u in p.digunit]
        if cfg3:
            parts.append(
                struct.pack(
                    ">fffcii",
                    p.latitude,
                    p.longitude,
                    p.elevation,
                    p.service_class.encode("ascii"),
                    p.window_us,
                    p.group_delay_us,
                )
            )
        parts.append(struct.pack(">HH", 1 if p.nominal_frequency_hz == 50 else 0, p.cfgcnt))
    parts.append(struct.pack(">h", cfg.data_rate))
    return encode_frame(cfg.frame_type, cfg.id_code, cfg.soc, cfg.fracsec, b"".join(parts), cfg.version)


def _check_pmu(p: PmuConfig, cfg3: bool) -> None:
    if len(p.digital_names) % 16:
        raise ValueError(f"digital names: expected 16 per digital word, got {len(p.digital_names)}")
    units = (p.phscale, p.anscale) if cfg3 else (p.phunit, p.anunit)
    want = (len(p.phasor_names), len(p.analog_names))
    if (len(units[0]), len(units[1])) != want or len(p.digunit) != p.n_digital:
        raise ValueError(
            f"PMU {p.station!r}: expected one unit per phasor, analog and digital word {(*want, p.n_digital)}, "
            f"got {(len(units[0]), len(units[1]), len(p.digunit))}"
        )


class _Reader:
    def __init__(self, body: bytes, what: str) -> None:
        self.body = body
        self.pos = 0
        self.what = what

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.body):
            raise FrameError(
                f"{self.what}: truncated, expected {n} more byte(s) at offset {HEADER_SIZE + self.pos}, "
                f"got {len(self.body) - self.pos}",
                kind="truncated",
            )
        out = self.body[self.pos : self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str) -> tuple[Any, ...]:
        s = struct.Struct(">" + fmt)
        return s.unpack(self.take(s.size))

    def u16(self) -> int:
        return int.from_bytes(self.take(2), "big")

    def name16(self) -> str:
        return self.take(NAME_SIZE).decode("ascii", "replace").rstrip(" \x00")

    def name_var(self) -> str:
        n = self.take(1)[0]
        return self.take(n).decode("utf-8", "replace")


def decode_config(frame: Frame) -> ConfigFrame:
    if frame.frame_type not in (FrameType.CFG1, FrameType.CFG2, FrameType.CFG3):
        raise FrameError(f"expected a configuration frame, got {frame.frame_type.name}", kind="type")
    cfg3 = frame.frame_type is FrameType.CFG3
    r = _Reader(frame.body, frame.frame_type.name)
    cont_idx = r.u16() if cfg3 else 0
    time_base = int.from_bytes(r.take(4), "big") & 0xFFFFFF
    if time_base == 0:
        raise FrameError("TIME_BASE: expected 1..2^24-1, got 0")
    n_pmu = r.u16()
    pmus = []
    for _ in range(n_pmu):
        name = r.name_var if cfg3 else r.name16
        station = name()
        id_code = r.u16()
        g_pmu_id = r.take(16) if cfg3 else bytes(16)
        fmt, phnmr, annmr, dgnmr = (int(v) for v in r.unpack("HHHH"))
        names = [name() for _ in range(phnmr + annmr + 16 * dgnmr)]
        phunit: list[int] = []
        anunit: list[int] = []
        phscale: list[PhasorScale] = []
        anscale: list[tuple[float, float]] = []
        if cfg3:
            for _ in range(phnmr):
                flags, type_code, user, scale, angle = r.unpack("HBBff")
                phscale.append(PhasorScale(int(flags), int(type_code), int(user), float(scale), float(angle)))
            for _ in range(annmr):
                scale, offset = r.unpack("ff")
                anscale.append((float(scale), float(offset)))
        else:
            phunit = [int.from_bytes(r.take(4), "big") for _ in range(phnmr)]
            anunit = [int.from_bytes(r.take(4), "big") for _ in range(annmr)]
        digunit = [int.from_bytes(r.take(4), "big") for _ in range(dgnmr)]
        extra: dict[str, Any] = {}
        if cfg3:
            lat, lon, elev, svc, window, delay = r.unpack("fffcii")
            extra = dict(
                latitude=lat,
                longitude=lon,
                elevation=elev,
                service_class=bytes(svc).decode("ascii", "replace"),
                window_us=window,
                group_delay_us=delay,
            )
        fnom, cfgcnt = r.unpack("HH")
        pmus.append(
            PmuConfig(
                station=station,
                id_code=id_code,
                format=DataFormat.of(fmt),
                phasor_names=names[:phnmr],
                analog_names=names[phnmr : phnmr + annmr],
                digital_names=names[phnmr + annmr :],
                phunit=phunit,
                anunit=anunit,
                digunit=digunit,
                nominal_frequency_hz=50 if int(fnom) & 1 else 60,
                cfgcnt=int(cfgcnt),
                g_pmu_id=g_pmu_id,
                phscale=phscale,
                anscale=anscale,
                **extra,
            )
        )
    (data_rate,) = r.unpack("h")
    if r.pos != len(r.body):
        raise FrameError(f"{frame.frame_type.name}: {len(r.body) - r.pos} unexpected byte(s) after DATA_RATE")
    return ConfigFrame(
        frame.frame_type,
        frame.id_code,
        time_base,
        pmus,
        int(data_rate),
        frame.soc,
        frame.fracsec,
        cont_idx,
        frame.version,
    )


# ---- data frames (clause 6.3) ---------------------------------------------------------------------
def stat_word(
    data_error: DataError = DataError.GOOD,
    *,
    in_sync: bool = True,
    sorted_by_arrival: bool = False,
    trigger: bool = False,
    config_change: bool = False,
    data_modified: bool = False,
    pmu_time_quality: int = 0,
    unlocked: int = 0,
    trigger_reason: int = 0,
) -> int:
    """STAT (Table 6): 15-14 data error, 13 PMU sync error (1: not in sync with UTC), 12 data
    sorting (1: by arrival), 11 trigger, 10 configuration change, 9 data modified, 8-6 PMU
    time quality (Table 7), 5-4 unlocked time (00 < 10 s ... 11 > 1000 s), 3-0 trigger reason."""
    if not 0 <= pmu_time_quality <= 7 or not 0 <= unlocked <= 3 or not 0 <= trigger_reason <= 15:
        raise ValueError(
            f"STAT: expected time quality 0..7, unlocked 0..3, trigger reason 0..15, "
            f"got {pmu_time_quality}, {unlocked}, {trigger_reason}"
        )
    return (
        (int(data_error) << 14)
        | ((not in_sync) << 13)
        | (sorted_by_arrival << 12)
        | (trigger << 11)
        | (config_change << 10)
        | (data_modified << 9)
        | (pmu_time_quality << 6)
        | (unlocked << 4)
        | trigger_reason
    )


@dataclass(frozen=True)
class PmuData:
    """One PMU's block of a data frame, in engineering units: phasors as (magnitude, angle rad)
    when the format is polar, else (real, imaginary); FREQ in Hz, DFREQ in Hz/s."""

    stat: int
    phasors: list[tuple[float, float]]
    freq_hz: float
    dfreq_hz_per_s: float
    analogs: list[float] = field(default_factory=list)
    digitals: list[int] = field(default_factory=list)

    @property
    def data_error(self) -> DataError:
        return DataError((self.stat >> 14) & 0b11)

    @property
    def in_sync(self) -> bool:
        return not (self.stat >> 13) & 1

    @property
    def data_modified(self) -> bool:
        return bool((self.stat >> 9) & 1)


@dataclass(frozen=True)
class DataFrame:
    id_code: int
    soc: int
    fracsec: int
    pmus: list[PmuData]


def _phunit_scale(unit: int) -> float:
    return (unit & 0xFFFFFF) * 1e-5


def _int16(v: float, what: str) -> int:
    r = round(v)
    if not -32767 <= r <= 32767:
        raise ValueError(f"{what}: expected a 16-bit integer value, got {v}")
    return r


def encode_data(cfg: ConfigFrame, soc: int, fracsec: int, pmus: list[PmuData]) -> bytes:
    """A data frame for configuration ``cfg`` (its PMUs in order, one PmuData each)."""
    if len(pmus) != len(cfg.pmus):
        raise ValueError(f"data frame: expected {len(cfg.pmus)} PMU block(s), got {len(pmus)}")
    parts: list[bytes] = []
    for p, d in zip(cfg.pmus, pmus, strict=True):
        f = p.format
        if len(d.phasors) != len(p.phasor_names) or len(d.analogs) != len(p.analog_names):
            raise ValueError(
                f"PMU {p.station!r}: expected {len(p.phasor_names)} phasors and {len(p.analog_names)} analogs, "
                f"got {len(d.phasors)} and {len(d.analogs)}"
            )
        parts.append(struct.pack(">H", d.stat))
        for (a, b), unit in zip(d.phasors, p.phunit or [0] * len(d.phasors), strict=True):
            if f.phasor_float:
                parts.append(struct.pack(">ff", a, b))
            else:
                scale = _phunit_scale(unit) or 1.0
                if f.polar:
                    parts.append(struct.pack(">Hh", max(0, min(65535, round(a / scale))), _int16(b * 1e4, "angle")))
                else:
                    parts.append(struct.pack(">hh", _int16(a / scale, "real"), _int16(b / scale, "imaginary")))
        if f.freq_float:
            parts.append(struct.pack(">ff", d.freq_hz, d.dfreq_hz_per_s))
        else:
            dev = (d.freq_hz - p.nominal_frequency_hz) * 1000.0
            parts.append(struct.pack(">hh", _int16(dev, "FREQ"), _int16(d.dfreq_hz_per_s * 100.0, "DFREQ")))
        for v, unit in zip(d.analogs, p.anunit or [0] * len(d.analogs), strict=True):
            if f.analog_float:
                parts.append(struct.pack(">f", v))
            else:
                scale = _anunit_scale(unit)
                parts.append(struct.pack(">h", _int16(v / scale, "analog")))
        parts += [struct.pack(">H", w) for w in d.digitals]
    return encode_frame(FrameType.DATA, cfg.id_code, soc, fracsec, b"".join(parts), cfg.version)


def _anunit_scale(unit: int) -> float:
    raw = unit & 0xFFFFFF
    if raw & 0x800000:
        raw -= 1 << 24
    return raw * 1e-5 if raw else 1.0


def decode_data(frame: Frame, cfg: ConfigFrame) -> DataFrame:
    """The PMU blocks of a data frame, read with the configuration it was sent under."""
    if frame.frame_type is not FrameType.DATA:
        raise FrameError(f"expected a data frame, got {frame.frame_type.name}", kind="type")
    want = cfg.data_block_size()
    if len(frame.body) != want:
        raise FrameError(f"data frame: expected {want} bytes of PMU data for the configuration, got {len(frame.body)}")
    r = _Reader(frame.body, "data frame")
    out = []
    for p in cfg.pmus:
        f = p.format
        stat = r.u16()
        phasors: list[tuple[float, float]] = []
        for unit in p.phunit or [0] * len(p.phasor_names):
            if f.phasor_float:
                a, b = r.unpack("ff")
                phasors.append((float(a), float(b)))
            else:
                scale = _phunit_scale(unit) or 1.0
                if f.polar:
                    m, ang = r.unpack("Hh")
                    phasors.append((int(m) * scale, int(ang) * 1e-4))
                else:
                    re, im = r.unpack("hh")
                    phasors.append((int(re) * scale, int(im) * scale))
        if f.freq_float:
            fr, dfr = r.unpack("ff")
            freq, dfreq = float(fr), float(dfr)
        else:
            fr, dfr = r.unpack("hh")
            freq = p.nominal_frequency_hz + int(fr) / 1000.0
            dfreq = int(dfr) / 100.0
        analogs = []
        for unit in p.anunit or [0] * len(p.analog_names):
            if f.analog_float:
                (v,) = r.unpack("f")
                analogs.append(float(v))
            else:
                (v,) = r.unpack("h")
                analogs.append(int(v) * _anunit_scale(unit))
        digitals = [r.u16() for _ in range(p.n_digital)]
        out.append(PmuData(stat, phasors, freq, dfreq, analogs, digitals))
    return DataFrame(frame.id_code, frame.soc, frame.fracsec, out)


__all__ = [
    "Command",
    "ConfigFrame",
    "DataError",
    "DataFormat",
    "DataFrame",
    "Frame",
    "FrameError",
    "FrameSplitter",
    "FrameType",
    "PhasorScale",
    "PmuConfig",
    "PmuData",
    "crc_ccitt",
    "decode_command",
    "decode_config",
    "decode_data",
    "decode_frame",
    "encode_command",
    "encode_config",
    "encode_data",
    "encode_frame",
    "encode_header",
    "fracsec_word",
    "soc_fraction",
    "split_fracsec",
    "stat_word",
    "time_ns",
]
