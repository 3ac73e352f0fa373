"""Encoding and decoding of sinewatch messages (wire format version 1).

Every message announces its encoding in its Zenoh Encoding:

=========================================  =============================================
``application/x-sinewatch-block;v=1``      SampleBlock, compact binary (layout below)
``application/json;sinewatch/SampleBlock@1``  SampleBlock, JSON (schemas/sinewatch/schemas/json/SampleBlock.json)
``application/json;sinewatch/Estimate@5``      Estimate, JSON (``@1``-``@4`` in recordings of earlier builds)
``application/json;sinewatch/ErrorReport@1``   ErrorReport, JSON
``application/json;sinewatch/Status@1``        Status, JSON
=========================================  =============================================

A payload published without an encoding (Zenoh's default ``zenoh/bytes``) is sniffed:
the binary magic ``SWSB`` or a JSON object.

Binary SampleBlock, all little-endian, no padding (``struct`` format ``<4sBBBBQqdIHH``)::

    offset size type     field
    0      4    bytes    magic b"SWSB"
    4      1    u8       format_version (1)
    5      1    u8       dtype: 1 = float32, 2 = float64
    6      1    u8       columns (>= 1): values per sample
    7      1    u8       flags: the time quality (0 = not stated; see below)
    8      8    u64      seq
    16     8    i64      t0_ns, time of the first sample, ns since the epoch
    24     8    f64      sample_rate_hz
    32     4    u32      n_samples
    36     2    u16      channel_len (bytes)
    38     2    u16      unit_len (bytes, 0 = no unit)
    40     .    utf-8    channel
    .      .    utf-8    unit
    .      .    f32/f64  samples: n_samples * columns values, sample-major
                         (s0c0, s0c1, ..., s1c0, ...); the payload ends here.

A reader decodes the samples with ``np.frombuffer(payload, "<f4" or "<f8",
offset=40 + channel_len + unit_len)``.

The time-quality byte (a SampleBlock's ``flags``, a SampleFrame's header from format version
2; :class:`sinewatch.schemas.messages.TimeQuality`)::

    0         not stated (what every sender wrote before the byte had a meaning)
    bit 7     1: stated; then
    bits 1-0  sync: 0 none, 1 local area clock, 2 global area clock (UTC-traceable): the
              IEC 61850-9-2 ``smpSynch`` values; 3 is refused
    bit 2     holdover: the time reference was lost during the stream, the clock runs free
    bits 6-3  zero

So 0x80 not synchronised, 0x81 local, 0x82 global, 0x84 not synchronised since a loss,
0x86 global but holding over. Any other value is a DecodeError.
"""

from __future__ import annotations

import functools
import json
import math
import re
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import ValidationError

from sinewatch.schemas.errors import DecodeError, InputError, UnsupportedVersionError
from sinewatch.schemas.messages import (
    CHANNEL_PATTERN,
    ESTIMATE_FORMAT_VERSION,
    FORMAT_VERSION,
    ErrorReport,
    Estimate,
    SampleBlock,
    Status,
    TimeQuality,
)

BLOCK_BINARY_ENCODING = "application/x-sinewatch-block;v=1"
BLOCK_JSON_ENCODING = "application/json;sinewatch/SampleBlock@1"
ESTIMATE_JSON_ENCODING = f"application/json;sinewatch/Estimate@{ESTIMATE_FORMAT_VERSION}"
ESTIMATE_V1_JSON_ENCODING = "application/json;sinewatch/Estimate@1"
ERROR_JSON_ENCODING = "application/json;sinewatch/ErrorReport@1"
STATUS_JSON_ENCODING = "application/json;sinewatch/Status@1"

MAGIC = b"SWSB"
HEADER = struct.Struct("<4sBBBBQqdIHH")
_DTYPE_CODES: dict[int, np.dtype[np.floating[Any]]] = {1: np.dtype("<f4"), 2: np.dtype("<f8")}
_CODE_OF_DTYPE = {"float32": 1, "float64": 2}
_CHANNEL_RE = re.compile(CHANNEL_PATTERN)

# ---- time quality: one byte on the binary encodings (module docstring) -------------------
TQ_NOT_STATED = 0
TQ_STATED = 0x80
TQ_HOLDOVER = 0x04
TQ_SYNC_MASK = 0x03
SYNC_NAMES = ("none", "local", "global")  # index = the sync code = IEC 61850-9-2 smpSynch
_TQ_VALID = frozenset(TQ_STATED | h | s for h in (0, TQ_HOLDOVER) for s in range(3)) | {TQ_NOT_STATED}


def time_quality_byte(sync: str | int, holdover: bool = False) -> int:
    """The byte of a stated time quality (``sync`` a name of :data:`SYNC_NAMES` or its code)."""
    code = SYNC_NAMES.index(sync) if isinstance(sync, str) else sync
    if not 0 <= code <= 2:
        raise InputError(f"time quality sync: expected none, local or global (0-2), got {sync!r}")
    return TQ_STATED | (TQ_HOLDOVER if holdover else 0) | code


def check_time_quality(byte: int, where: str) -> int:
    """``byte`` if it is a valid time-quality byte, else a DecodeError saying so."""
    if byte not in _TQ_VALID:
        raise DecodeError(
            f"{where}: expected 0 (time quality not stated) or 0x80 | holdover 0x04 | sync 0-2, got 0x{byte:02X}"
        )
    return byte


def time_quality_model(byte: int) -> TimeQuality | None:
    """The message form of a time-quality byte (None: not stated)."""
    if byte == TQ_NOT_STATED:
        return None
    return TimeQuality(sync=SYNC_NAMES[byte & TQ_SYNC_MASK], holdover=bool(byte & TQ_HOLDOVER))


def time_quality_of(model: TimeQuality | None) -> int:
    return TQ_NOT_STATED if model is None else time_quality_byte(model.sync, model.holdover)


#: each valid byte's JSON, as :func:`dumps` writes the Estimate's ``time_quality``
TIME_QUALITY_JSON: dict[int, str] = {
    b: "null"
    if b == TQ_NOT_STATED
    else f'{{"sync":"{SYNC_NAMES[b & TQ_SYNC_MASK]}","holdover":{"true" if b & TQ_HOLDOVER else "false"}}}'
    for b in _TQ_VALID
}


@dataclass(slots=True)
class Block:
    """A decoded SampleBlock with its samples as a numpy array ((N,) or (N, columns))."""

    channel: str
    seq: int
    t0_ns: int
    sample_rate_hz: float
    samples: np.ndarray
    unit: str | None = None
    time_quality: int = TQ_NOT_STATED  # the time-quality byte (module docstring)

    @property
    def n_samples(self) -> int:
        return int(self.samples.shape[0])

    @property
    def columns(self) -> int:
        return 1 if self.samples.ndim == 1 else int(self.samples.shape[1])


# ---- SampleBlock ------------------------------------------------------------------------
def encode_block_binary(block: Block, dtype: str = "float64") -> bytes:
    """The compact binary encoding (layout in the module docstring)."""
    if dtype not in _CODE_OF_DTYPE:
        raise InputError(f"dtype: expected float32 or float64, got {dtype!r}")
    channel = block.channel.encode("utf-8")
    unit = (block.unit or "").encode("utf-8")
    arr = np.ascontiguousarray(block.samples, dtype=_DTYPE_CODES[_CODE_OF_DTYPE[dtype]])
    header = HEADER.pack(
        MAGIC,
        FORMAT_VERSION,
        _CODE_OF_DTYPE[dtype],
        block.columns,
        check_time_quality(block.time_quality, "time_quality"),
        block.seq,
        block.t0_ns,
        block.sample_rate_hz,
        block.n_samples,
        len(channel),
        len(unit),
    )
    return b"".join((header, channel, unit, arr.tobytes()))


def encode_block_json(block: Block) -> bytes:
    samples = block.samples.tolist()
    msg = {
        "format_version": FORMAT_VERSION,
        "channel": block.channel,
        "seq": block.seq,
        "t0_ns": block.t0_ns,
        "sample_rate_hz": block.sample_rate_hz,
        "dtype": "float64",
        "columns": block.columns,
        "unit": block.unit,
        "samples": samples,
    }
    return json.dumps(msg, separators=(",", ":"), allow_nan=True).encode("utf-8")


def decode_block(payload: bytes, encoding: str = "") -> Block:
    """Decode a SampleBlock from either encoding; raise DecodeError (or its subclass
    UnsupportedVersionError) with a reason when the payload is not a valid block.

    Any payload from any peer ends here: nothing but an InputError ever leaves this
    function, so one hostile or buggy sender cannot stop a daemon's intake."""
    try:
        return _decode_any(payload, encoding)
    except InputError:
        raise
    except Exception as exc:  # the boundary of untrusted input: a decoder gap is a rejection
        raise DecodeError(f"block: not decodable ({type(exc).__name__}: {str(exc)[:200]})") from exc


def is_json_block(payload: bytes, encoding: str = "") -> bool:
    """Whether :func:`decode_block` takes ``payload`` as JSON (its encoding says so, or it
    is unlabelled and starts with ``{``): what a size limit for JSON applies to."""
    if encoding.startswith("application/x-sinewatch-block"):
        return False
    if encoding.startswith(("application/json", "text/json")):
        return True
    return payload[:4] != MAGIC and payload[:1] == b"{"


def _decode_any(payload: bytes, encoding: str) -> Block:
    if encoding.startswith("application/x-sinewatch-block"):
        return _decode_binary(payload, encoding)
    if encoding.startswith(("application/json", "text/json")):
        return _decode_json(payload)
    if payload[:4] == MAGIC:
        return _decode_binary(payload, encoding)
    if payload[:1] == b"{":
        return _decode_json(payload)
    raise DecodeError(
        f"encoding: expected {BLOCK_BINARY_ENCODING!r} or {BLOCK_JSON_ENCODING!r}, "
        f"got {encoding or 'none'!r} with a payload that is neither"
    )


def _decode_binary(payload: bytes, encoding: str) -> Block:
    version = _encoding_version(encoding)
    if version is not None and version != FORMAT_VERSION:
        raise UnsupportedVersionError(f"format version: expected {FORMAT_VERSION}, got {version} (from the encoding)")
    if len(payload) < HEADER.size:
        raise DecodeError(f"binary block: expected at least {HEADER.size} bytes, got {len(payload)}")
    magic, ver, dcode, columns, flags, seq, t0, fs, n, clen, ulen = HEADER.unpack_from(payload)
    if magic != MAGIC:
        raise DecodeError(f"binary block: expected magic {MAGIC!r}, got {magic!r}")
    if ver != FORMAT_VERSION:
        raise UnsupportedVersionError(f"format version: expected {FORMAT_VERSION}, got {ver}")
    dtype = _DTYPE_CODES.get(dcode)
    if dtype is None:
        raise DecodeError(f"binary block dtype: expected 1 (float32) or 2 (float64), got {dcode}")
    if columns < 1:
        raise DecodeError("binary block columns: expected >= 1, got 0")
    start = HEADER.size + clen + ulen
    expected = start + n * columns * dtype.itemsize
    if len(payload) != expected:
        raise DecodeError(
            f"binary block length: expected {expected} bytes for {n} x {columns} "
            f"{dtype.name} samples, got {len(payload)}"
        )
    try:
        channel = payload[HEADER.size : HEADER.size + clen].decode("utf-8")
        unit = payload[HEADER.size + clen : start].decode("utf-8") or None
    except UnicodeDecodeError as exc:
        raise DecodeError(f"binary block: channel/unit are not UTF-8 ({exc})") from None
    _check_channel(channel)
    if not (math.isfinite(fs) and fs > 0):
        raise DecodeError(f"sample_rate_hz: expected a finite value > 0, got {fs}")
    samples = np.frombuffer(payload, dtype=dtype, count=n * columns, offset=start)
    if columns > 1:
        samples = samples.reshape(n, columns)
    return Block(channel, seq, t0, fs, samples, unit, check_time_quality(flags, "binary block flags"))


def _decode_json(payload: bytes) -> Block:
    try:
        raw = json.loads(payload)
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:  # RecursionError: nesting too deep
        raise DecodeError(f"JSON block: not valid JSON ({exc})") from None
    if not isinstance(raw, dict):
        raise DecodeError(f"JSON block: expected an object, got {type(raw).__name__}")
    version = raw.get("format_version", FORMAT_VERSION)
    if version != FORMAT_VERSION:
        raise UnsupportedVersionError(f"format version: expected {FORMAT_VERSION}, got {version!r}")
    try:
        msg = SampleBlock.model_validate(raw)
    except ValidationError as exc:
        where, first = first_error(exc)
        got = repr(first.get("input"))
        got = got if len(got) <= 60 else got[:57] + "..."
        raise DecodeError(f"JSON block: {where}: {first['msg']}, got {got}") from None
    samples = _json_samples(msg.samples, msg.columns)
    return Block(msg.channel, msg.seq, msg.t0_ns, msg.sample_rate_hz, samples, msg.unit)


def _json_samples(rows: list[float] | list[list[float]], columns: int) -> np.ndarray:
    """(N,) for one column, (N, columns) otherwise; a single column may also come as
    one-element rows. Ragged or wrongly sized rows are a DecodeError."""
    nested = bool(rows) and isinstance(rows[0], list)  # the model admits all lists or no list
    widths = {len(r) for r in rows} if nested else {1 if rows else columns}  # type: ignore[arg-type]
    if len(widths) != 1:
        raise DecodeError(f"JSON block samples: expected rows of equal length, got lengths {sorted(widths)[:5]}")
    width = widths.pop()
    if width != columns:
        raise DecodeError(f"JSON block samples: expected {columns} column(s), got rows of {width}")
    samples = np.asarray(rows, dtype=np.float64)
    if columns == 1:
        return samples.reshape(-1)
    return samples.reshape(-1, columns)


@functools.lru_cache(maxsize=64)  # a handful of encodings in practice; bounded against hostile ones
def _encoding_version(encoding: str) -> int | None:
    m = re.search(r"[;,]v=(\d+)", encoding)
    return int(m.group(1)) if m else None


@functools.lru_cache(maxsize=8192)  # each channel's name is checked once, not once per block
def _channel_ok(channel: str) -> bool:
    # fullmatch: with match, the pattern's ``$`` also matches before a trailing newline, so
    # "a/b\n" passed here while the pydantic models (Rust regex, ``$`` = end of text) refused it
    return bool(channel) and len(channel) <= 256 and _CHANNEL_RE.fullmatch(channel) is not None


def _check_channel(channel: str) -> None:
    if not _channel_ok(channel):
        raise DecodeError(f"channel: expected 1-256 chars of [A-Za-z0-9_.-] separated by '/', got {channel!r}")


# ---- JSON messages out ----------------------------------------------------------------------
def finite_or_none(x: float) -> float | None:
    """JSON has no NaN/Inf: undefined values travel as null."""
    x = float(x)
    return x if math.isfinite(x) else None


def dumps(msg: dict[str, Any]) -> bytes:
    """Compact, deterministic JSON (key order as built, shortest round-trip floats)."""
    return json.dumps(msg, separators=(",", ":"), allow_nan=False).encode("utf-8")


def encode_estimate(estimate: Estimate, version: int = ESTIMATE_FORMAT_VERSION) -> bytes:
    """The Estimate's JSON bytes in wire-format ``version`` (5, or 4, 3, 2 or 1 for replaying
    recordings of earlier builds: the same bytes those builds wrote)."""
    exclude: dict[str, Any] = {}
    if version < 5:
        exclude.update(dict.fromkeys(Estimate.V5_FIELDS, True))
    if version < 4:
        exclude.update(dict.fromkeys(Estimate.V4_FIELDS, True))
    if version < 3:
        exclude.update(dict.fromkeys(Estimate.V3_FIELDS, True))
        exclude["diagnostics"] = set(Estimate.V3_DIAGNOSTICS)
    if version < 2:
        exclude.update(dict.fromkeys(Estimate.V2_FIELDS, True))
    msg = estimate.model_dump(mode="python", exclude=exclude or None)
    msg["format_version"] = version
    return dumps(msg)


_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)  # what dumps() uses


def json_string(s: str) -> str:
    """``s`` as a JSON string literal, exactly as :func:`dumps` writes it (ASCII, escaped)."""
    return _ENCODER.encode(s)


def _number(x: float | None) -> str:
    """A finite float (or None) as :func:`dumps` writes it: ``repr``, or ``null``."""
    return "null" if x is None else repr(x)


def _numbers(xs: list[float | None]) -> str:
    return "[" + ",".join(["null" if x is None else repr(x) for x in xs]) + "]"


def encode_estimate_values(
    version: int,
    channel_json: str,
    seq: int,
    timestamp_ns: int,
    n_samples: int,
    estimator_json: str,
    frequency_hz: list[float | None],
    amplitude: list[float | None],
    phase_rad: list[float | None],
    offset: float | None,
    rocof_hz_per_s: list[float | None] | None,
    std: tuple[list[float | None], list[float | None], list[float | None], float | None] | None,
    converged: bool,
    valid: bool,
    residual_rms: float | None,
    gap: bool,
    gap_blocks: int,
    restart: bool,
    reset: bool,
    extras: dict[str, float | list[float | None] | None],
    fencing_json: str = "null",
    time_quality_json: str = "null",
) -> bytes:
    """The same bytes as ``encode_estimate(Estimate(...), version)`` for these fields, without
    building the model (the pipeline's hot path: one estimate per block).

    The caller guarantees what the model would check: every float finite or None (as
    :func:`finite_or_none` makes them), ``seq``, ``timestamp_ns``, ``n_samples`` and
    ``gap_blocks`` Python ints (``gap_blocks >= 0``), ``std`` as (frequency_hz, amplitude,
    phase_rad, offset); ``channel_json`` and ``estimator_json`` are :func:`json_string` of
    the names (callers cache them). tests/test_codec_estimate_fast.py proves the bytes equal
    to the model's over every version, null values, std, rocof and extras. ``fencing_json``
    is the ``fencing`` object as :func:`dumps` writes it (format 4; the caller caches it);
    ``time_quality_json`` the ``time_quality`` object (format 5; :data:`TIME_QUALITY_JSON`)."""
    sec, nsec = divmod(timestamp_ns, 1_000_000_000)
    head = (
        f'{{"format_version":{version},"channel":{channel_json},"seq":{seq},"timestamp_ns":{timestamp_ns},'
        + (f'"timestamp":{{"sec":{sec},"nsec":{nsec}}},' if version >= 3 else "")
        + f'"n_samples":{n_samples},"estimator":{estimator_json},"frequency_hz":{_numbers(frequency_hz)},'
        f'"amplitude":{_numbers(amplitude)},"phase_rad":{_numbers(phase_rad)},"offset":{_number(offset)},'
    )
    if version >= 2:
        head += '"rocof_hz_per_s":' + ("null" if rocof_hz_per_s is None else _numbers(rocof_hz_per_s)) + ","
        if std is None:
            head += '"std":null,'
        else:
            head += (
                f'"std":{{"frequency_hz":{_numbers(std[0])},"amplitude":{_numbers(std[1])},'
                f'"phase_rad":{_numbers(std[2])},"offset":{_number(std[3])}}},'
            )
    tail = (
        f'"diagnostics":{{"converged":{"true" if converged else "false"},'
        + (f'"valid":{"true" if valid else "false"},' if version >= 3 else "")
        + f'"residual_rms":{_number(residual_rms)},"gap":{"true" if gap else "false"},"gap_blocks":{gap_blocks},'
        f'"restart":{"true" if restart else "false"},"reset":{"true" if reset else "false"},'
        f'"extras":{_ENCODER.encode(extras) if extras else "{}"}}}'
        + (f',"fencing":{fencing_json}' if version >= 4 else "")
        + (f',"time_quality":{time_quality_json}}}' if version >= 5 else "}")
    )
    return (head + tail).encode("ascii")


def encode_error(report: ErrorReport) -> bytes:
    return dumps(report.model_dump(mode="json"))


def encode_status(status: Status) -> bytes:
    # c37118 is left out when the server is off: the message stays what earlier builds wrote
    return dumps(status.model_dump(mode="json", exclude={"c37118"} if status.c37118 is None else None))


def first_error(exc: ValidationError) -> tuple[str, Any]:
    """Where a JSON message's first validation error is (its first two path parts, dotted), and
    the error (pydantic's dict): what a decode error names."""
    first = exc.errors()[0]
    return ".".join(str(p) for p in first["loc"][:2]), first
