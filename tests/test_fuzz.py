"""Fuzzing the inputs a daemon takes from the network and from its operator.

Properties, checked by Hypothesis with a fixed seed (the default run) and by a seeded
mutation fuzzer over a million payloads (``make test-slow``):

* the block and frame decoder raises nothing but an InputError, whatever the bytes;
* config loading (file and environment) raises nothing but a ConfigError;
* the pipeline's intake never raises, counts every input as one estimate or one
  ErrorReport (a multi-channel frame: one per channel), files each rejection under a known ``kind``, and never lets a bad payload
  touch an estimator: a clean channel fed between bad payloads gives bit-identical
  estimates to a run without them.
"""

from __future__ import annotations

import json
import random
import struct
from collections import Counter

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sinewatch.core.pipeline import NullSink, Pipeline
from sinewatch.schemas.codec import (
    BLOCK_BINARY_ENCODING,
    BLOCK_JSON_ENCODING,
    HEADER,
    MAGIC,
    Block,
    decode_block,
    encode_block_binary,
    encode_block_json,
)
from sinewatch.schemas.config import EstimatorRule, LimitsSection, SinewatchConfig, load_config
from sinewatch.schemas.errors import ConfigError, InputError
from sinewatch.schemas.frame import (
    FRAME_BINARY_ENCODING,
    FRAME_HEADER,
    FRAME_JSON_ENCODING,
    FRAME_MAGIC,
    Frame,
    channel_key,
    decode_input,
    encode_frame_binary,
    encode_frame_json,
)
from sinewatch.schemas.messages import ErrorKind

FUZZ = settings(max_examples=300, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ENCODINGS = [
    "",
    BLOCK_BINARY_ENCODING,
    BLOCK_JSON_ENCODING,
    "application/x-sinewatch-block;v=7",
    "zenoh/bytes",
    FRAME_BINARY_ENCODING,
    FRAME_JSON_ENCODING,
    "application/x-sinewatch-frame;v=9",
]
KINDS = {k.value for k in ErrorKind}

# ---- generators -------------------------------------------------------------------------------
json_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
)
json_values = st.recursive(
    json_scalars,
    lambda inner: st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=30,
)
block_fields = st.fixed_dictionaries(
    {},
    optional={
        "format_version": st.one_of(st.just(1), json_values),
        "channel": st.one_of(st.just("fz/a"), st.text(max_size=300), json_values),
        "seq": st.one_of(st.integers(min_value=-5, max_value=2**65), json_values),
        "t0_ns": st.one_of(st.integers(min_value=-(2**64), max_value=2**64), json_values),
        "sample_rate_hz": st.one_of(st.floats(), json_values),
        "dtype": st.one_of(st.sampled_from(["float32", "float64", "int8"]), json_values),
        "columns": st.one_of(st.integers(min_value=-2, max_value=300), json_values),
        "unit": st.one_of(st.none(), st.text(max_size=80), json_values),
        "samples": st.one_of(
            st.lists(st.floats(), max_size=20),
            st.lists(st.lists(st.floats(), max_size=4), max_size=10),
            json_values,
        ),
    },
)


VALID_JSON_BLOCK = {
    "format_version": 1,
    "channel": "fz/a",
    "seq": 1,
    "t0_ns": 0,
    "sample_rate_hz": 1000.0,
    "columns": 1,
    "samples": [0.5, -0.5, 1.0],
}


@st.composite
def near_valid_json_blocks(draw: st.DrawFn) -> bytes:
    """A valid JSON block with one to three fields replaced: the payloads that get past
    json.loads and most of the model, where decoder gaps hide."""
    msg = dict(VALID_JSON_BLOCK)
    fields = block_fields.filter(bool)
    for _ in range(draw(st.integers(0, 2))):
        msg.update(draw(fields))
    if draw(st.booleans()):  # rows of any widths, for any announced column count
        msg["samples"] = draw(st.lists(st.lists(st.floats(-1e3, 1e3), max_size=3), min_size=1, max_size=5))
        msg["columns"] = draw(st.integers(1, 3))
    nesting = draw(st.integers(0, 3))
    if nesting == 3:  # deep nesting inside an otherwise valid object
        msg["samples"] = json.loads("[" * 50 + "]" * 50)
        return json.dumps(msg).replace('"samples": ' + "[" * 50, '"samples": ' + "[" * 100_000, 1).encode()
    return json.dumps(msg).encode()


@st.composite
def binary_blocks(draw: st.DrawFn) -> bytes:
    """Headers with every field drawn (mostly nonsense), followed by random bytes."""
    header = HEADER.pack(
        draw(st.sampled_from([MAGIC, b"SWSB", b"XXXX"])),
        draw(st.integers(0, 255)),
        draw(st.integers(0, 255)),
        draw(st.integers(0, 255)),
        draw(st.integers(0, 255)),
        draw(st.integers(0, 2**64 - 1)),
        draw(st.integers(-(2**63), 2**63 - 1)),
        draw(st.floats(width=64)),
        draw(st.integers(0, 2**32 - 1)),
        draw(st.integers(0, 300)),
        draw(st.integers(0, 300)),
    )
    return header + draw(st.binary(max_size=400))


@st.composite
def binary_frames(draw: st.DrawFn) -> bytes:
    """Frame headers with every field drawn, names that may or may not fit, then random
    bytes or exactly the samples the header announces."""
    n_ch = draw(st.integers(0, 4))
    names = draw(
        st.one_of(
            st.just("".join(f"fz/c{c}\n" for c in range(n_ch)).encode()),
            st.binary(max_size=40),
            st.just(b"fz/a\nfz/a\n"),
        )
    )
    n = draw(st.integers(0, 6))
    version = draw(st.sampled_from([1, 1, 0, 2, 2, 255]))
    header = FRAME_HEADER.pack(
        draw(st.sampled_from([FRAME_MAGIC, b"XXXX"])),
        version,
        draw(st.sampled_from([1, 2, 0, 3])),
        n_ch,
        draw(st.integers(0, 2**64 - 1)),
        draw(st.integers(-(2**63), 2**63 - 1)),
        draw(st.floats(width=64)),
        draw(st.one_of(st.just(n), st.integers(0, 2**32 - 1))),
        draw(st.one_of(st.just(len(names)), st.integers(0, 2**32 - 1))),
    )
    if version == 2:  # the time-quality byte and the reserved bytes: valid, or any
        header += draw(
            st.one_of(st.sampled_from([b"\x82\0\0\0", b"\x84\0\0\0", b"\0\0\0\0"]), st.binary(min_size=4, max_size=4))
        )
    pad = b"\0" * ((-(len(header) + len(names))) % 8)
    tail = draw(st.one_of(st.just(b"\0" * (8 * n * n_ch)), st.binary(max_size=200)))
    return header + names + draw(st.sampled_from([pad, b"", b"\1" * len(pad)])) + tail


frame_fields = st.fixed_dictionaries(
    {},
    optional={
        "format_version": st.one_of(st.just(1), json_values),
        "channels": st.one_of(st.just(["fz/a", "fz/b"]), st.lists(st.text(max_size=8), max_size=3), json_values),
        "seq": st.one_of(st.integers(min_value=-5, max_value=2**65), json_values),
        "sample_rate_hz": st.one_of(st.floats(), json_values),
        "samples": st.one_of(st.lists(st.lists(st.floats(), max_size=3), max_size=5), json_values),
    },
)
VALID_JSON_FRAME = {
    "seq": 1,
    "t0_ns": 0,
    "sample_rate_hz": 1000.0,
    "channels": ["fz/a", "fz/b"],
    "samples": [[0.5, 1.0]],
}

payloads = st.one_of(
    st.binary(max_size=600),
    binary_blocks(),
    binary_frames(),
    frame_fields.map(lambda d: json.dumps({**VALID_JSON_FRAME, **d}).encode()),
    block_fields.map(lambda d: json.dumps(d).encode()),
    near_valid_json_blocks(),
    json_values.map(lambda v: json.dumps(v).encode()),
)


def _decode_or_reject(payload: bytes, encoding: str) -> None:
    for decode in (decode_block, decode_input):
        try:
            decode(payload, encoding)
        except InputError as exc:
            assert exc.kind in KINDS and str(exc)


def _outputs_of(key: str, payload: bytes, encoding: str) -> int:
    """How many estimates or ErrorReports an input must give: one per channel of a frame
    that decodes (on a key with a parent), else one."""
    try:
        decoded = decode_input(payload, encoding)
        if isinstance(decoded, Frame) and decoded.n_samples and len(payload) <= 1 << 20:
            channel_key(key, decoded.channels[0])
            return decoded.n_channels
    except InputError:
        pass
    return 1


# ---- the decoder --------------------------------------------------------------------------------
@FUZZ
@given(payload=payloads, encoding=st.sampled_from(ENCODINGS))
def test_the_decoder_raises_nothing_but_input_errors(payload, encoding):
    _decode_or_reject(payload, encoding)


# ---- config loading -----------------------------------------------------------------------------
toml_keys = st.sampled_from(["zenoh", "keys", "rules", "recording", "limits", "daemon_id", "on_gap", "x", "mode"])


@FUZZ
@given(
    doc=st.dictionaries(toml_keys, json_values, max_size=5),
    env=st.dictionaries(
        st.sampled_from(
            [
                "SINEWATCH__ZENOH__MODE",
                "SINEWATCH__LIMITS",
                "SINEWATCH__",
                "SINEWATCH____X",
                "SINEWATCH__RULES",
                "SINEWATCH__LIMITS__QUEUE_CAPACITY",
                "SINEWATCH__ZENOH__LISTEN__X",
            ]
        ),
        st.text(max_size=30),
        max_size=3,
    ),
)
def test_config_loading_raises_nothing_but_config_errors(tmp_path_factory, doc, env):
    path = tmp_path_factory.mktemp("cfg") / "c.json"
    path.write_text(json.dumps(doc))
    try:
        load_config(path, env)
    except ConfigError as exc:
        assert str(exc)


# ---- the pipeline's intake ----------------------------------------------------------------------
class _Keep(NullSink):
    def __init__(self) -> None:
        self.estimates: list[tuple[str, bytes]] = []
        self.errors: list[dict] = []

    def on_estimate(self, key, payload, log_time_ns):
        self.estimates.append((key, payload))

    def on_error(self, key, payload, log_time_ns):
        self.errors.append(json.loads(payload))


def _config() -> SinewatchConfig:
    return SinewatchConfig(
        rules=[EstimatorRule(match="sinewatch/in/**", estimator="ipdft", params={"window_cycles": 4})],
        limits=LimitsSection(max_block_samples=4096, max_channels=64),
        recording={"enabled": False},
    )


def _clean_blocks(n: int) -> list[bytes]:
    fs, size = 10_000.0, 250
    t = np.arange(n * size) / fs
    x = 0.2 + np.sin(2 * np.pi * 50.3 * t + 0.4)
    return [
        encode_block_binary(Block("clean", i, 1_000_000_000 + i * 25_000_000, fs, x[i * size : (i + 1) * size]))
        for i in range(n)
    ]


def _check_intake(bad: list[tuple[str, bytes, str]], clean: list[bytes]) -> Counter:
    """Interleave bad payloads (on any key) with a clean channel; return the kinds counted."""
    keep_dirty, keep_clean = _Keep(), _Keep()
    dirty, reference = Pipeline(_config(), [keep_dirty]), Pipeline(_config(), [keep_clean])
    per_clean = max(1, len(bad) // len(clean))
    inputs = outputs = 0
    for i, payload in enumerate(clean):
        for key, junk, enc in bad[i * per_clean : (i + 1) * per_clean]:
            dirty.process(key, junk, enc, 0)
            inputs += 1
            outputs += _outputs_of(key, junk, enc)
        dirty.process("sinewatch/in/clean", payload, BLOCK_BINARY_ENCODING, 0)
        reference.process("sinewatch/in/clean", payload, BLOCK_BINARY_ENCODING, 0)
        inputs += 1
        outputs += 1
    for key, junk, enc in bad[len(clean) * per_clean :]:
        dirty.process(key, junk, enc, 0)
        inputs += 1
        outputs += _outputs_of(key, junk, enc)
    dirty.release_held(0)  # the input's end: estimates held back for the presence detector come out
    reference.release_held(0)
    # every input (every channel of a frame) is one estimate or one error, each error under a known kind
    assert inputs == dirty.counters.inputs
    assert len(keep_dirty.estimates) + len(keep_dirty.errors) == outputs
    kinds = Counter(e["kind"] for e in keep_dirty.errors)
    assert set(kinds) <= KINDS and sum(kinds.values()) == dirty.counters.errors
    assert kinds == dirty.counters.by_kind
    # the clean channel's estimator never saw a bad payload
    clean_out = [p for k, p in keep_dirty.estimates if k.endswith("/clean")]
    assert clean_out == [p for _, p in keep_clean.estimates]
    return kinds


@settings(max_examples=40, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    bad=st.lists(
        st.tuples(
            st.sampled_from(["sinewatch/in/clean", "sinewatch/in/other", "sinewatch/in/x/y"]),
            payloads,
            st.sampled_from(ENCODINGS),
        ),
        min_size=1,
        max_size=30,
    )
)
def test_the_intake_counts_every_bad_payload_and_never_touches_a_clean_channel(bad):
    _check_intake(bad, _clean_blocks(6))


# ---- a million payloads (make test-slow) ------------------------------------------------------------
def _mutants(rng: random.Random, templates: list[bytes], n: int):
    """Seeded mutations of valid blocks: bit flips, byte overwrites, truncation, extension,
    splices of two blocks, and header fields set to extremes."""
    extremes = [0, 1, 255, 2**16 - 1, 2**32 - 1, 2**63 - 1, 2**64 - 1]
    for _ in range(n):
        data = bytearray(rng.choice(templates))
        op = rng.randrange(6)
        if op == 0:
            for _ in range(rng.randint(1, 8)):
                i = rng.randrange(len(data))
                data[i] ^= 1 << rng.randrange(8)
        elif op == 1:
            i = rng.randrange(len(data))
            data[i : i + 4] = bytes(rng.randrange(256) for _ in range(4))
        elif op == 2:
            del data[rng.randrange(len(data)) :]
        elif op == 3:
            data += bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
        elif op == 4:
            other = rng.choice(templates)
            data = data[: rng.randrange(len(data))] + other[rng.randrange(len(other)) :]
        elif data[:4] == FRAME_MAGIC:
            fmt, off = rng.choice([("<H", 6), ("<Q", 8), ("<d", 24), ("<I", 32), ("<I", 36)])
            value = rng.choice(extremes) if fmt != "<d" else rng.choice([0.0, -1.0, float("inf"), float("nan")])
            struct.pack_into(fmt, data, off, value % (2 ** (8 * struct.calcsize(fmt))) if fmt != "<d" else value)
        elif data[:4] == MAGIC:
            fmt, off = rng.choice([("<Q", 8), ("<q", 16), ("<d", 24), ("<I", 32), ("<H", 36), ("<H", 38)])
            value = rng.choice(extremes)
            if fmt == "<d":
                value = rng.choice([0.0, -1.0, float("inf"), float("nan"), 1e308])
            elif fmt == "<q":
                value = value % 2**63
            struct.pack_into(fmt, data, off, value % (2 ** (8 * struct.calcsize(fmt))) if fmt != "<d" else value)
        yield bytes(data)


def _templates() -> list[bytes]:
    rng = np.random.default_rng(16)
    blocks = [
        Block("fz/a", 3, 10**9, 1000.0, rng.standard_normal(16)),
        Block("fz/b", 4, -(10**9), 48_000.0, rng.standard_normal((8, 3)), "V"),
    ]
    frames = [
        Frame(("fz/a", "fz/b", "fz/c"), 3, 10**9, 1000.0, rng.standard_normal((16, 3))),
        Frame(("fz/d",), 0, 0, 48_000.0, rng.standard_normal((5, 1))),
    ]
    return (
        [encode_block_binary(b, d) for b in blocks for d in ("float32", "float64")]
        + [encode_block_json(b) for b in blocks]
        + [encode_frame_binary(f, d) for f in frames for d in ("float32", "float64")]
        + [encode_frame_json(f) for f in frames]
    )


@pytest.mark.slow
def test_a_million_mutated_payloads_through_the_decoder_and_the_intake():
    rng = random.Random(16)
    templates = _templates()
    n_decoder, n_intake = 800_000, 200_000
    for payload in _mutants(rng, templates, n_decoder):
        _decode_or_reject(payload, rng.choice(ENCODINGS))
    keys = ["sinewatch/in/clean", "sinewatch/in/fz/a", "sinewatch/in/fz/b"]
    bad = [(rng.choice(keys), p, rng.choice(ENCODINGS)) for p in _mutants(rng, templates, n_intake)]
    kinds = _check_intake(bad, _clean_blocks(400))
    print(f"\n{n_decoder + n_intake} payloads, 0 crashes; intake rejections by kind: {dict(kinds)}")
