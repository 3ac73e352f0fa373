"""Codec and schemas: bytes on the wire, both encodings, versioning, exported schemas."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sinewatch.estimators import available
from sinewatch.schemas.codec import (
    BLOCK_BINARY_ENCODING,
    BLOCK_JSON_ENCODING,
    ESTIMATE_JSON_ENCODING,
    Block,
    decode_block,
    encode_block_binary,
    encode_block_json,
    encode_estimate,
)
from sinewatch.schemas.errors import DecodeError, UnsupportedVersionError
from sinewatch.schemas.export import all_schemas
from sinewatch.schemas.messages import Diagnostics, Estimate, Fencing, TimeQuality, Uncertainty

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("columns", [1, 3])
def test_binary_round_trip(dtype, columns):
    rng = np.random.default_rng(3)
    x = rng.standard_normal((257, columns) if columns > 1 else 257).astype(dtype)
    blk = Block("feeder1/phase-a", 2**63 + 5, -(2**62), 12_345.5, x, "V")
    out = decode_block(encode_block_binary(blk, dtype), BLOCK_BINARY_ENCODING)
    assert (out.channel, out.seq, out.t0_ns, out.sample_rate_hz, out.unit) == (
        "feeder1/phase-a",
        2**63 + 5,
        -(2**62),
        12_345.5,
        "V",
    )
    assert out.samples.dtype == np.dtype(dtype) and out.samples.shape == x.shape
    np.testing.assert_array_equal(out.samples, x)


def test_json_round_trip_and_sniffing():
    x = np.array([[0.5, 1.0], [-0.25, 2.0]])
    blk = Block("a", 3, 10, 1000.0, x)
    payload = encode_block_json(blk)
    for enc in (BLOCK_JSON_ENCODING, "zenoh/bytes", ""):
        out = decode_block(payload, enc)
        np.testing.assert_array_equal(out.samples, x)
    assert decode_block(encode_block_binary(Block("a", 0, 0, 1.0, np.ones(2))), "zenoh/bytes").n_samples == 2


def test_a_c_gateway_can_write_the_json_by_hand():
    payload = b'{"channel":"gw/1","seq":0,"t0_ns":0,"sample_rate_hz":50.0,"samples":[1,2,3]}'
    out = decode_block(payload, "application/json")
    assert out.samples.tolist() == [1.0, 2.0, 3.0] and out.channel == "gw/1"


@pytest.mark.parametrize(
    "payload, encoding, error, match",
    [
        (b"SWSB\x02" + bytes(35), BLOCK_BINARY_ENCODING, UnsupportedVersionError, "expected 1, got 2"),
        (b"x" * 50, "application/x-sinewatch-block;v=2", UnsupportedVersionError, "got 2"),
        (b'{"format_version": 7}', BLOCK_JSON_ENCODING, UnsupportedVersionError, "got 7"),
        (b"{not json", BLOCK_JSON_ENCODING, DecodeError, "not valid JSON"),
        (b'{"channel":"bad channel!","seq":0,"t0_ns":0,"sample_rate_hz":1,"samples":[1]}', "", DecodeError, "channel"),
        (b'{"channel":"a","seq":-1,"t0_ns":0,"sample_rate_hz":1,"samples":[1]}', "", DecodeError, "seq"),
        (b'{"channel":"a","seq":0,"t0_ns":0,"sample_rate_hz":0,"samples":[1]}', "", DecodeError, "sample_rate"),
        (b'{"channel":"a","seq":0,"t0_ns":0,"sample_rate_hz":1,"samples":[1],"extra":1}', "", DecodeError, "extra"),
        (b"\x89PNG....", "image/png", DecodeError, "encoding"),
    ],
)
def test_bad_payloads_raise_typed_errors(payload, encoding, error, match):
    with pytest.raises(error, match=match) as info:
        decode_block(payload, encoding)
    assert isinstance(info.value, ValueError)


def test_binary_length_and_dtype_are_checked():
    raw = bytearray(encode_block_binary(Block("a", 0, 0, 1.0, np.ones(4))))
    with pytest.raises(DecodeError, match="length"):
        decode_block(bytes(raw) + b"\0", BLOCK_BINARY_ENCODING)
    raw[5] = 7
    with pytest.raises(DecodeError, match="dtype"):
        decode_block(bytes(raw), BLOCK_BINARY_ENCODING)


@pytest.mark.parametrize("channel", ["a/b\n", "a\n", "a/b\r", "\na", "a//b", "a/b/"])
def test_channel_names_are_checked_to_the_last_character(channel):
    # The binary path checks names with Python's re, where "$" also matches before a final
    # newline: "a/b\n" was accepted there (and refused by the JSON path), a second channel
    # that prints like the first.
    good = bytearray(encode_block_binary(Block("a" * len(channel), 0, 0, 1.0, np.ones(4))))
    at = bytes(good).index(b"a" * len(channel))
    good[at : at + len(channel)] = channel.encode()
    with pytest.raises(DecodeError, match="channel"):
        decode_block(bytes(good), BLOCK_BINARY_ENCODING)


def test_committed_json_schemas_are_up_to_date():
    # `make schemas` regenerates schemas/sinewatch/schemas/json from the models; a stale copy fails here.
    for rel, schema in all_schemas(available()).items():
        path = REPO / "schemas" / "sinewatch" / "schemas" / "json" / rel
        assert path.exists(), f"{path} missing: run `make schemas`"
        assert json.loads(path.read_text()) == schema, f"{path} is stale: run `make schemas`"


def _estimate(**over):
    fields = dict(
        channel="a/b",
        seq=3,
        timestamp_ns=1_700_000_000_000_000_000,
        n_samples=10,
        estimator="x",
        frequency_hz=[50.0],
        amplitude=[1.0],
        phase_rad=[0.25],
        offset=None,
        diagnostics=Diagnostics(converged=True, residual_rms=0.01, extras={"k": 1.5}),
    )
    fields.update(over)
    return Estimate(**fields)


def test_estimate_v3_carries_rocof_uncertainty_time_and_validity_and_earlier_versions_are_their_bytes():
    est = _estimate(
        rocof_hz_per_s=[0.5],
        std=Uncertainty(frequency_hz=[0.001], amplitude=[None], phase_rad=[0.01], offset=None),
    )
    v5 = json.loads(encode_estimate(est))
    assert v5["format_version"] == 5 and v5["time_quality"] is None and list(v5)[-1] == "time_quality"
    stated = est.model_copy(update={"time_quality": TimeQuality(sync="none", holdover=True)})
    assert json.loads(encode_estimate(stated))["time_quality"] == {"sync": "none", "holdover": True}
    assert Estimate.model_validate(json.loads(encode_estimate(stated))) == stated
    v4 = json.loads(encode_estimate(stated, version=4))
    assert "time_quality" not in v4  # version 4 is what the builds before the time quality wrote
    assert v4["format_version"] == 4 and v4["fencing"] is None  # a daemon that owns its keys without an election
    fenced = json.loads(encode_estimate(est.model_copy(update={"fencing": Fencing(shard="s", term=7)}), version=4))
    assert fenced["fencing"] == {"shard": "s", "term": 7} and list(fenced)[-1] == "fencing"
    v3 = json.loads(encode_estimate(est, version=3))
    assert "fencing" not in v3  # version 3 is what the builds before fencing wrote
    assert v3["format_version"] == 3 and v3["rocof_hz_per_s"] == [0.5] and v3["std"]["frequency_hz"] == [0.001]
    assert v3["diagnostics"]["valid"] is True
    assert Estimate.model_validate(v4) == est.model_copy(update={"format_version": 4})
    # Version 2 and 1 are what earlier builds wrote: the same keys in the same order, nothing more.
    v2 = encode_estimate(est, version=2)
    assert v2 == (
        b'{"format_version":2,"channel":"a/b","seq":3,"timestamp_ns":1700000000000000000,"n_samples":10,'
        b'"estimator":"x","frequency_hz":[50.0],"amplitude":[1.0],"phase_rad":[0.25],"offset":null,'
        b'"rocof_hz_per_s":[0.5],"std":{"frequency_hz":[0.001],"amplitude":[null],"phase_rad":[0.01],'
        b'"offset":null},"diagnostics":{"converged":true,"residual_rms":0.01,"gap":false,"gap_blocks":0,'
        b'"restart":false,"reset":false,"extras":{"k":1.5}}}'
    )
    v1 = encode_estimate(est, version=1)
    assert v1 == (
        b'{"format_version":1,"channel":"a/b","seq":3,"timestamp_ns":1700000000000000000,"n_samples":10,'
        b'"estimator":"x","frequency_hz":[50.0],"amplitude":[1.0],"phase_rad":[0.25],"offset":null,'
        b'"diagnostics":{"converged":true,"residual_rms":0.01,"gap":false,"gap_blocks":0,"restart":false,'
        b'"reset":false,"extras":{"k":1.5}}}'
    )
    assert ESTIMATE_JSON_ENCODING.endswith("@5")


@pytest.mark.parametrize("ns", [1_763_900_000_123_456_789, 2**63 - 1, -1, -(2**63), 0])
def test_estimate_time_is_exact_where_javascript_numbers_are_not(ns):
    """timestamp_ns beyond 2^53 loses digits in a JavaScript number (a float64); its
    {sec, nsec} twin does not: both parts are exact floats and recombine to the integer."""
    msg = json.loads(encode_estimate(_estimate(timestamp_ns=ns)))
    sec, nsec = msg["timestamp"]["sec"], msg["timestamp"]["nsec"]
    assert 0 <= nsec < 10**9 and abs(sec) < 2**53
    assert int(float(sec)) * 10**9 + int(float(nsec)) == ns
    if ns == 1_763_900_000_123_456_789:  # a time of today, in ns: not a float64 (JavaScript number)
        assert int(float(ns)) != ns


def test_estimate_time_must_agree_with_timestamp_ns():
    with pytest.raises(ValueError, match=r"expected \{sec, nsec\} equal to"):
        _estimate(timestamp={"sec": 1, "nsec": 0})
