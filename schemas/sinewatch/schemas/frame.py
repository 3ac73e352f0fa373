"""Multi-channel frames (SampleFrame, wire format version 2): C channels sampled at the
same n instants, in one message.

=============================================  ==========================================
``application/x-sinewatch-frame;v=2``          SampleFrame, compact binary (layout below)
``application/json;sinewatch/SampleFrame@2``   SampleFrame, JSON (schemas/sinewatch/schemas/json/SampleFrame.json)
=============================================  ==========================================

Version 2 added the time quality (what the source says of its clock: not synchronised, a
local or a global area clock, holdover). A frame that states none is written as version 1,
byte for byte what earlier builds wrote (``;v=1``, ``@1``), and both versions are read.

A payload published without an encoding is sniffed: the binary magic ``SWFR``, or a JSON
object with a ``channels`` list.

Binary SampleFrame, all little-endian (``struct`` format ``<4sBBHQqdIIBBH``; version 1:
``<4sBBHQqdII``, the same without bytes 40-43, names at 40)::

    offset size type     field
    0      4    bytes    magic b"SWFR"
    4      1    u8       format_version (2; 1 for a frame without a time quality)
    5      1    u8       dtype: 1 = float32, 2 = float64
    6      2    u16      n_channels C (>= 1)
    8      8    u64      seq
    16     8    i64      t0_ns, time of the first sample, ns since the epoch
    24     8    f64      sample_rate_hz
    32     4    u32      n_samples n
    36     4    u32      names_len (bytes)
    40     1    u8       time_quality (version 2): 0 = not stated; else 0x80 | holdover 0x04 |
                         sync 0 none, 1 local, 2 global (the IEC 61850-9-2 smpSynch values;
                         :mod:`sinewatch.schemas.codec` has the byte's table)
    41     1    u8       reserved (0)
    42     2    u16      reserved (0)
    H      .    utf-8    the C channel names, each followed by one b"\\n"; H = 44 (40 in version 1)
    .      .    zero     pad: 0-7 zero bytes, so that the samples start at a multiple of 8
    S      .    f32/f64  samples: n * C values, sample-major (s0c0, s0c1, ..., s0c(C-1), s1c0, ...);
                         S = H + names_len rounded up to a multiple of 8; the payload ends here.

Sample-major, because that is how a DAQ card, a merging unit (one ASDU per sampling
instant) or a COMTRADE ``.dat`` row delivers them: a gateway copies its scans as they come,
without a transpose, and the daemon's estimator banks take exactly this (n, C) array, all
channels at one instant side by side. A reader needs numpy alone::

    C, n, names_len = struct.unpack_from("<H", p, 6)[0], *struct.unpack_from("<II", p, 32)
    H = 44 if p[4] == 2 else 40
    names = p[H : H + names_len].decode().split("\\n")[:-1]
    x = np.frombuffer(p, "<f4" or "<f8", offset=(H + names_len + 7) // 8 * 8).reshape(n, C)

Keys. A frame published on ``PREFIX/FRAME`` (at least two chunks) carries channels whose
keys are ``PREFIX/<channel name>``: the keys those channels would have if each were sent
alone as a SampleBlock. Rules, errors, status, shards of a cluster and workers address a
frame's channels by those keys and names, as they do single blocks; the frame as a whole
(its recording, its ownership by a shard or a worker) goes by the frame's key.
"""

from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import ValidationError

from sinewatch.schemas.codec import (
    BLOCK_BINARY_ENCODING,
    BLOCK_JSON_ENCODING,
    MAGIC,
    TQ_NOT_STATED,
    Block,
    _channel_ok,
    _encoding_version,
    check_time_quality,
    decode_block,
    first_error,
    time_quality_model,
    time_quality_of,
)
from sinewatch.schemas.errors import DecodeError, InputError, UnsupportedVersionError
from sinewatch.schemas.messages import FRAME_FORMAT_VERSION, SampleFrame

#: a frame without a time quality: version 1, as earlier builds wrote it
FRAME_BINARY_ENCODING = "application/x-sinewatch-frame;v=1"
FRAME_JSON_ENCODING = "application/json;sinewatch/SampleFrame@1"
#: a frame with a time quality: version 2
FRAME_BINARY_ENCODING_V2 = "application/x-sinewatch-frame;v=2"
FRAME_JSON_ENCODING_V2 = "application/json;sinewatch/SampleFrame@2"
FRAME_MAGIC = b"SWFR"
FRAME_HEADER = struct.Struct("<4sBBHQqdII")  # version 1's header; version 2 adds FRAME_HEADER_TAIL
FRAME_HEADER_TAIL = struct.Struct("<BBH")  # version 2: time_quality, reserved u8, reserved u16
FRAME_HEADER_V2_SIZE = FRAME_HEADER.size + FRAME_HEADER_TAIL.size
_VERSIONS = (1, FRAME_FORMAT_VERSION)
_DTYPES: dict[int, np.dtype[np.floating[Any]]] = {1: np.dtype("<f4"), 2: np.dtype("<f8")}
_CODES = {"float32": 1, "float64": 2}
MAX_FRAME_CHANNELS = 65535
_JSON_CHANNELS = re.compile(rb'"channels"\s*:')


@dataclass(slots=True)
class Frame:
    """A decoded SampleFrame: ``samples`` is (n, C), column c the channel ``channels[c]``."""

    channels: tuple[str, ...]
    seq: int
    t0_ns: int
    sample_rate_hz: float
    samples: np.ndarray
    time_quality: int = TQ_NOT_STATED  # the time-quality byte (sinewatch.schemas.codec)

    @property
    def version(self) -> int:
        """The format version the frame is written in: 2 with a time quality, else 1."""
        return 1 if self.time_quality == TQ_NOT_STATED else FRAME_FORMAT_VERSION

    @property
    def n_samples(self) -> int:
        return int(self.samples.shape[0])

    @property
    def n_channels(self) -> int:
        return len(self.channels)

    def block(self, c: int) -> Block:
        """Column ``c`` as the SampleBlock of its channel (same seq and time)."""
        return Block(
            self.channels[c], self.seq, self.t0_ns, self.sample_rate_hz, self.samples[:, c], None, self.time_quality
        )


def header_size(version: int) -> int:
    """Where the names start: after version 1's 40 bytes, or version 2's 44."""
    return FRAME_HEADER.size if version == 1 else FRAME_HEADER_V2_SIZE


def samples_offset(names_len: int, version: int = 1) -> int:
    """Where the samples start: after the header and the names, at a multiple of 8."""
    return (header_size(version) + names_len + 7) // 8 * 8


def frame_encoding(frame: Frame, binary: bool = True) -> str:
    """The Zenoh encoding of ``frame`` in the binary or the JSON encoding (by its version)."""
    if frame.version == 1:
        return FRAME_BINARY_ENCODING if binary else FRAME_JSON_ENCODING
    return FRAME_BINARY_ENCODING_V2 if binary else FRAME_JSON_ENCODING_V2


def channel_key(frame_key: str, channel: str) -> str:
    """The key of a frame's channel: the frame key's parent, then the channel's name."""
    parent, sep, _ = frame_key.rpartition("/")
    if not sep or not parent:
        raise DecodeError(f"frame key: expected PREFIX/FRAME (at least two chunks), got {frame_key!r}")
    return f"{parent}/{channel}"


# ---- encoding ----------------------------------------------------------------------------
def encode_frame_binary(frame: Frame, dtype: str = "float64") -> bytes:
    """The compact binary encoding (layout in the module docstring)."""
    if dtype not in _CODES:
        raise InputError(f"dtype: expected float32 or float64, got {dtype!r}")
    _check_names(frame.channels)
    samples = np.asarray(frame.samples)
    if samples.ndim != 2 or samples.shape[1] != len(frame.channels):
        raise InputError(f"samples: expected shape (n, {len(frame.channels)}), got {samples.shape}")
    names = "".join(f"{c}\n" for c in frame.channels).encode("utf-8")
    version = frame.version
    header = FRAME_HEADER.pack(
        FRAME_MAGIC,
        version,
        _CODES[dtype],
        len(frame.channels),
        frame.seq,
        frame.t0_ns,
        frame.sample_rate_hz,
        samples.shape[0],
        len(names),
    )
    if version > 1:
        header += FRAME_HEADER_TAIL.pack(check_time_quality(frame.time_quality, "time_quality"), 0, 0)
    pad = b"\0" * (samples_offset(len(names), version) - len(header) - len(names))
    data = np.ascontiguousarray(samples, dtype=_DTYPES[_CODES[dtype]])
    return b"".join((header, names, pad, data.tobytes()))


def encode_frame_json(frame: Frame) -> bytes:
    msg: dict[str, Any] = {
        "format_version": frame.version,
        "seq": frame.seq,
        "t0_ns": frame.t0_ns,
        "sample_rate_hz": frame.sample_rate_hz,
        "dtype": "float64",
        "channels": list(frame.channels),
        "samples": np.asarray(frame.samples, dtype=np.float64).tolist(),
    }
    tq = time_quality_model(check_time_quality(frame.time_quality, "time_quality"))
    if tq is not None:  # version 2 only: a version 1 frame's bytes stay what earlier builds wrote
        msg["time_quality"] = tq.model_dump()
    return json.dumps(msg, separators=(",", ":"), allow_nan=True).encode("utf-8")


# ---- decoding ----------------------------------------------------------------------------
def is_frame(payload: bytes, encoding: str) -> bool:
    """Whether a payload is a frame (by its encoding, else by its magic or JSON shape)."""
    if encoding.startswith("application/x-sinewatch-frame") or encoding.startswith(FRAME_JSON_ENCODING[:-2]):
        return True
    if encoding.startswith(("application/x-sinewatch-block", BLOCK_JSON_ENCODING[:-2])):
        return False
    if payload[:4] == FRAME_MAGIC:
        return True
    # a JSON object without a sinewatch encoding: a frame if it has "channels" (a block has "channel")
    return payload[:1] == b"{" and _JSON_CHANNELS.search(payload[:4096]) is not None


def decode_input(payload: bytes, encoding: str = "") -> Block | Frame:
    """A SampleBlock or a SampleFrame, whichever the payload is; nothing but an InputError
    leaves this function."""
    if is_frame(payload, encoding):
        return decode_frame(payload, encoding)
    return decode_block(payload, encoding)


def decode_frame(payload: bytes, encoding: str = "") -> Frame:
    """Decode a SampleFrame from either encoding; raise DecodeError (UnsupportedVersionError
    for a version this build does not know) with a reason when it is not a valid frame."""
    try:
        if encoding.startswith(("application/json", "text/json")) or payload[:1] == b"{":
            return _decode_json(payload)
        return _decode_binary(payload, encoding)
    except InputError:
        raise
    except Exception as exc:  # the boundary of untrusted input: a decoder gap is a rejection
        raise DecodeError(f"frame: not decodable ({type(exc).__name__}: {str(exc)[:200]})") from exc


def _decode_binary(payload: bytes, encoding: str) -> Frame:
    version = _encoding_version(encoding)
    if version is not None and version not in _VERSIONS:
        raise UnsupportedVersionError(f"format version: expected 1 or 2, got {version} (from the encoding)")
    if len(payload) < FRAME_HEADER.size:
        raise DecodeError(f"binary frame: expected at least {FRAME_HEADER.size} bytes, got {len(payload)}")
    magic, ver, dcode, n_ch, seq, t0, fs, n, names_len = FRAME_HEADER.unpack_from(payload)
    if magic != FRAME_MAGIC:
        raise DecodeError(f"binary frame: expected magic {FRAME_MAGIC!r}, got {magic!r}")
    if ver not in _VERSIONS:
        raise UnsupportedVersionError(f"format version: expected 1 or 2, got {ver}")
    if version is not None and version != ver:
        raise DecodeError(f"binary frame: expected format version {version} (as the encoding says), got {ver}")
    tq = TQ_NOT_STATED
    if ver > 1:
        if len(payload) < FRAME_HEADER_V2_SIZE:
            raise DecodeError(f"binary frame: expected at least {FRAME_HEADER_V2_SIZE} bytes, got {len(payload)}")
        tq, reserved8, reserved16 = FRAME_HEADER_TAIL.unpack_from(payload, FRAME_HEADER.size)
        check_time_quality(tq, "binary frame time_quality")
        if reserved8 or reserved16:
            raise DecodeError("binary frame: expected zero reserved bytes 41-43, got non-zero")
    head = header_size(ver)
    dtype = _DTYPES.get(dcode)
    if dtype is None:
        raise DecodeError(f"binary frame dtype: expected 1 (float32) or 2 (float64), got {dcode}")
    if n_ch < 1:
        raise DecodeError("binary frame n_channels: expected >= 1, got 0")
    start = samples_offset(names_len, ver)
    expected = start + n * n_ch * dtype.itemsize
    if len(payload) != expected:
        raise DecodeError(
            f"binary frame length: expected {expected} bytes for {names_len} bytes of names and {n} x {n_ch} "
            f"{dtype.name} samples, got {len(payload)}"
        )
    if any(payload[head + names_len : start]):
        raise DecodeError("binary frame: expected zero pad bytes before the samples, got non-zero")
    raw = payload[head : head + names_len]
    if raw[-1:] != b"\n":
        raise DecodeError(f"binary frame names: expected {n_ch} names each ending in a newline, got {raw[:80]!r}")
    try:
        names = tuple(raw[:-1].decode("utf-8").split("\n"))
    except UnicodeDecodeError as exc:
        raise DecodeError(f"binary frame channel names: expected UTF-8, got {raw[:80]!r} ({exc.reason})") from None
    if len(names) != n_ch:
        raise DecodeError(f"binary frame names: expected {n_ch} (n_channels), got {len(names)}")
    _check_names(names)
    if not (math.isfinite(fs) and fs > 0):
        raise DecodeError(f"sample_rate_hz: expected a finite value > 0, got {fs}")
    samples = np.frombuffer(payload, dtype=dtype, count=n * n_ch, offset=start).reshape(n, n_ch)
    return Frame(names, seq, t0, fs, samples, tq)


def _decode_json(payload: bytes) -> Frame:
    # The steps of codec's JSON block decoder (parse, an object, the version, the model), kept
    # apart: each message names a frame, a frame has two format versions, and the rows then
    # need their widths checked against the channels, which a block has no notion of.
    try:
        raw = json.loads(payload)
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise DecodeError(f"JSON frame: expected valid JSON, got {payload[:40]!r}... ({exc})") from None
    if not isinstance(raw, dict):
        raise DecodeError(f"JSON frame: expected an object, got {type(raw).__name__}")
    version = raw.get("format_version", 1)
    if version not in _VERSIONS or isinstance(version, bool):
        raise UnsupportedVersionError(f"format version: expected 1 or 2, got {version!r}")
    try:
        msg = SampleFrame.model_validate(raw)
    except ValidationError as exc:
        where, first = first_error(exc)
        raise DecodeError(f"JSON frame {where}: expected a valid value, got {first['msg'].lower()}") from None
    n_ch = len(msg.channels)
    widths = {len(r) for r in msg.samples}
    if widths and widths != {n_ch}:
        raise DecodeError(
            f"JSON frame samples: expected rows of {n_ch} values (one per channel), got {sorted(widths)[:5]}"
        )
    samples = np.asarray(msg.samples, dtype=np.float64).reshape(-1, n_ch)
    return Frame(
        tuple(msg.channels), msg.seq, msg.t0_ns, msg.sample_rate_hz, samples, time_quality_of(msg.time_quality)
    )


def _check_names(names: tuple[str, ...] | list[str]) -> None:
    if not 1 <= len(names) <= MAX_FRAME_CHANNELS:
        raise DecodeError(f"frame channels: expected 1-{MAX_FRAME_CHANNELS}, got {len(names)}")
    for name in names:
        if not _channel_ok(name):
            raise DecodeError(f"channel: expected 1-256 chars of [A-Za-z0-9_.-] separated by '/', got {name!r}")
    if len(set(names)) != len(names):
        seen: set[str] = set()
        repeated = next(c for c in names if c in seen or seen.add(c))  # type: ignore[func-returns-value]
        raise DecodeError(f"frame channels: expected distinct names, got {repeated!r} twice")


__all__ = [
    "BLOCK_BINARY_ENCODING",
    "FRAME_BINARY_ENCODING",
    "FRAME_BINARY_ENCODING_V2",
    "FRAME_HEADER",
    "FRAME_HEADER_TAIL",
    "FRAME_HEADER_V2_SIZE",
    "FRAME_JSON_ENCODING",
    "FRAME_JSON_ENCODING_V2",
    "FRAME_MAGIC",
    "MAGIC",
    "Frame",
    "channel_key",
    "decode_frame",
    "decode_input",
    "encode_frame_binary",
    "encode_frame_json",
    "frame_encoding",
    "header_size",
    "is_frame",
    "samples_offset",
]
