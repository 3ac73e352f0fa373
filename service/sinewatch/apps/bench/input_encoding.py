"""What recording an input costs in each well-known MCAP encoding: size and write cost.

``python -m sinewatch.apps.bench.input_encoding [--blocks N] [--block SAMPLES] [--repeats R]``
(``make bench-input-encoding``) takes N realistic binary input blocks (a 50 Hz sine with
noise, float64, SAMPLES samples each, 10 kHz) and turns each into the record the recorder
would write, per encoding, interleaved R times, best of the repeats:

* ``raw``: the payload as received (what builds before InputBlock recorded: no schema a
  standard reader knows); the baseline;
* ``protobuf``: :func:`sinewatch.schemas.input_record.encode_input_record`, the recorder's
  own (fields, the samples copied as packed doubles);
* ``jsonschema``: the same fields as a JSON object, samples as JSON numbers (``json.dumps``
  of the decoded block, as a writer that wants the samples readable must);
* ``flatbuffer``: the same fields as a FlatBuffers table, samples as a ``[double]`` vector
  (``flatbuffers.Builder``, when the ``flatbuffers`` package is installed).

It prints one JSON line per encoding: bytes per record, bytes per record after zstd (level
3, as the recorder's chunks; all N records together), microseconds to build a record, and
ratios to ``raw`` measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zstandard

from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, Block, decode_block, encode_block_binary
from sinewatch.schemas.input_record import encode_input_record

FS = 10_000.0


def blocks(n: int, size: int) -> list[bytes]:
    """n consecutive binary blocks of a 50 Hz, 1.5 V sine with 1 % noise (seeded)."""
    rng = np.random.default_rng(1)
    out = []
    for i in range(n):
        k = np.arange(i * size, (i + 1) * size)
        x = 1.5 * np.sin(2 * np.pi * 50.0 * k / FS) + 0.015 * rng.standard_normal(size)
        out.append(encode_block_binary(Block("bench/v", i, 1_763_900_000_000_000_000 + i * 10**8, FS, x, "V")))
    return out


def as_json(payload: bytes) -> bytes:
    b = decode_block(payload, BLOCK_BINARY_ENCODING)
    sec, nsec = divmod(b.t0_ns, 1_000_000_000)
    msg = {
        "zenoh_encoding": BLOCK_BINARY_ENCODING,
        "channel": b.channel,
        "seq": b.seq,
        "t0_ns": b.t0_ns,
        "timestamp": {"sec": sec, "nsec": nsec},
        "sample_rate_hz": b.sample_rate_hz,
        "columns": b.columns,
        "n_samples": b.n_samples,
        "unit": b.unit,
        "samples": b.samples.tolist(),
    }
    return json.dumps(msg, separators=(",", ":")).encode()


def flatbuffer_encoder() -> Callable[[bytes], bytes] | None:
    try:
        import flatbuffers  # an optional measurement: not a dependency of sinewatch
    except ImportError:
        return None

    def encode(payload: bytes) -> bytes:
        b = decode_block(payload, BLOCK_BINARY_ENCODING)
        fb: Any = flatbuffers.Builder(len(payload) + 256)
        enc, ch, unit = (fb.CreateString(s) for s in (BLOCK_BINARY_ENCODING, b.channel, b.unit or ""))
        samples = fb.CreateNumpyVector(b.samples)
        fb.StartObject(8)
        fb.PrependUOffsetTRelativeSlot(0, enc, 0)
        fb.PrependUOffsetTRelativeSlot(1, ch, 0)
        fb.PrependUint64Slot(2, b.seq, 0)
        fb.PrependInt64Slot(3, b.t0_ns, 0)
        fb.PrependFloat64Slot(4, b.sample_rate_hz, 0.0)
        fb.PrependUint32Slot(5, b.n_samples, 0)
        fb.PrependUOffsetTRelativeSlot(6, unit, 0)
        fb.PrependUOffsetTRelativeSlot(7, samples, 0)
        fb.Finish(fb.EndObject())
        return bytes(fb.Output())

    return encode


def measure(payloads: list[bytes], encode: Callable[[bytes], bytes]) -> tuple[float, list[bytes]]:
    """Seconds for one pass over the payloads, and the records."""
    t = time.perf_counter()
    records = [encode(p) for p in payloads]
    return time.perf_counter() - t, records


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", type=int, default=500)
    ap.add_argument("--block", type=int, default=1024, help="samples per block")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    payloads = blocks(args.blocks, args.block)
    encoders: dict[str, Callable[[bytes], bytes]] = {
        "raw": bytes,
        "protobuf": lambda p: encode_input_record(p, BLOCK_BINARY_ENCODING),
        "jsonschema": as_json,
    }
    fb = flatbuffer_encoder()
    if fb is not None:
        encoders["flatbuffer"] = fb
    best = dict.fromkeys(encoders, float("inf"))
    records: dict[str, list[bytes]] = {}
    for _ in range(args.repeats):  # interleaved: a load change hits every encoding alike
        for name, encode in encoders.items():
            seconds, records[name] = measure(payloads, encode)
            best[name] = min(best[name], seconds)
    zstd = zstandard.ZstdCompressor(level=3)
    raw_size = sum(map(len, records["raw"])) / args.blocks
    for name in encoders:
        size = sum(map(len, records[name])) / args.blocks
        zsize = len(zstd.compress(b"".join(records[name]))) / args.blocks
        us = best[name] / args.blocks * 1e6
        line = {
            "encoding": name,
            "block_samples": args.block,
            "bytes": round(size),
            "bytes_zstd": round(zsize),
            "us_per_record": round(us, 2),
            "size_vs_raw": round(size / raw_size, 3),
            "us_minus_raw": round(us - best["raw"] / args.blocks * 1e6, 2),
        }
        print(json.dumps(line))
    if fb is None:
        print(json.dumps({"encoding": "flatbuffer", "skipped": "the flatbuffers package is not installed"}))


if __name__ == "__main__":
    main()
