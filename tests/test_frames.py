"""Multi-channel frames (SampleFrame): the bytes on the wire against the byte table, every
malformed frame a typed error, each channel of a frame estimated as if it had been sent
alone (bit for bit), per-channel errors, a channel set that changes mid-stream, and a real
daemon on Zenoh fed frames and single blocks at once whose recording replays bit for bit
and exports per channel."""

from __future__ import annotations

import csv
import json
import struct
from pathlib import Path

import numpy as np
import pytest
from conftest import make_config, run_daemon, take

from sinewatch.apps.export import export
from sinewatch.clients import BlockPublisher, connect, subscribe_errors, subscribe_estimates, subscribe_status
from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.runtime.replay import read_recording, replay
from sinewatch.schemas.codec import (
    SYNC_NAMES,
    TIME_QUALITY_JSON,
    Block,
    decode_block,
    encode_block_binary,
    encode_block_json,
    time_quality_byte,
)
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.errors import DecodeError, InputError, UnsupportedVersionError
from sinewatch.schemas.frame import (
    FRAME_BINARY_ENCODING,
    FRAME_BINARY_ENCODING_V2,
    FRAME_HEADER,
    FRAME_JSON_ENCODING,
    FRAME_JSON_ENCODING_V2,
    FRAME_MAGIC,
    Frame,
    channel_key,
    decode_frame,
    decode_input,
    encode_frame_binary,
    encode_frame_json,
    frame_encoding,
)
from sinewatch.schemas.input_record import decode_input_record, encode_frame_record, encode_input_record

FS = 10_000.0
N = 256
STEP_NS = round(N * 1e9 / FS)


def _signal(seq: int, n_ch: int, n: int = N) -> np.ndarray:
    """(n, n_ch): channel c a (50 + c) Hz sine with a little seeded noise, continuous over seq."""
    t = (seq * n + np.arange(n)) / FS
    noise = np.random.default_rng(seq).standard_normal((n, n_ch))
    return np.stack([np.sin(2 * np.pi * (50 + c) * t + 0.3 * c) for c in range(n_ch)], axis=1) + 0.01 * noise


# ---- the bytes --------------------------------------------------------------------------------
def test_the_binary_frame_is_the_byte_table_and_numpy_alone_reads_it():
    x = np.arange(6, dtype=np.float64).reshape(3, 2) / 4  # samples s0c0, s0c1, s1c0, ...
    frame = Frame(("mu1/ia", "mu1/va"), 7, -5, 4000.0, x)
    payload = encode_frame_binary(frame, "float32")
    names = b"mu1/ia\nmu1/va\n"  # 14 bytes: the samples start at 40 + 14 -> 56
    expected = (
        b"SWFR"
        + bytes([1, 1])  # format_version 1, dtype float32
        + struct.pack("<H", 2)  # n_channels
        + struct.pack("<Q", 7)
        + struct.pack("<q", -5)
        + struct.pack("<d", 4000.0)
        + struct.pack("<I", 3)  # n_samples
        + struct.pack("<I", len(names))
        + names
        + b"\0\0"  # pad to offset 56
        + struct.pack("<6f", 0.0, 0.25, 0.5, 0.75, 1.0, 1.25)
    )
    assert payload == expected
    assert len(encode_frame_binary(frame, "float64")) == 56 + 6 * 8
    # the reader in the byte table's docstring, numpy and struct only
    p = payload
    c, (n, names_len) = struct.unpack_from("<H", p, 6)[0], struct.unpack_from("<II", p, 32)
    got_names = p[40 : 40 + names_len].decode().split("\n")[:-1]
    got = np.frombuffer(p, "<f4", offset=(40 + names_len + 7) // 8 * 8).reshape(n, c)
    assert got_names == ["mu1/ia", "mu1/va"] and np.array_equal(got, x)
    back = decode_frame(payload, FRAME_BINARY_ENCODING)
    assert (back.channels, back.seq, back.t0_ns, back.sample_rate_hz) == (frame.channels, 7, -5, 4000.0)
    assert np.array_equal(back.samples, x)
    j = decode_input(encode_frame_json(frame), FRAME_JSON_ENCODING)
    assert isinstance(j, Frame) and j.channels == frame.channels and np.array_equal(j.samples, x)
    assert isinstance(decode_input(encode_frame_json(frame)), Frame)  # sniffed without an encoding


def _good() -> bytearray:
    """A valid frame whose 9 bytes of names leave a 7-byte pad before the samples (at 56)."""
    frame = Frame(("a/xy", "a/z"), 1, 0, 1000.0, np.ones((4, 2)))
    return bytearray(encode_frame_binary(frame, "float64"))


def _good_v2() -> bytearray:
    """The same frame with a time quality (global): format version 2, names at 44, pad to 56."""
    frame = Frame(("a/xy", "a/z"), 1, 0, 1000.0, np.ones((4, 2)), time_quality_byte("global"))
    return bytearray(encode_frame_binary(frame, "float64"))


def _raw_names(names: bytes, n_ch: int) -> bytes:
    """A frame of one sample per channel with these name bytes, as written by hand."""
    head = FRAME_HEADER.pack(b"SWFR", 1, 2, n_ch, 0, 0, 1000.0, 1, len(names))
    return head + names + b"\0" * ((-(len(head) + len(names))) % 8) + b"\0" * 8 * n_ch


def _set(data: bytearray, fmt: str, offset: int, value) -> bytes:
    struct.pack_into(fmt, data, offset, value)
    return bytes(data)


MALFORMED = {
    "empty": (b"", "", DecodeError),
    "truncated header": (bytes(_good()[:30]), FRAME_BINARY_ENCODING, DecodeError),
    "bad magic": (_set(_good(), "<4s", 0, b"SWFX"), FRAME_BINARY_ENCODING, DecodeError),
    "unknown version": (_set(_good(), "<B", 4, 3), "", UnsupportedVersionError),
    "version in the encoding": (bytes(_good()), "application/x-sinewatch-frame;v=3", UnsupportedVersionError),
    "encoding's version not the header's": (bytes(_good()), "application/x-sinewatch-frame;v=2", DecodeError),
    "unknown dtype": (_set(_good(), "<B", 5, 9), "", DecodeError),
    "no channels": (_set(_good(), "<H", 6, 0), "", DecodeError),
    "channel count above the names": (_set(_good(), "<H", 6, 3), "", DecodeError),
    "samples cut short": (bytes(_good()[:-8]), "", DecodeError),
    "samples too long": (bytes(_good()) + b"\0" * 8, "", DecodeError),
    "n_samples lies": (_set(_good(), "<I", 32, 5), "", DecodeError),
    "names_len lies": (_set(_good(), "<I", 36, 12), "", DecodeError),
    "non-zero pad": (_set(_good(), "<B", 40 + 9, 1), "", DecodeError),
    "names without their last newline": (_raw_names(b"a/x\na/y", 2), "", DecodeError),
    "name not UTF-8": (_set(_good(), "<B", 40, 0xFF), "", DecodeError),
    "name not a channel name": (_set(_good(), "<B", 41, ord(" ")), "", DecodeError),
    "repeated name": (_raw_names(b"a/x\na/x\n", 2), "", DecodeError),
    "zero sample rate": (_set(_good(), "<d", 24, 0.0), "", DecodeError),
    "NaN sample rate": (_set(_good(), "<d", 24, float("nan")), "", DecodeError),
    "JSON not JSON": (b"{not json", FRAME_JSON_ENCODING, DecodeError),
    "JSON ragged rows": (
        b'{"seq":0,"t0_ns":0,"sample_rate_hz":1.0,"channels":["a","b"],"samples":[[1,2],[3]]}',
        FRAME_JSON_ENCODING,
        DecodeError,
    ),
    "JSON repeated channel": (
        b'{"seq":0,"t0_ns":0,"sample_rate_hz":1.0,"channels":["a","a"],"samples":[[1,2]]}',
        "",
        DecodeError,
    ),
    "JSON version": (
        b'{"format_version":3,"seq":0,"t0_ns":0,"sample_rate_hz":1.0,"channels":["a"],"samples":[[1]]}',
        "",
        UnsupportedVersionError,
    ),
    # format version 2: the time-quality byte at 40, reserved bytes 41-43
    "version 2 header cut short": (bytes(_good_v2()[:42]), "", DecodeError),
    "time quality sync 3": (_set(_good_v2(), "<B", 40, 0x83), "", DecodeError),
    "time quality without its stated bit": (_set(_good_v2(), "<B", 40, 0x02), "", DecodeError),
    "time quality reserved bit": (_set(_good_v2(), "<B", 40, 0x8A), "", DecodeError),
    "reserved byte 41": (_set(_good_v2(), "<B", 41, 1), "", DecodeError),
    "reserved bytes 42-43": (_set(_good_v2(), "<H", 42, 0x100), "", DecodeError),
    "version 2 pad": (_set(_good_v2(), "<B", 44 + 9, 1), "", DecodeError),
    "version 2 payload, version 1 encoding": (bytes(_good_v2()), FRAME_BINARY_ENCODING, DecodeError),
    "JSON time quality in a version 1 frame": (
        b'{"format_version":1,"seq":0,"t0_ns":0,"sample_rate_hz":1.0,"channels":["a"],"samples":[[1]],'
        b'"time_quality":{"sync":"global","holdover":false}}',
        "",
        DecodeError,
    ),
    "JSON unknown sync": (
        b'{"format_version":2,"seq":0,"t0_ns":0,"sample_rate_hz":1.0,"channels":["a"],"samples":[[1]],'
        b'"time_quality":{"sync":"utc"}}',
        "",
        DecodeError,
    ),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_every_malformed_frame_is_a_typed_decode_error_saying_what_was_expected(case):
    payload, encoding, error = MALFORMED[case]
    with pytest.raises(error) as info:
        decode_input(payload, encoding)
    assert isinstance(info.value, ValueError) and "expected" in str(info.value)


def test_every_frame_recorded_as_an_input_frame_gives_back_its_bytes():
    """The InputFrame record (a well-formed binary frame as fields, anything else raw) gives
    back every payload byte for byte: well-formed frames of 1-4 channels (every pad length),
    float32 and float64, a NaN sample rate with payload bits, an unknown version; and the
    same frames damaged (a byte flipped, cut, lengthened, a pad byte set), the malformed
    frames above and JSON frames."""
    rng = np.random.default_rng(2808)
    payloads = [p for p, _, _ in MALFORMED.values()]
    for n_ch in range(1, 5):
        for dtype in ("float32", "float64"):
            names = tuple(f"m/{'x' * (c + n_ch)}{c}" for c in range(n_ch))
            frame = Frame(names, int(rng.integers(2**63)), -(10**18), 4000.0, rng.standard_normal((3, n_ch)))
            good = encode_frame_binary(frame, dtype)
            record = encode_frame_record(good, FRAME_BINARY_ENCODING)
            assert FRAME_MAGIC not in record and len(record) < len(good) + 40 + 8 * n_ch  # as fields
            payloads += [good, encode_frame_json(frame), good[:-1], good + b"\0", _set(bytearray(good), "<B", 4, 2)]
            frame.time_quality = time_quality_byte("local", holdover=n_ch % 2 == 1)
            v2 = encode_frame_binary(frame, dtype)
            payloads += [
                v2,
                encode_frame_json(frame),
                _set(bytearray(v2), "<B", 41, 1),
                _set(bytearray(v2), "<B", 4, 1),
            ]
            frame.time_quality = 0
            payloads.append(_set(bytearray(good), "<Q", 24, 0x7FF0_0000_0000_0001))  # a signalling NaN's bits
            for _ in range(40):
                damaged = bytearray(good)
                damaged[int(rng.integers(len(good)))] ^= 1 << int(rng.integers(8))
                payloads.append(bytes(damaged))
            pad = 40 + len("".join(f"{c}\n" for c in names))
            if pad % 8:
                payloads.append(good[:pad] + b"\1" + good[pad + 1 :])
    for payload in payloads:
        for encoding in ("", FRAME_BINARY_ENCODING, FRAME_JSON_ENCODING):
            assert decode_input_record(encode_frame_record(payload, encoding)) == (payload, encoding)


# every stated time quality: (sync, holdover) -> the byte of the table in sinewatch.schemas.codec
QUALITIES = {(s, h): 0x80 | (0x04 if h else 0) | code for code, s in enumerate(SYNC_NAMES) for h in (False, True)}


@pytest.mark.parametrize(("sync", "holdover"), list(QUALITIES))
def test_a_frame_with_a_time_quality_is_version_2_s_byte_table_and_decodes_back(sync, holdover):
    byte = QUALITIES[(sync, holdover)]
    assert time_quality_byte(sync, holdover) == byte
    x = np.arange(6, dtype=np.float64).reshape(3, 2) / 4
    frame = Frame(("mu1/ia", "mu1/va"), 7, -5, 4000.0, x, byte)
    payload = encode_frame_binary(frame, "float32")
    names = b"mu1/ia\nmu1/va\n"  # 14 bytes at 44: the samples start at 58 -> 64
    expected = (
        b"SWFR"
        + bytes([2, 1])  # format_version 2, dtype float32
        + struct.pack("<HQqdII", 2, 7, -5, 4000.0, 3, len(names))
        + bytes([byte, 0, 0, 0])  # time_quality, reserved u8, reserved u16
        + names
        + b"\0" * 6  # pad to offset 64
        + struct.pack("<6f", 0.0, 0.25, 0.5, 0.75, 1.0, 1.25)
    )
    assert payload == expected
    # the docstring's reader: the version byte says where the names start
    p = payload
    head = 44 if p[4] == 2 else 40
    c, (n, names_len) = struct.unpack_from("<H", p, 6)[0], struct.unpack_from("<II", p, 32)
    got = np.frombuffer(p, "<f4", offset=(head + names_len + 7) // 8 * 8).reshape(n, c)
    assert p[head : head + names_len] == names and np.array_equal(got, x)
    for dtype in ("float32", "float64"):
        wire = encode_frame_binary(frame, dtype)
        back = decode_frame(wire, FRAME_BINARY_ENCODING_V2)
        assert back.time_quality == byte and back.version == 2 and np.array_equal(back.samples, x)
        assert decode_input(wire).time_quality == byte  # sniffed without an encoding
        # the InputFrame record: fields (field 17 the byte), and the payload back byte for byte
        record = encode_frame_record(wire, FRAME_BINARY_ENCODING_V2)
        # field 17's key (17 << 3 | varint: 0x88 0x01) and the byte as a varint (two bytes: >= 0x80)
        assert FRAME_MAGIC not in record and record.endswith(bytes([0x88, 0x01, (byte & 0x7F) | 0x80, byte >> 7]))
        assert decode_input_record(record) == (wire, FRAME_BINARY_ENCODING_V2)
    assert frame_encoding(frame) == FRAME_BINARY_ENCODING_V2 and frame_encoding(frame, False) == FRAME_JSON_ENCODING_V2
    j = encode_frame_json(frame)
    msg = json.loads(j)
    assert msg["format_version"] == 2 and msg["time_quality"] == {"sync": sync, "holdover": holdover}
    back = decode_input(j, FRAME_JSON_ENCODING_V2)
    assert back.time_quality == byte and np.array_equal(back.samples, x)
    # each channel's block carries it: what the pipeline hands each estimate
    assert {frame.block(k).time_quality for k in range(2)} == {byte}


def test_a_frame_without_a_time_quality_stays_version_1_byte_for_byte():
    x = np.arange(6, dtype=np.float64).reshape(3, 2)
    frame = Frame(("mu1/ia", "mu1/va"), 7, -5, 4000.0, x)  # time_quality 0: not stated
    assert frame.version == 1 and frame_encoding(frame) == FRAME_BINARY_ENCODING
    payload = encode_frame_binary(frame)
    assert payload[4] == 1 and payload[40:54] == b"mu1/ia\nmu1/va\n"
    assert decode_frame(payload, FRAME_BINARY_ENCODING).time_quality == 0
    assert (
        "time_quality" not in json.loads(encode_frame_json(frame))
        and json.loads(encode_frame_json(frame))["format_version"] == 1
    )


@pytest.mark.parametrize("byte", [0, *QUALITIES.values()])
def test_a_binary_block_s_flags_byte_carries_the_time_quality(byte):
    block = Block("daq/v", 3, 10**18, 10_000.0, np.arange(4.0), "V", byte)
    payload = encode_block_binary(block)
    assert payload[7] == byte  # the flags byte, reserved (0) before
    assert decode_block(payload).time_quality == byte
    record = encode_input_record(payload, "application/x-sinewatch-block;v=1")
    assert decode_input_record(record) == (payload, "application/x-sinewatch-block;v=1")
    assert decode_block(encode_block_json(block)).time_quality == 0  # JSON blocks do not state it


@pytest.mark.parametrize("flags", [0x01, 0x40, 0x83, 0x88, 0xFF])
def test_a_binary_block_with_flags_that_are_no_time_quality_is_a_decode_error(flags):
    payload = bytearray(encode_block_binary(Block("daq/v", 3, 0, 10_000.0, np.arange(4.0))))
    payload[7] = flags
    with pytest.raises(DecodeError, match=r"expected 0 \(time quality not stated\)"):
        decode_block(bytes(payload))


def test_a_frame_s_channel_keys_sit_beside_the_frame_key():
    assert channel_key("sinewatch/in/mu1", "mu1/ia") == "sinewatch/in/mu1/ia"
    with pytest.raises(DecodeError, match="two chunks"):
        channel_key("mu1", "mu1/ia")


# ---- the pipeline ----------------------------------------------------------------------------
class Keep(NullSink):
    def __init__(self) -> None:
        self.estimates: dict[str, list[bytes]] = {}
        self.errors: list[dict] = []
        self.inputs: list[tuple[str, str]] = []

    def on_input(self, key, payload, encoding, log_time_ns):
        self.inputs.append((key, encoding))

    def on_estimate(self, key, payload, log_time_ns):
        self.estimates.setdefault(key, []).append(payload)

    def on_error(self, key, payload, log_time_ns):
        self.errors.append(json.loads(payload))


def _frame(names, seq, x, fs=FS) -> bytes:
    return encode_frame_binary(Frame(tuple(names), seq, seq * STEP_NS, fs, x), "float32")


def _blocks_reference(tmp_path: Path, sends: list[tuple[str, int, np.ndarray]]) -> dict[str, list[bytes]]:
    """What single blocks give: (channel, seq, samples) each sent alone, float32 as the frames."""
    keep = Keep()
    p = Pipeline(make_config(tmp_path, hold_estimates=False), [keep])
    for name, seq, x in sends:
        payload = encode_block_binary(Block(name, seq, seq * STEP_NS, FS, x), "float32")
        p.process(f"sinewatch/in/{name}", payload, "", seq)
    return keep.estimates


def test_each_channel_of_a_frame_gets_the_bits_its_own_blocks_would_give(tmp_path):
    names = [f"daq/ch{c}" for c in range(5)]
    keep = Keep()
    p = Pipeline(make_config(tmp_path, hold_estimates=False, rules=_two_rules()), [keep])
    sends = []
    for seq in range(8):
        x = _signal(seq, 5)
        p.process("sinewatch/in/daq", _frame(names, seq, x), FRAME_BINARY_ENCODING, seq)
        sends += [(name, seq, x[:, c]) for c, name in enumerate(names)]
    assert not keep.errors
    assert keep.inputs == [("sinewatch/in/daq", FRAME_BINARY_ENCODING)] * 8  # recorded whole, once each
    reference = _blocks_reference_rules(tmp_path, sends)
    assert keep.estimates == reference and len(reference) == 5
    assert {json.loads(v[0])["estimator"] for v in keep.estimates.values()} == {"ges-kalman", "sogi-fll"}
    assert p.counters.inputs == 8 and p.counters.estimates == 40
    assert [s["blocks"] for s in p.channel_status()] == [8] * 5


def test_every_estimate_of_a_frame_s_channels_carries_the_frame_s_time_quality(tmp_path):
    """Frames of a merging unit that is synchronised globally, loses it, holds over and is
    never stated: each estimate (Estimate format 5) carries its own frame's time quality, as
    the byte said, and nothing else of it changes: the values are the bits a frame without
    a time quality gives."""
    names = [f"daq/ch{c}" for c in range(3)]
    stated = (
        [QUALITIES[("global", False)]] * 3 + [QUALITIES[("none", True)]] * 2 + [0] * 2 + [QUALITIES[("local", False)]]
    )
    keep, plain = Keep(), Keep()
    p = Pipeline(make_config(tmp_path, hold_estimates=False), [keep])
    q = Pipeline(make_config(tmp_path, hold_estimates=False), [plain])
    for seq, tq in enumerate(stated):
        frame = Frame(tuple(names), seq, seq * STEP_NS, FS, _signal(seq, 3), tq)
        p.process("sinewatch/in/daq", encode_frame_binary(frame, "float32"), frame_encoding(frame), seq)
        frame.time_quality = 0
        q.process("sinewatch/in/daq", encode_frame_binary(frame, "float32"), FRAME_BINARY_ENCODING, seq)
    assert not keep.errors and len(keep.estimates) == 3
    for key, payloads in keep.estimates.items():
        msgs = [json.loads(b) for b in payloads]
        assert [m["format_version"] for m in msgs] == [5] * len(stated)
        assert [json.dumps(m["time_quality"], separators=(",", ":")) for m in msgs] == [
            TIME_QUALITY_JSON[tq] for tq in stated
        ]
        assert msgs[3]["time_quality"] == {"sync": "none", "holdover": True} and msgs[5]["time_quality"] is None
        # the rest of every estimate is what the same frames without a time quality gave
        for m, ref in zip(msgs, plain.estimates[key], strict=True):
            r = json.loads(ref)
            assert {k: v for k, v in m.items() if k != "time_quality"} == {
                k: v for k, v in r.items() if k != "time_quality"
            }


def _two_rules() -> list[EstimatorRule]:
    """Two banks in one frame: even channels on one rule, the others on another."""
    from sinewatch.scenarios.demo import KALMAN_10K

    return [
        EstimatorRule(match="sinewatch/in/daq/ch1", estimator="sogi-fll", params={}),
        EstimatorRule(match="sinewatch/in/daq/ch3", estimator="sogi-fll", params={}),
        EstimatorRule(match="sinewatch/in/**", estimator="ges-kalman", params=KALMAN_10K),
    ]


def _blocks_reference_rules(tmp_path, sends):
    keep = Keep()
    p = Pipeline(make_config(tmp_path, hold_estimates=False, rules=_two_rules()), [keep])
    for name, seq, x in sends:
        payload = encode_block_binary(Block(name, seq, seq * STEP_NS, FS, x), "float32")
        p.process(f"sinewatch/in/{name}", payload, "", seq)
    return keep.estimates


def test_one_nan_column_is_that_channel_s_error_and_the_others_are_estimated(tmp_path):
    names = ["daq/a", "daq/b", "daq/c"]
    keep = Keep()
    p = Pipeline(make_config(tmp_path, hold_estimates=False), [keep])
    sends = []
    for seq in range(4):
        x = _signal(seq, 3)
        if seq == 2:
            x[100, 1] = np.nan
        p.process("sinewatch/in/daq", _frame(names, seq, x), "", seq)
        sends += [(n, seq, x[:, c]) for c, n in enumerate(names) if not (seq == 2 and c == 1)]
    assert [(e["kind"], e["key"], e["channel"], e["seq"]) for e in keep.errors] == [
        ("non_finite", "sinewatch/in/daq/b", "daq/b", 2)
    ]
    assert p.counters.by_kind == {"non_finite": 1}
    assert {s["channel"]: s["errors"] for s in p.channel_status()} == {"daq/a": 0, "daq/b": 1, "daq/c": 0}
    assert {k: len(v) for k, v in keep.estimates.items()} == {
        "sinewatch/est/daq/a": 4,
        "sinewatch/est/daq/b": 3,
        "sinewatch/est/daq/c": 4,
    }
    # the rejected column never reached b's estimator: the same bits as blocks without it
    assert keep.estimates == _blocks_reference(tmp_path, sends)


def test_a_frame_whose_channel_set_changes_mid_stream(tmp_path):
    """The rule: each channel is followed as if its column were sent alone with the frame's
    seq. A channel left out of frames 2 and 3 comes back flagged as a gap of 2 blocks; a
    channel that first appears in frame 3 starts afresh; the order of the columns may
    change; the others go on untouched."""
    keep = Keep()
    p = Pipeline(make_config(tmp_path, hold_estimates=False), [keep])
    layouts = {
        0: ["daq/a", "daq/b"],
        1: ["daq/a", "daq/b"],
        2: ["daq/a"],
        3: ["daq/new", "daq/a"],
        4: ["daq/b", "daq/a", "daq/new"],
    }
    sends = []
    for seq, names in layouts.items():
        x = _signal(seq, len(names))
        p.process("sinewatch/in/daq", _frame(names, seq, x), "", seq)
        sends += [(n, seq, x[:, c]) for c, n in enumerate(names)]
    assert not keep.errors
    b = [json.loads(e)["diagnostics"] for e in keep.estimates["sinewatch/est/daq/b"]]
    assert [(d["gap"], d["gap_blocks"]) for d in b] == [(False, 0), (False, 0), (True, 2)]
    new = [json.loads(e) for e in keep.estimates["sinewatch/est/daq/new"]]
    assert [e["seq"] for e in new] == [3, 4] and not any(e["diagnostics"]["gap"] for e in new)
    assert all(not json.loads(e)["diagnostics"]["gap"] for e in keep.estimates["sinewatch/est/daq/a"])
    assert keep.estimates == _blocks_reference(tmp_path, sends)


def test_a_lost_frame_and_its_late_redelivery_cost_one_refusal_per_channel_and_no_cascade(tmp_path):
    """Frames 0..9 of 4 channels with frame 3 lost, then frame 3 and an older cache of
    frames 0..5 arriving again after frame 6 (what a recovery that re-sends a publisher's
    cache delivers), stamped as the bench's held-back feeder stamps them (a quarter period
    late, then on time). Frame 4 is accepted as a gap of one block, every re-delivered
    channel-block is refused once (out of order or duplicate), and every frame after them is
    accepted: one lost frame cannot make the daemon refuse what follows."""
    keep = Keep()
    p = Pipeline(make_config(tmp_path, hold_estimates=False), [keep])
    names = ["mu/a", "mu/b", "mu/c", "mu/d"]
    late = {4, 5, 8}  # stamped a quarter period after their time (stamp_ns's cap)

    def send(seq: int) -> None:
        t0 = seq * STEP_NS + (STEP_NS // 4 if seq in late else 0)
        frame = Frame(tuple(names), seq, t0, FS, _signal(seq, 4))
        p.process("sinewatch/in/mu", encode_frame_binary(frame, "float32"), "", seq)

    for seq in (0, 1, 2, 4, 5, 6):
        send(seq)
    for seq in (3, 0, 1, 2, 3, 4, 5, 6):  # the lost one late, then a cache re-sent
        send(seq)
    for seq in (7, 8, 9):
        send(seq)
    refused = sorted((e["channel"], e["seq"], e["kind"]) for e in keep.errors)
    assert refused == sorted(
        (n, seq, "duplicate" if seq == 6 else "out_of_order") for n in names for seq in (3, 0, 1, 2, 3, 4, 5, 6)
    )
    for n in names:
        got = [json.loads(e) for e in keep.estimates[f"sinewatch/est/{n}"]]
        assert [e["seq"] for e in got] == [0, 1, 2, 4, 5, 6, 7, 8, 9]
        assert [e["diagnostics"]["gap_blocks"] for e in got] == [0, 0, 0, 1, 0, 0, 0, 0, 0]
        assert not any(e["diagnostics"]["reset"] for e in got)


def test_a_frame_channel_whose_rule_needs_two_columns_is_rejected_alone(tmp_path):
    rules = [
        EstimatorRule(
            match="sinewatch/in/daq/iq",
            estimator="differential-rls",
            params={"input": "iq", "nominal_frequency_hz": 0.0},
        ),
        *make_config(tmp_path, hold_estimates=False).rules,
    ]
    keep = Keep()
    p = Pipeline(make_config(tmp_path, hold_estimates=False, rules=rules), [keep])
    p.process("sinewatch/in/daq", _frame(["daq/iq", "daq/v"], 0, _signal(0, 2)), "", 0)
    assert [(e["kind"], e["channel"]) for e in keep.errors] == [("shape_mismatch", "daq/iq")]
    assert list(keep.estimates) == ["sinewatch/est/daq/v"]


def test_a_frame_on_a_one_chunk_key_or_with_bad_bytes_is_one_decode_error(tmp_path):
    keep = Keep()
    p = Pipeline(make_config(tmp_path, rules=[EstimatorRule(match="**", estimator="ipdft")]), [keep])
    p.process("daq", _frame(["a"], 0, _signal(0, 1)), "", 0)
    p.process("sinewatch/in/daq", _frame(["a"], 0, _signal(0, 1))[:-4], "", 0)
    assert [e["kind"] for e in keep.errors] == ["decode_error", "decode_error"]
    assert not keep.estimates


# ---- a real daemon ---------------------------------------------------------------------------------
def test_a_daemon_fed_frames_and_single_blocks_at_once_records_what_replays_bit_for_bit(tmp_path):
    """Real Zenoh on loopback, real MCAP: a 3-channel frame stream (with a NaN column in
    frame 3 and channel c missing from frame 5) beside a channel sent as single blocks.
    Every estimate arrives, the NaN column is c's error only, the recording holds one
    message per frame, replays bit for bit and exports each channel's samples."""
    config = make_config(tmp_path)
    names = ["mu1/a", "mu1/b", "mu1/c"]
    n_frames = 8
    frames = []
    for seq in range(n_frames):
        x = _signal(seq, 3)
        if seq == 3:
            x[10, 1] = np.nan
        cols = [0, 1] if seq == 5 else [0, 1, 2]
        frames.append(Frame(tuple(names[c] for c in cols), seq, 10**18 + seq * STEP_NS, FS, x[:, cols]))
    expected_estimates = sum(f.n_channels for f in frames) - 1 + n_frames  # one NaN column; the solo channel

    def client(_daemon, ep):
        with connect([ep]) as s:
            est = subscribe_estimates(s)
            err = subscribe_errors(s)
            status = subscribe_status(s)
            pub = BlockPublisher(s, dtype="float64")
            assert pub.wait_for_frame_subscriber("mu1", 20) and pub.wait_for_subscriber("solo", 20)
            # The daemon's inputs are subscribed; its outputs reach this session only once the
            # daemon has this session's subscriptions. They arrive over one link in the order
            # declared: a Status received proves the estimates' and errors' ones (declared
            # before it) are there too, so no estimate can go out to nobody.
            assert status.get(timeout=20) is not None
            status.close()
            for seq, frame in enumerate(frames):
                pub.publish_frame_raw("mu1", encode_frame_binary(frame))
                pub.publish("solo", _signal(seq, 1)[:, 0], FS)
            got = take(est, expected_estimates)
            return got, take(err, 1)

    (got, errors), _daemon, code = run_daemon(config, client)
    assert code == 0 and len(got) == expected_estimates
    by_channel: dict[str, list[int]] = {}
    for e in got:
        by_channel.setdefault(e["channel"], []).append(e["seq"])
    assert {k: sorted(v) for k, v in by_channel.items()} == {
        "mu1/a": list(range(8)),
        "mu1/b": [0, 1, 2, 4, 5, 6, 7],
        "mu1/c": [0, 1, 2, 3, 4, 6, 7],
        "solo": list(range(8)),
    }
    assert [(e["kind"], e["channel"], e["seq"]) for e in errors] == [("non_finite", "mu1/b", 3)]
    [mcap] = list((tmp_path / "rec").glob("*.mcap"))
    inputs = [m for kind, m in read_recording(mcap) if kind == "message" and m.role == "input"]
    assert sorted({m.topic for m in inputs}) == ["sinewatch/in/mu1", "sinewatch/in/solo"]
    assert sum(m.topic == "sinewatch/in/mu1" for m in inputs) == n_frames  # one MCAP message a frame
    result = replay([mcap])
    assert result.ok and result.matched == expected_estimates == result.recorded_estimates
    (tmp_path / "export").mkdir()
    out = export(mcap, tmp_path / "export", samples=True, channels="mu1/*")
    [samples_csv] = [p for p in out.paths if ".samples." in p.name]
    with open(samples_csv) as f:
        rows = list(csv.DictReader(f))
    per_channel: dict[str, int] = {}
    for row in rows:
        per_channel[row["channel"]] = per_channel.get(row["channel"], 0) + 1
    assert per_channel == {"mu1/a": 8 * N, "mu1/b": 8 * N, "mu1/c": 7 * N}
    a_rows = [r for r in rows if r["channel"] == "mu1/a" and r["seq"] == "2"]
    assert [float(r["value"]) for r in a_rows] == frames[2].samples[:, 0].tolist()


def test_typed_errors_stay_value_errors():
    assert issubclass(DecodeError, InputError) and issubclass(DecodeError, ValueError)


def test_feed_sends_its_scenarios_as_frames_and_every_channel_is_estimated(tmp_path):
    """``Feed(frame_channels=3)`` (``sinewatch feed --frame-channels 3``) over real Zenoh:
    five channels go as a frame of three and a frame of two, each channel estimated on its
    own key as if it had been fed alone."""
    from sinewatch.apps.feed import Feed, make_channels, rules_for

    channels = make_channels(["demo-ramp"], copies=5, seed=3)
    config = make_config(tmp_path, rules=rules_for(channels))

    def client(_daemon, ep):
        with connect([ep]) as s:
            est = subscribe_estimates(s)
            pub = BlockPublisher(s)
            feed = Feed(pub, channels, block_size=500, realtime=False, frame_channels=3)
            assert [(name, len(m)) for name, m in feed.frames] == [("sim-f0", 3), ("sim-f1", 2)]
            assert pub.wait_for_frame_subscriber("sim-f0", 20)
            sent = feed.run(0.5)
            return sent, take(est, 5 * 10)

    (sent, got), _daemon, code = run_daemon(config, client)
    assert code == 0 and sent == 2 * 10
    assert sorted({e["channel"] for e in got}) == [f"sim/demo-ramp/{c}" for c in range(5)]
    assert all(sorted(e["seq"] for e in got if e["channel"] == ch.channel) == list(range(10)) for ch in channels)
    [mcap] = list((tmp_path / "rec").glob("*.mcap"))
    assert replay([mcap]).ok


def test_feed_comtrade_as_frames_gives_the_estimates_of_its_blocks(tmp_path):
    """``feed --comtrade --frame-channels 8``: the record's three analog channels (one rate
    segment) go as one frame per block, and the estimates are those the same record fed as
    blocks gives (test_comtrade), bit for bit: the frame path changes no bits."""
    from conftest import serve_comtrade
    from test_comtrade import PHASES, check_estimates, write_comtrade

    cfg = write_comtrade(tmp_path, "1999", "BINARY")
    results = {}
    for frame_channels in ("1", "8"):
        feed_err, estimates = serve_comtrade(
            tmp_path, cfg, "--frame-channels", frame_channels, name=f"daemon{frame_channels}"
        )
        results[frame_channels] = (feed_err, sorted(estimates, key=lambda e: (e["channel"], e["seq"])))
    assert "published 4 frames (12000 samples) on 3 channels" in results["8"][0]
    check_estimates(results["8"][1], [f"comtrade/SUB-STATION-1/{k}" for k in PHASES])
    assert results["8"][1] == results["1"][1]


def test_a_frame_of_the_three_phases_feeds_the_three_phase_stage_directly(tmp_path):
    """The three phases of a power-quality group in one frame: every ThreePhaseReport comes
    out while that frame is processed (all three phases at one time, nothing waiting for
    another message to line up), within IEC 61000-4-30 class A of the scenario's truth,
    and the stage's outputs are byte for byte those of the same phases sent as blocks."""
    from test_pq_service import BLOCK, T0_NS, Outputs, check_accuracy, phase_blocks, pq_config

    rounds, names = phase_blocks(36)
    config = pq_config(tmp_path, names)
    as_frames, as_blocks = Outputs(), Outputs()
    frames, blocks = Pipeline(config, [as_frames]), Pipeline(config, [as_blocks])
    for i, blks in enumerate(rounds):
        x = np.stack([b.samples for b in blks], axis=1)
        before = sum(kind == "ThreePhaseReport" for kind, _, _ in as_frames.out)
        frames.process(
            "sinewatch/in/pq-f0", encode_frame_binary(Frame(tuple(names), i, blks[0].t0_ns, 10_000.0, x)), "", 0
        )
        reports = [json.loads(p) for kind, _, p in as_frames.out if kind == "ThreePhaseReport"][before:]
        assert [r["timestamp_ns"] for r in reports] == [T0_NS + i * BLOCK * 100_000 + (BLOCK - 1) * 100_000]
        for b in blks:
            blocks.process(f"sinewatch/in/{b.channel}", encode_block_binary(b), "", 0)
    assert as_frames.out == as_blocks.out
    check_accuracy([(kind, key, json.loads(p)) for kind, key, p in as_frames.out], names)


def test_the_intake_queue_counts_a_frame_as_its_channels(tmp_path):
    """``limits.queue_capacity`` counts blocks: a frame of 8 channels takes 8 places, so a
    backlog of frames holds no more samples than one of blocks (drop policy here: the frame
    that does not fit is dropped whole and gives its partial room back)."""
    import threading
    from collections import Counter

    from sinewatch.runtime.daemon import Intake, IntakeCounters

    intake = Intake.__new__(Intake)  # its queue logic only: no session, no thread
    intake._capacity, intake._policy = 10, "drop"
    intake._room = threading.Semaphore(10)
    intake.counters = IntakeCounters()
    frame8 = _frame([f"d/{c}" for c in range(8)], 0, _signal(0, 8))
    block = encode_block_binary(Block("d/x", 0, 0, FS, np.zeros(4)))
    dropped: Counter[str] = Counter()
    assert intake.weight(frame8) == 8 and intake.weight(block) == 1
    assert intake._admit(("sinewatch/in/d", frame8, "", 0), dropped)
    assert not intake._admit(("sinewatch/in/d", frame8, "", 0), dropped)  # 2 places left, 8 needed
    assert dropped == {"sinewatch/in/d": 1} and intake.counters.dropped == 1
    assert intake._admit(("sinewatch/in/x", block, "", 0), dropped)
    assert intake._admit(("sinewatch/in/x", block, "", 0), dropped)  # the dropped frame's room came back
    assert not intake._admit(("sinewatch/in/x", block, "", 0), dropped)
    intake.release(intake.weight(frame8))
    assert intake._admit(("sinewatch/in/d", frame8, "", 0), dropped)


def test_foxglove_summarises_each_readable_channel_of_a_frame():
    pytest.importorskip("foxglove")
    from sinewatch.outputs.foxglove_live import summaries

    x = _signal(0, 3)
    x[5, 1] = np.inf
    msgs = summaries(_frame(["daq/a", "daq/b", "daq/c"], 0, x), FRAME_BINARY_ENCODING, 64)
    assert [m["channel"] for m in msgs] == ["daq/a", "daq/c"]  # b's block is rejected by the pipeline too
    a = x[:, 0].astype(np.float32).astype(np.float64)
    assert msgs[0]["n_samples"] == N and msgs[0]["max"] == float(a.max()) and len(msgs[0]["samples"]) == 64
    with pytest.raises(InputError):
        summaries(_frame(["daq/a"], 0, np.full((4, 1), np.nan)), "", 64)


def test_refused_columns_of_frames_leave_the_channel_slots_free(tmp_path):
    """As for blocks: a channel whose first column is refused (NaN) gives its slot back, so
    frames of NaN columns on ever new names cannot use up ``limits.max_channels``."""
    from sinewatch.schemas.config import LimitsSection

    keep = Keep()
    p = Pipeline(make_config(tmp_path, hold_estimates=False, limits=LimitsSection(max_channels=6)), [keep])
    for i in range(5):  # 20 hostile channels, 4 a frame, beside one good channel
        x = _signal(i, 5)
        x[3, 1:] = np.nan
        names = ["good/a", *(f"hostile/{i}/{c}" for c in range(4))]
        p.process("sinewatch/in/f", _frame(names, i, x), "", i)
    assert len(keep.errors) == 20 and {e["kind"] for e in keep.errors} == {"non_finite"}
    assert list(p.channels) == ["good/a"] and len(keep.estimates["sinewatch/est/good/a"]) == 5
