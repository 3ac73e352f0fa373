"""``sinewatch bench recorder-compression``: what each compression of the MCAP recorder costs.

One chunk (``--chunk-bytes``, the recorder's 1 MiB by default) of what a daemon fed frames
records: float32 SampleFrames of ``--frame-channels`` channels x 1024 samples (a 50 Hz sine
with 1 % noise, seeded) and, after each frame, one Estimate's JSON per channel. Each way the
recorder can compress a chunk (none, lz4, zstd at level 1, the recorder's, and at level 3,
mcap's own) compresses the same chunk: CPU nanoseconds per recorded sample (the thread's CPU
time, fastest of ``--repeats``, the ways taking turns) and the bytes written, as a fraction
of the uncompressed chunk. Compression runs on the recorder's chunk thread, so its CPU is the
daemon's whichever thread pays it.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import numpy as np
from rich.table import Table

from sinewatch.apps.console import make_console, print_table
from sinewatch.outputs.recorder import RECORDING_ZSTD_LEVEL
from sinewatch.schemas.frame import Frame, encode_frame_binary

_ESTIMATE = {
    "format_version": 5,
    "channel": "bench/123",
    "seq": 123,
    "timestamp_ns": 1732680000123456789,
    "timestamp": {"sec": 1732680000, "nsec": 123456789},
    "n_samples": 1024,
    "estimator": "ges-kalman",
    "frequency_hz": [50.00012345678912],
    "amplitude": [0.9999876543210987],
    "phase_rad": [1.2345678901234567],
    "offset": -0.0001234567890123,
    "rocof_hz_per_s": None,
    "std": {
        "frequency_hz": [0.0012345678901234],
        "amplitude": [2.345678901234e-4],
        "phase_rad": [1.234e-4],
        "offset": 1.2e-5,
    },
    "diagnostics": {
        "converged": True,
        "valid": True,
        "residual_rms": 0.0099876543210987,
        "gap": False,
        "gap_blocks": 0,
        "restart": False,
        "reset": False,
        "extras": {},
    },
    "fencing": None,
    "time_quality": None,
}


def chunk(chunk_bytes: int, per_frame: int, block: int = 1024, rate: float = 10_000.0) -> tuple[bytes, int]:
    """The chunk's records' data (frames and estimates, as the recorder lays them one after
    the other) and the samples it holds."""
    rng = np.random.default_rng(0)
    estimate = json.dumps(_ESTIMATE, separators=(",", ":")).encode()
    t = np.arange(block) / rate
    out = bytearray()
    samples = k = 0
    while len(out) < chunk_bytes:
        phases = rng.uniform(0, 2 * np.pi, per_frame)
        cols = np.sin(2 * np.pi * 50.0 * (t[:, None] + k * block / rate) + phases) + 0.01 * rng.standard_normal(
            (block, per_frame)
        )
        names = tuple(f"c{i}" for i in range(per_frame))
        out += encode_frame_binary(Frame(names, k, k, rate, cols.astype(np.float32)), "float32")
        out += estimate * per_frame
        samples += per_frame * block
        k += 1
    return bytes(out), samples


def compressors() -> dict[str, Callable[[bytes], bytes]]:
    """The recorder's ways, with the very modules mcap's writer imports."""
    import lz4.frame  # type: ignore[import-untyped]
    import zstandard

    return {
        "none": bytes,
        "lz4": lz4.frame.compress,
        f"zstd level {RECORDING_ZSTD_LEVEL} (the recorder's)": zstandard.ZstdCompressor(
            level=RECORDING_ZSTD_LEVEL
        ).compress,
        "zstd level 3 (mcap's)": zstandard.ZstdCompressor(level=3).compress,
    }


def measure(chunk_bytes: int, per_frame: int, repeats: int) -> list[dict[str, float | str]]:
    data, samples = chunk(chunk_bytes, per_frame)
    ways = compressors()
    best = dict.fromkeys(ways, float("inf"))
    size = dict.fromkeys(ways, 0)
    for _ in range(repeats):
        for name, compress in ways.items():
            t0 = time.thread_time()
            out = compress(data)
            best[name] = min(best[name], time.thread_time() - t0)
            size[name] = len(out)
    base = best["zstd level 3 (mcap's)"]
    return [
        {
            "compression": name,
            "cpu_ns_per_sample": 1e9 * best[name] / samples,
            "cpu_vs_zstd3": best[name] / base,
            "bytes_fraction": size[name] / len(data),
        }
        for name in ways
    ]


def run(args: argparse.Namespace) -> int:
    rows = measure(args.chunk_bytes, args.frame_channels, args.repeats)
    table = Table(
        title=f"sinewatch bench recorder-compression --frame-channels {args.frame_channels} "
        f"(one {args.chunk_bytes} B chunk, fastest of {args.repeats})"
    )
    for col in ("compression", "CPU ns/sample", "CPU vs zstd 3", "bytes on file / uncompressed"):
        table.add_column(col)
    for r in rows:
        table.add_row(
            str(r["compression"]),
            f"{r['cpu_ns_per_sample']:.2f}",
            f"{r['cpu_vs_zstd3']:.2f}",
            f"{r['bytes_fraction']:.3f}",
        )
    print_table(make_console(), table)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0
