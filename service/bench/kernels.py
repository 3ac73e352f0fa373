"""``sinewatch bench kernels``: samples/s per core for every registered estimator.

Each estimator runs in its example configuration through its public ``update`` (so the
thin class's per-block overhead is included), emitting one estimate per block
(``last_only``) and, separately, the full per-sample track; on one channel and on 64
channels (64 instances updated in turn). The baseline is measured in the same run: a
numpy FFT front end of 1024-point Hann-windowed rfft frames with hop 256 (49 M samples/s
was measured here once; the ratio, not the absolute, is what is reported).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable

import numpy as np

from sinewatch.console import make_console
from rich.table import Table

from sinewatch.estimators import available, get

FFT_SIZE = 1024
FFT_HOP = 256


def _rate(fn: Callable[[], int], seconds: float, repeats: int = 3) -> float:
    """Median samples/s of ``fn`` (which returns the samples it processed) over repeats."""
    fn()  # warm-up: compile, caches
    rates = []
    for _ in range(repeats):
        n = 0
        t0 = time.perf_counter()
        while True:
            n += fn()
            dt = time.perf_counter() - t0
            if dt >= seconds / repeats:
                break
        rates.append(n / dt)
    return statistics.median(rates)


def fft_baseline(seconds: float) -> float:
    """Samples/s of a 1024-point Hann rfft with hop 256 over a long signal."""
    x = np.random.default_rng(0).standard_normal(1 << 16)
    window = np.hanning(FFT_SIZE)
    frames = np.lib.stride_tricks.sliding_window_view(x, FFT_SIZE)[::FFT_HOP]
    n_input = (frames.shape[0] - 1) * FFT_HOP + FFT_SIZE  # samples the frames cover

    def run() -> int:
        spectrum = np.fft.rfft(frames * window, axis=1)
        np.abs(spectrum, out=np.empty(spectrum.shape))
        return n_input - FFT_SIZE + FFT_HOP  # new samples consumed

    return _rate(run, seconds)


def estimator_rates(name: str, block: int, seconds: float) -> dict[str, float]:
    cls = get(name)
    n_blocks = 16
    signal = cls.example_signal(block * n_blocks, seed=1)
    blocks = [np.ascontiguousarray(signal[i * block : (i + 1) * block]) for i in range(n_blocks)]
    out: dict[str, float] = {}
    for channels in (1, 64):
        ests = [cls.example() for _ in range(channels)]
        for last_only in (True, False):
            state = {"i": 0}

            def run(ests=ests, last_only=last_only, state=state) -> int:
                b = blocks[state["i"] % n_blocks]
                state["i"] += 1
                for est in ests:
                    est.update(b, last_only=last_only)
                return block * len(ests)

            mode = "per_block" if last_only else "per_sample"
            out[f"{channels}ch_{mode}"] = _rate(run, seconds)
    return out


def run(args: argparse.Namespace) -> int:
    console = make_console()
    names = args.estimators.split(",") if args.estimators else list(available())
    blocks = args.block or [1024, 4096]
    baseline = fft_baseline(args.seconds)
    console.print(f"FFT baseline (numpy rfft, {FFT_SIZE}-point Hann, hop {FFT_HOP}): "
                  f"{baseline / 1e6:.1f} M samples/s ({1e9 / baseline:.1f} ns/sample)")
    results = {"fft_baseline_samples_per_s": baseline, "estimators": {}}
    table = Table(title="samples/s per core (ratio = estimator / FFT baseline, same run)")
    for col in ("estimator", "block", "1 ch, 1 est/block", "ratio", "64 ch, 1 est/block", "ratio",
                "1 ch, per-sample track", "ns/sample"):
        table.add_column(col, justify="left" if col == "estimator" else "right")
    for name in names:
        for block in blocks:
            r = estimator_rates(name, block, args.seconds)
            results["estimators"].setdefault(name, {})[str(block)] = r
            table.add_row(
                name, str(block),
                f"{r['1ch_per_block'] / 1e6:.1f} M", f"{r['1ch_per_block'] / baseline:.2f}",
                f"{r['64ch_per_block'] / 1e6:.1f} M", f"{r['64ch_per_block'] / baseline:.2f}",
                f"{r['1ch_per_sample'] / 1e6:.1f} M", f"{1e9 / r['1ch_per_block']:.1f}",
            )
    console.print(table)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0
