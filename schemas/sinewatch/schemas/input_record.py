"""The recorded form of an input: a protobuf message any MCAP reader decodes with the schema
the file carries (MCAP message encoding ``protobuf``, schema encoding ``protobuf``: a
serialised ``google.protobuf.FileDescriptorSet``), and from which replay rebuilds the exact
bytes and Zenoh encoding the daemon received.

The message (:data:`INPUT_PROTO` is its ``.proto`` text)::

    message InputBlock {
      string zenoh_encoding = 1;     // the Zenoh encoding the payload arrived with
      string channel = 2;
      fixed64 seq = 3;
      sfixed64 t0_ns = 4;            // time of the first sample, ns since the epoch
      double sample_rate_hz = 5;
      uint32 columns = 6;            // values per sample
      uint32 n_samples = 7;
      string unit = 8;
      repeated double samples = 9;   // float64 blocks: n_samples * columns, sample-major
      repeated float samples_f32 = 10;  // float32 blocks, likewise
      uint32 binary_version = 11;    // > 0: the payload is the binary layout of this version,
      uint32 binary_flags = 12;      //      rebuilt from the fields (with these flags)
      bytes raw = 13;                // otherwise: the payload as received
      Time timestamp = 14;           // t0_ns as {sec, nsec}
    }
    message Time { sfixed64 sec = 1; fixed32 nsec = 2; }

A well-formed binary block (:mod:`sinewatch.schemas.codec`) is recorded as its fields, its
samples copied as they are (little-endian IEEE 754 is protobuf's packed ``double``/``float``
wire form), so the record is the payload's size plus about 60 bytes and costs one copy; the
payload is rebuilt from it byte for byte. Anything else (a JSON block, a payload the daemon
rejected) is recorded as ``raw`` with, when it decodes as a block, the same fields filled in,
so a reader plots every block the daemon accepted. Either way ``zenoh_encoding`` is the
message's own, so replay feeds the pipeline exactly what it got live.

Only the protobuf wire format is written and read here (a handful of fields), so sinewatch
needs no protobuf runtime; tests/test_recording_standard_readers.py decodes recordings with
the standard decoders (Python ``mcap-protobuf-support``, Node ``@mcap/support``) and no
sinewatch code.
"""

from __future__ import annotations

import functools
import struct
from typing import Any

from sinewatch.schemas.codec import HEADER, MAGIC, decode_block
from sinewatch.schemas.errors import InputError

INPUT_SCHEMA_NAME = "sinewatch.InputBlock"
INPUT_MESSAGE_ENCODING = "protobuf"
INPUT_SCHEMA_ENCODING = "protobuf"

INPUT_PROTO = """syntax = "proto3";
package sinewatch;

// time as whole seconds and nanoseconds since the epoch
message Time {
  sfixed64 sec = 1;
  fixed32 nsec = 2;
}

// One input as the daemon received it: its samples for any reader, and what replay needs to
// rebuild the received bytes (the binary layout from the fields, or raw) and their encoding.
message InputBlock {
  string zenoh_encoding = 1;
  string channel = 2;
  fixed64 seq = 3;
  sfixed64 t0_ns = 4;
  double sample_rate_hz = 5;
  uint32 columns = 6;
  uint32 n_samples = 7;
  string unit = 8;
  repeated double samples = 9;
  repeated float samples_f32 = 10;
  uint32 binary_version = 11;
  uint32 binary_flags = 12;
  bytes raw = 13;
  Time timestamp = 14;
}
"""

# FieldDescriptorProto.Type and .Label values (google/protobuf/descriptor.proto)
_DOUBLE, _FLOAT, _FIXED64, _FIXED32, _STRING, _MESSAGE, _BYTES, _UINT32, _SFIXED64 = 1, 2, 6, 7, 9, 11, 12, 13, 16
_OPTIONAL, _REPEATED = 1, 3

_TIME_FIELDS = (("sec", 1, _SFIXED64, _OPTIONAL, ""), ("nsec", 2, _FIXED32, _OPTIONAL, ""))
_INPUT_FIELDS = (
    ("zenoh_encoding", 1, _STRING, _OPTIONAL, ""),
    ("channel", 2, _STRING, _OPTIONAL, ""),
    ("seq", 3, _FIXED64, _OPTIONAL, ""),
    ("t0_ns", 4, _SFIXED64, _OPTIONAL, ""),
    ("sample_rate_hz", 5, _DOUBLE, _OPTIONAL, ""),
    ("columns", 6, _UINT32, _OPTIONAL, ""),
    ("n_samples", 7, _UINT32, _OPTIONAL, ""),
    ("unit", 8, _STRING, _OPTIONAL, ""),
    ("samples", 9, _DOUBLE, _REPEATED, ""),
    ("samples_f32", 10, _FLOAT, _REPEATED, ""),
    ("binary_version", 11, _UINT32, _OPTIONAL, ""),
    ("binary_flags", 12, _UINT32, _OPTIONAL, ""),
    ("raw", 13, _BYTES, _OPTIONAL, ""),
    ("timestamp", 14, _MESSAGE, _OPTIONAL, ".sinewatch.Time"),
)

# wire types
_VARINT, _I64, _LEN, _I32 = 0, 1, 2, 5


_SMALL = [bytes((i,)) for i in range(0x80)]


def _varint(n: int) -> bytes:
    if 0 <= n < 0x80:
        return _SMALL[n]
    if 0 < n < 0x4000:  # two bytes: a block's sample bytes up to 16 KiB
        return bytes(((n & 0x7F) | 0x80, n >> 7))
    out = bytearray()
    n &= (1 << 64) - 1  # negative int64: ten bytes, two's complement (protobuf's rule)
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


@functools.lru_cache(maxsize=64)
def _key(field: int, wire_type: int) -> bytes:
    return _varint(field << 3 | wire_type)


def _len_field(field: int, data: bytes) -> bytes:
    return _key(field, _LEN) + _varint(len(data)) + data


#: The same few strings (encodings, channel names, units) on every block: encoded once each.
_string_field = functools.lru_cache(maxsize=4096)(_len_field)


def _field_descriptor(name: str, number: int, type_: int, label: int, type_name: str) -> bytes:
    # FieldDescriptorProto: name = 1, number = 3, label = 4, type = 5, type_name = 6, json_name = 10
    json_name = name.split("_")[0] + "".join(w.title() for w in name.split("_")[1:])
    out = _len_field(1, name.encode()) + _key(3, _VARINT) + _varint(number)
    out += _key(4, _VARINT) + _varint(label) + _key(5, _VARINT) + _varint(type_)
    if type_name:
        out += _len_field(6, type_name.encode())
    return out + _len_field(10, json_name.encode())


def _message_descriptor(name: str, fields: tuple[tuple[str, int, int, int, str], ...]) -> bytes:
    # DescriptorProto: name = 1, field = 2
    return _len_field(1, name.encode()) + b"".join(_len_field(2, _field_descriptor(*f)) for f in fields)


@functools.cache
def file_descriptor_set() -> bytes:
    """The schema as MCAP's protobuf profile wants it: a serialised FileDescriptorSet holding
    ``sinewatch/input_block.proto`` (package ``sinewatch``, proto3)."""
    # FileDescriptorProto: name = 1, package = 2, message_type = 4, syntax = 12
    file = _len_field(1, b"sinewatch/input_block.proto") + _len_field(2, b"sinewatch")
    file += _len_field(4, _message_descriptor("Time", _TIME_FIELDS))
    file += _len_field(4, _message_descriptor("InputBlock", _INPUT_FIELDS))
    file += _len_field(12, b"proto3")
    return _len_field(1, file)  # FileDescriptorSet: file = 1


_DOUBLE_BYTES = struct.Struct("<d")
_U64_BYTES = struct.Struct("<Q")


# field 14 (Time, 14 bytes long): sec = 1 (sfixed64), nsec = 2 (fixed32), in one pack
_TIME = struct.Struct("<BBBqBI")
_TIME_HEAD = (14 << 3 | _LEN, 14, 1 << 3 | _I64)
_NSEC_KEY = 2 << 3 | _I32
# fields 3, 4, 5: seq (fixed64), t0_ns (sfixed64), sample_rate_hz (double), keys and values in one pack
_FIXED = struct.Struct("<BQBqBd")
_SEQ_KEY, _T0_KEY, _FS_KEY = 3 << 3 | _I64, 4 << 3 | _I64, 5 << 3 | _I64
_COLUMNS_KEY, _N_KEY, _VERSION_KEY, _FLAGS_KEY = (bytes((k << 3 | _VARINT,)) for k in (6, 7, 11, 12))
_SAMPLES_KEY, _SAMPLES_F32_KEY = bytes((9 << 3 | _LEN,)), bytes((10 << 3 | _LEN,))


def _time(ns: int) -> bytes:
    sec, nsec = divmod(ns, 1_000_000_000)
    return _TIME.pack(*_TIME_HEAD, sec, _NSEC_KEY, nsec)


def _fields(
    channel: bytes, seq: int, t0_ns: int, fs: float, columns: int, n: int, unit: bytes, samples: bytes, f32: bool
) -> list[bytes]:
    """The block's fields, in field order (``samples`` as their little-endian bytes)."""
    parts = [_string_field(2, channel)] if channel else []
    parts += (
        _FIXED.pack(_SEQ_KEY, seq, _T0_KEY, t0_ns, _FS_KEY, fs),
        _COLUMNS_KEY,
        _varint(columns),
        _N_KEY,
        _varint(n),
    )
    if unit:
        parts.append(_string_field(8, unit))
    if samples:
        parts += (_SAMPLES_F32_KEY if f32 else _SAMPLES_KEY, _varint(len(samples)), samples)
    return parts


_HEAD = HEADER.size


def _binary_layout(payload: bytes) -> tuple[Any, ...] | None:
    """The header of a payload that is a complete binary block (any version but 0, any flags;
    channel and unit UTF-8), or None: exactly what :func:`encode_input_record` can rebuild."""
    if len(payload) < _HEAD or payload[:4] != MAGIC:
        return None
    fields = HEADER.unpack_from(payload)
    version, dcode, columns, n, clen, ulen = fields[1], fields[2], fields[3], fields[8], fields[9], fields[10]
    # no samples: which samples field is absent would not say the dtype; such a block goes raw
    if version == 0 or not 1 <= dcode <= 2 or n * columns == 0:
        return None
    if len(payload) != _HEAD + clen + ulen + n * columns * (4 if dcode == 1 else 8):
        return None
    if not payload[_HEAD : _HEAD + clen + ulen].isascii():  # the usual case, cheaply; else UTF-8 (protobuf's strings)
        try:
            payload[_HEAD : _HEAD + clen].decode("utf-8")
            payload[_HEAD + clen : _HEAD + clen + ulen].decode("utf-8")
        except UnicodeDecodeError:
            return None
    return fields[1:]


def encode_input_record(payload: bytes, zenoh_encoding: str) -> bytes:
    """The InputBlock record of one received input (any bytes, any encoding)."""
    parts = [_string_field(1, zenoh_encoding.encode())] if zenoh_encoding else []
    layout = _binary_layout(payload)
    if layout is not None:
        version, dcode, columns, flags, seq, t0, fs, n, clen, ulen = layout
        start = HEADER.size + clen + ulen
        channel, unit = payload[HEADER.size : HEADER.size + clen], payload[HEADER.size + clen : start]
        parts += _fields(channel, seq, t0, fs, columns, n, unit, payload[start:], dcode == 1)
        parts += (_VERSION_KEY, _varint(version))
        if flags:
            parts += (_FLAGS_KEY, _varint(flags))
        parts.append(_time(t0))
        return b"".join(parts)
    try:
        block = decode_block(payload, zenoh_encoding)
    except InputError:
        block = None  # a rejected input: its bytes alone
    if block is not None:
        samples = block.samples.astype("<f8", copy=False).tobytes()
        unit = (block.unit or "").encode()
        parts += _fields(
            block.channel.encode(), block.seq, block.t0_ns, block.sample_rate_hz, block.columns, block.n_samples, unit,
            samples, False,
        )  # fmt: skip
    parts.append(_len_field(13, payload))
    if block is not None:
        parts.append(_time(block.t0_ns))
    return b"".join(parts)


class InputRecordError(InputError):
    """A recorded InputBlock is not what :func:`encode_input_record` writes (a damaged file)."""


def _read_varint(data: memoryview, at: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if at >= len(data) or shift > 63:
            raise InputRecordError(f"InputBlock: expected a varint at byte {at}, got the record's end")
        byte = data[at]
        value |= (byte & 0x7F) << shift
        at += 1
        shift += 7
        if byte < 0x80:
            return value, at


def _parse(data: bytes) -> dict[int, int | bytes]:
    """Field number -> its last value (int for varint and fixed, bytes for length-delimited)."""
    view = memoryview(data)
    out: dict[int, int | bytes] = {}
    at = 0
    while at < len(view):
        key, at = _read_varint(view, at)
        field, wire_type = key >> 3, key & 7
        if wire_type == _VARINT:
            out[field], at = _read_varint(view, at)
        elif wire_type == _I64:
            out[field] = _U64_BYTES.unpack_from(view, at)[0]
            at += 8
        elif wire_type == _I32:
            out[field] = struct.unpack_from("<I", view, at)[0]
            at += 4
        elif wire_type == _LEN:
            n, at = _read_varint(view, at)
            if at + n > len(view):
                raise InputRecordError(f"InputBlock field {field}: expected {n} bytes, got {len(view) - at}")
            out[field] = bytes(view[at : at + n])
            at += n
        else:
            raise InputRecordError(f"InputBlock: expected wire type 0, 1, 2 or 5, got {wire_type} (field {field})")
    return out


def decode_input_record(data: bytes) -> tuple[bytes, str]:
    """(payload, Zenoh encoding) exactly as the daemon received them, from an InputBlock."""
    try:
        f = _parse(data)
    except struct.error as exc:
        raise InputRecordError(f"InputBlock: cut short ({exc})") from None
    encoding = _bytes(f, 1)
    if not _int(f, 11):  # not the binary layout: the bytes as received
        return _bytes(f, 13), encoding.decode()
    f32 = 10 in f
    version, flags, seq, t0, fs_bits, columns, n = (_int(f, k) for k in (11, 12, 3, 4, 5, 6, 7))
    channel, unit, samples = (_bytes(f, k) for k in (2, 8, 10 if f32 else 9))
    t0 = t0 - (1 << 64) if t0 >= 1 << 63 else t0
    fs = _DOUBLE_BYTES.unpack(_U64_BYTES.pack(fs_bits))[0]
    head = HEADER.pack(MAGIC, version, 1 if f32 else 2, columns, flags, seq, t0, fs, n, len(channel), len(unit))
    return b"".join((head, channel, unit, samples)), encoding.decode()


def _int(fields: dict[int, int | bytes], number: int) -> int:
    value = fields.get(number, 0)
    if not isinstance(value, int):
        raise InputRecordError(f"InputBlock field {number}: expected a number, got bytes")
    return value


def _bytes(fields: dict[int, int | bytes], number: int) -> bytes:
    value = fields.get(number, b"")
    if not isinstance(value, bytes):
        raise InputRecordError(f"InputBlock field {number}: expected bytes, got a number")
    return value


__all__ = [
    "INPUT_MESSAGE_ENCODING",
    "INPUT_PROTO",
    "INPUT_SCHEMA_ENCODING",
    "INPUT_SCHEMA_NAME",
    "InputRecordError",
    "decode_input_record",
    "encode_input_record",
    "file_descriptor_set",
]
