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

A multi-channel SampleFrame (:mod:`sinewatch.schemas.frame`) is recorded likewise as an
``InputFrame``: the same field numbers where the meaning is InputBlock's, its own where it
differs, so one reader (:func:`decode_input_record`) rebuilds either from its bytes alone::

    message InputFrame {
      string zenoh_encoding = 1;
      fixed64 seq = 3;
      sfixed64 t0_ns = 4;
      double sample_rate_hz = 5;
      uint32 n_samples = 7;
      repeated double samples = 9;      // n_samples * len(channels), sample-major
      repeated float samples_f32 = 10;
      bytes raw = 13;
      Time timestamp = 14;
      repeated string channels = 15;
      uint32 frame_version = 16;        // > 0: the binary frame layout of this version, rebuilt
                                        //      from the fields; else the payload is in raw
      uint32 time_quality = 17;         // the frame's time-quality byte (format version 2;
    }                                   //      absent: 0, not stated, as in every version 1 frame)

``time_quality`` was added with SampleFrame format version 2; a recording of version 1 frames
has none and replays as before, byte for byte.

A well-formed binary block (:mod:`sinewatch.schemas.codec`) or frame is recorded as its fields, its
samples copied as they are (little-endian IEEE 754 is protobuf's packed ``double``/``float``
wire form), so the record is the payload's size plus about 60 bytes and costs one copy; the
payload is rebuilt from it byte for byte: only a payload whose every byte the fields
determine is recorded so (a frame's pad bytes must be zero, its names end in a newline).
Anything else (a JSON block or frame, a payload the daemon rejected) is recorded as ``raw``
with, when it decodes, the same fields filled in, so a reader plots every block and frame
the daemon accepted. Either way ``zenoh_encoding`` is the
message's own, so replay feeds the pipeline exactly what it got live.

Only the protobuf wire format is written and read here (a handful of fields), so sinewatch
needs no protobuf runtime; tests/test_recording_standard_readers.py decodes recordings with
the standard decoders (Python ``mcap-protobuf-support``, Node ``@mcap/support``) and no
sinewatch code.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Callable
from typing import Any, TypeVar

from sinewatch.schemas.codec import HEADER, MAGIC, decode_block
from sinewatch.schemas.errors import InputError
from sinewatch.schemas.frame import (
    FRAME_HEADER,
    FRAME_HEADER_TAIL,
    FRAME_MAGIC,
    decode_frame,
    header_size,
    samples_offset,
)

_T = TypeVar("_T")

INPUT_SCHEMA_NAME = "sinewatch.InputBlock"
FRAME_SCHEMA_NAME = "sinewatch.InputFrame"
INPUT_MESSAGE_ENCODING = "protobuf"
INPUT_SCHEMA_ENCODING = "protobuf"

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
# InputFrame: InputBlock's fields where the meaning is the same (same numbers, same order), then its own
_FRAME_FIELDS = (
    *(f for f in _INPUT_FIELDS if f[0] not in {"channel", "columns", "unit", "binary_version", "binary_flags"}),
    ("channels", 15, _STRING, _REPEATED, ""),
    ("frame_version", 16, _UINT32, _OPTIONAL, ""),
    ("time_quality", 17, _UINT32, _OPTIONAL, ""),
)

_PROTO_TYPES = {
    _DOUBLE: "double",
    _FLOAT: "float",
    _FIXED64: "fixed64",
    _FIXED32: "fixed32",
    _STRING: "string",
    _BYTES: "bytes",
    _UINT32: "uint32",
    _SFIXED64: "sfixed64",
}


def _proto_message(comment: str, name: str, fields: tuple[tuple[str, int, int, int, str], ...]) -> str:
    """One message of :data:`INPUT_PROTO`, written from the same field table as its descriptor."""
    lines = [f"// {line}" for line in comment.splitlines()] + [f"message {name} {{"]
    for field_name, number, type_, label, type_name in fields:
        spelled = type_name.rsplit(".", 1)[1] if type_ == _MESSAGE else _PROTO_TYPES[type_]
        lines.append(f"  {'repeated ' if label == _REPEATED else ''}{spelled} {field_name} = {number};")
    return "\n".join(lines) + "\n}\n"


#: The schema as ``.proto`` text (what :func:`file_descriptor_set` serialises), for readers.
INPUT_PROTO = 'syntax = "proto3";\npackage sinewatch;\n\n' + "\n".join(
    (
        _proto_message("time as whole seconds and nanoseconds since the epoch", "Time", _TIME_FIELDS),
        _proto_message(
            "One input as the daemon received it: its samples for any reader, and what replay needs to\n"
            "rebuild the received bytes (the binary layout from the fields, or raw) and their encoding.",
            "InputBlock",
            _INPUT_FIELDS,
        ),
        _proto_message(
            "One multi-channel frame as the daemon received it (field numbers InputBlock's where the\n"
            "meaning is the same): its samples sample-major, all channels at one instant side by side.\n"
            "Its fields repeat InputBlock's on purpose: a standard protobuf reader (Foxglove, the mcap\n"
            "CLI) decodes each message from its own descriptor in the file and knows no shared base,\n"
            "and the field numbers, fixed by recordings already written, must stay as they are.",
            "InputFrame",
            _FRAME_FIELDS,
        ),
    )
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
    ``sinewatch/input_block.proto`` (package ``sinewatch``, proto3; InputBlock and InputFrame)."""
    # FileDescriptorProto: name = 1, package = 2, message_type = 4, syntax = 12
    file = _len_field(1, b"sinewatch/input_block.proto") + _len_field(2, b"sinewatch")
    file += _len_field(4, _message_descriptor("Time", _TIME_FIELDS))
    file += _len_field(4, _message_descriptor("InputBlock", _INPUT_FIELDS))
    file += _len_field(4, _message_descriptor("InputFrame", _FRAME_FIELDS))
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


#: a piece of a record: bytes, or a view of a payload's samples (joined without a copy first)
_Part = bytes | memoryview


def _fields(
    channel: bytes,
    seq: int,
    t0_ns: int,
    fs: float,
    columns: int,
    n: int,
    unit: bytes,
    samples: _Part,
    f32: bool,
) -> list[_Part]:
    """The block's fields, in field order (``samples`` as their little-endian bytes)."""
    parts: list[_Part] = [_string_field(2, channel)] if channel else []
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
    parts: list[_Part] = [_string_field(1, zenoh_encoding.encode())] if zenoh_encoding else []
    layout = _binary_layout(payload)
    if layout is not None:
        version, dcode, columns, flags, seq, t0, fs, n, clen, ulen = layout
        start = HEADER.size + clen + ulen
        channel, unit = payload[HEADER.size : HEADER.size + clen], payload[HEADER.size + clen : start]
        parts += _fields(channel, seq, t0, fs, columns, n, unit, memoryview(payload)[start:], dcode == 1)
        parts += (_VERSION_KEY, _varint(version))
        if flags:
            parts += (_FLAGS_KEY, _varint(flags))
        parts.append(_time(t0))
        return b"".join(parts)
    block = _accepted(decode_block, payload, zenoh_encoding)
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


def _accepted(decode: Callable[[bytes, str], _T], payload: bytes, zenoh_encoding: str) -> _T | None:
    """The payload decoded, or None for one the daemon rejected (recorded as its bytes alone)."""
    try:
        return decode(payload, zenoh_encoding)
    except InputError:
        return None


# the frame header with the sample rate as its bits: a NaN's payload bits go through untouched
_FRAME_HEADER_BITS = struct.Struct("<4sBBHQqQII")
_FRAME_FIXED = struct.Struct("<BQBqBQ")
_N_FRAME_KEY, _FRAME_VERSION_KEY = bytes((7 << 3 | _VARINT,)), _key(16, _VARINT)
_TIME_QUALITY_KEY = _key(17, _VARINT)
_FRAME_HEAD = FRAME_HEADER.size


def _frame_layout(payload: bytes) -> tuple[Any, ...] | None:
    """(version, f32, seq, t0_ns, rate bits, n_samples, channel names, samples start, time
    quality) of a payload whose every byte those fields determine: a complete binary frame
    (version 1, or 2 with zero reserved bytes; any later version goes raw, its header unknown
    here), zero pad bytes, UTF-8 names each ending in a newline; else None (it goes raw)."""
    if len(payload) < _FRAME_HEAD or payload[:4] != FRAME_MAGIC:
        return None
    _, version, dcode, n_ch, seq, t0, fs_bits, n, names_len = _FRAME_HEADER_BITS.unpack_from(payload)
    # no samples: which samples field is absent would not say the dtype; such a frame goes raw
    if not 1 <= version <= 2 or not 1 <= dcode <= 2 or n * n_ch == 0:
        return None
    head, tq = _FRAME_HEAD, 0
    if version == 2:
        if len(payload) < header_size(2):
            return None
        tq, reserved8, reserved16 = FRAME_HEADER_TAIL.unpack_from(payload, _FRAME_HEAD)
        if reserved8 or reserved16:
            return None
        head = header_size(2)
    start = samples_offset(names_len, version)
    if len(payload) != start + n * n_ch * (4 if dcode == 1 else 8) or any(payload[head + names_len : start]):
        return None
    names = payload[head : head + names_len]
    if names[-1:] != b"\n":
        return None
    try:
        names.decode("utf-8")
    except UnicodeDecodeError:
        return None
    channels = names[:-1].split(b"\n")
    if len(channels) != n_ch:
        return None
    return version, dcode == 1, seq, t0, fs_bits, n, channels, start, tq


def _frame_fields(
    channels: list[bytes], seq: int, t0_ns: int, fs_bits: int, n: int, samples: _Part, f32: bool
) -> list[_Part]:
    parts: list[_Part] = [_FRAME_FIXED.pack(_SEQ_KEY, seq, _T0_KEY, t0_ns, _FS_KEY, fs_bits), _N_FRAME_KEY, _varint(n)]
    parts += [_len_field(15, c) for c in channels]
    if samples:
        parts += (_SAMPLES_F32_KEY if f32 else _SAMPLES_KEY, _varint(len(samples)), samples)
    return parts


def encode_frame_record(payload: bytes, zenoh_encoding: str) -> bytes:
    """The InputFrame record of one received frame (any bytes, any encoding)."""
    parts: list[_Part] = [_string_field(1, zenoh_encoding.encode())] if zenoh_encoding else []
    layout = _frame_layout(payload)
    if layout is not None:
        version, f32, seq, t0, fs_bits, n, channels, start, tq = layout
        # a view, not a slice: the samples are copied once, by the join (a frame is tens of kB)
        parts += _frame_fields(channels, seq, t0, fs_bits, n, memoryview(payload)[start:], f32)
        parts += (_FRAME_VERSION_KEY, _varint(version), _time(t0))
        if tq:  # field 17 after 14: protobuf readers take fields in any order
            parts += (_TIME_QUALITY_KEY, _varint(tq))
        return b"".join(parts)
    frame = _accepted(decode_frame, payload, zenoh_encoding)
    if frame is not None:
        samples = frame.samples.astype("<f8", copy=False).tobytes()  # (n, C) C-ordered: sample-major
        fs_bits = _U64_BYTES.unpack(_DOUBLE_BYTES.pack(frame.sample_rate_hz))[0]
        names = [c.encode() for c in frame.channels]
        parts += _frame_fields(names, frame.seq, frame.t0_ns, fs_bits, frame.n_samples, samples, False)
    parts.append(_len_field(13, payload))
    if frame is not None:
        parts.append(_time(frame.t0_ns))
        if frame.time_quality:
            parts += (_TIME_QUALITY_KEY, _varint(frame.time_quality))
    return b"".join(parts)


def _rebuild_frame(f: dict[int, int | bytes], channels: list[bytes]) -> bytes:
    f32 = 10 in f
    version, seq, t0, fs_bits, n = (_int(f, k) for k in (16, 3, 4, 5, 7))
    t0 = t0 - (1 << 64) if t0 >= 1 << 63 else t0
    names = b"".join(c + b"\n" for c in channels)
    head = _FRAME_HEADER_BITS.pack(
        FRAME_MAGIC, version, 1 if f32 else 2, len(channels), seq, t0, fs_bits, n, len(names)
    )
    if version == 2:
        tq = _int(f, 17)
        if tq > 0xFF:
            raise InputRecordError(f"InputFrame time_quality: expected one byte (0-255), got {tq}")
        head += FRAME_HEADER_TAIL.pack(tq, 0, 0)
    pad = bytes(samples_offset(len(names), version) - len(head) - len(names))
    return b"".join((head, names, pad, _bytes(f, 10 if f32 else 9)))


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


def _parse(data: bytes) -> tuple[dict[int, int | bytes], list[bytes]]:
    """Field number -> its last value (int for varint and fixed, bytes for length-delimited),
    and InputFrame's channels (the repeated field 15) in order."""
    view = memoryview(data)
    out: dict[int, int | bytes] = {}
    channels: list[bytes] = []
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
            value = out[field] = bytes(view[at : at + n])
            if field == 15:
                channels.append(value)
            at += n
        else:
            raise InputRecordError(f"InputBlock: expected wire type 0, 1, 2 or 5, got {wire_type} (field {field})")
    return out, channels


def decode_input_record(data: bytes) -> tuple[bytes, str]:
    """(payload, Zenoh encoding) exactly as the daemon received them, from an InputBlock or
    an InputFrame."""
    try:
        f, channels = _parse(data)
    except struct.error as exc:
        raise InputRecordError(f"InputBlock: cut short ({exc})") from None
    encoding = _bytes(f, 1)
    if _int(f, 16):  # a frame in the binary layout
        return _rebuild_frame(f, channels), encoding.decode()
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
    "FRAME_SCHEMA_NAME",
    "INPUT_MESSAGE_ENCODING",
    "INPUT_PROTO",
    "INPUT_SCHEMA_ENCODING",
    "INPUT_SCHEMA_NAME",
    "InputRecordError",
    "decode_input_record",
    "encode_frame_record",
    "encode_input_record",
    "file_descriptor_set",
]
