"""``sinewatch bench kernels``: samples/s per core for every registered estimator.

Each estimator runs in its example configuration through its public ``update`` (so the
thin class's per-block overhead is included), emitting one estimate per block
(``last_only``) and, separately, the full per-sample track; on one channel and on 64
channels (64 instances updated in turn).

Two baselines are measured in the same run, both numpy 1024-point Hann-windowed rfft
frames with hop 256:

* ``fft-stream``: an FFT front end fed the same blocks as the estimators (it keeps the
  last 768 samples, frames each block with them, windows into a preallocated buffer and
  transforms): the like-for-like baseline, used for the ``ratio`` columns;
* ``fft-batch``: the same transform over one long signal at once, with no per-block
  overhead: the best numpy can do, shown for context (``vs batch``).

``--bank N`` (default 8) adds each estimator's bank (:func:`sinewatch.estimators.bank.update_bank`:
the N channels of a frame, each with its own signal, advanced by one call), per sample of every
channel. Its ``ratio`` (to the streaming FFT) and ``x 1 ch`` (to the same estimator one channel
at a time) are medians of paired rounds, the three measured in turn seven times, so that both
sides of each ratio see the same load from other processes; an estimator whose bank stays below
twice the streaming FFT says why under the table. The run names the CPU the kernels were compiled
for and its widest vector of doubles (:func:`sinewatch.estimators.lanes.host_vector_bits`): a
lane-major bank's 8 lanes are one vector with AVX-512 and two without, which moves its ratios.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from rich.table import Table

from sinewatch.apps.console import make_console, print_table
from sinewatch.estimators import available, get
from sinewatch.estimators.bank import NO_BANK, BankKernel, bank_of, update_bank
from sinewatch.estimators.base import Estimator
from sinewatch.estimators.lanes import LANES, host_vector_bits

FFT_SIZE = 1024
FFT_HOP = 256
BANK_TARGET = 2.0  # a bank's rate per sample against the streaming FFT's that needs no note


def _rate(fn: Callable[[], int], seconds: float, repeats: int = 3) -> float:
    """Median samples/s of ``fn`` (which returns the samples it processed) over repeats, per
    second of this thread's CPU time (``time.thread_time``): the rate of one core, which a
    process elsewhere on the machine does not lower (by wall time, the same build's ratio to the
    FFT moved by +-6 % between runs here). Everything timed runs on the calling thread: numpy's
    FFT and the kernels start no threads."""
    fn()  # warm-up: compile, caches
    rates = []
    for _ in range(repeats):
        n = 0
        t0 = time.thread_time()
        while True:
            n += fn()
            dt = time.thread_time() - t0
            if dt >= seconds / repeats:
                break
        rates.append(n / dt)
    return statistics.median(rates)


def fft_batch_baseline(seconds: float) -> float:
    """Samples/s of 1024-point Hann rfft frames, hop 256, over one long signal."""
    x = np.random.default_rng(0).standard_normal(1 << 16)
    window = np.hanning(FFT_SIZE)
    frames = np.lib.stride_tricks.sliding_window_view(x, FFT_SIZE)[::FFT_HOP]
    buf = np.empty(frames.shape)

    def run() -> int:
        np.multiply(frames, window, out=buf)
        np.fft.rfft(buf, axis=1)
        return int(frames.shape[0]) * FFT_HOP  # new samples consumed

    return _rate(run, seconds)


def fft_stream_baseline(block: int, seconds: float) -> float:
    """Samples/s of the same transform as a streaming front end fed ``block``-sample blocks."""
    return _rate(fft_stream_runner(block), seconds)


def fft_stream_runner(block: int) -> Callable[[], int]:
    """One block of the streaming FFT front end per call (returns the samples consumed)."""
    n_blocks = 16
    x = np.random.default_rng(0).standard_normal(block * n_blocks)
    blocks = [x[i * block : (i + 1) * block] for i in range(n_blocks)]
    window = np.hanning(FFT_SIZE)
    keep = FFT_SIZE - FFT_HOP
    tail = np.zeros(keep)
    i = 0
    buf = np.empty(((keep + block - FFT_SIZE) // FFT_HOP + 1, FFT_SIZE))

    def run() -> int:
        nonlocal tail, i
        seg = np.concatenate((tail, blocks[i % n_blocks]))
        i += 1
        frames = np.lib.stride_tricks.sliding_window_view(seg, FFT_SIZE)[::FFT_HOP]
        np.multiply(frames, window, out=buf[: frames.shape[0]])
        np.fft.rfft(buf[: frames.shape[0]], axis=1)
        tail = seg[-keep:]
        return block

    return run


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

            def run(ests: list[Estimator] = ests, last_only: bool = last_only, state: dict[str, int] = state) -> int:
                b = blocks[state["i"] % n_blocks]
                state["i"] += 1
                for est in ests:
                    est.update(b, last_only=last_only)
                return block * len(ests)

            mode = "per_block" if last_only else "per_sample"
            out[f"{channels}ch_{mode}"] = _rate(run, seconds)
    return out


def bank_rates(name: str, block: int, bank: int, seconds: float, repeats: int = 7) -> dict[str, float]:
    """The bank of ``bank`` channels (each with its own signal, advanced together by
    :func:`update_bank`, one estimate per block and channel), the same estimator one channel at a
    time and the streaming FFT, measured in turn ``repeats`` times: samples/s of each (every
    channel's samples; medians), and the medians of the ratios of each round (bank / FFT,
    bank / one channel). Paired rounds: on a machine whose other load changes from second to
    second, the two sides of a ratio see the same load. A compiled bank's kernel is also timed
    alone in the same rounds (``kernel``, ``kernel_vs_fft``: the same frames and stacked states,
    no Python around the call), which tells what bounds a bank below the target: its arithmetic,
    or :func:`update_bank`'s gathering, checks and Tracks around it."""
    cls = get(name)
    n_blocks = 16
    x = np.stack([cls.example_signal(block * n_blocks, seed=1 + c) for c in range(bank)], axis=1)
    frames = [np.ascontiguousarray(x[i * block : (i + 1) * block]) for i in range(n_blocks)]
    blocks = [np.ascontiguousarray(f[:, 0]) for f in frames]
    banked = [cls.example() for _ in range(bank)]
    single = cls.example()
    state = {"bank": 0, "single": 0, "kernel": 0}

    def run_bank() -> int:
        update_bank(banked, frames[state["bank"] % n_blocks], last_only=True)
        state["bank"] += 1
        return block * bank

    def run_single() -> int:
        single.update(blocks[state["single"] % n_blocks], last_only=True)
        state["single"] += 1
        return block

    fns = [fft_stream_runner(block), run_single, run_bank]
    compiled = bank_of(cls)
    if compiled is not None and compiled.run is None:  # a kernel called as update_bank calls it
        fns.append(_kernel_runner(compiled, banked, frames, state))
    rounds = [[_rate(fn, seconds / (len(fns) * repeats), repeats=1) for fn in fns] for _ in range(repeats)]
    rates = {
        "fft_stream": statistics.median(r[0] for r in rounds),
        "single": statistics.median(r[1] for r in rounds),
        "bank": statistics.median(r[2] for r in rounds),
        "bank_vs_fft": statistics.median(r[2] / r[0] for r in rounds),
        "bank_vs_single": statistics.median(r[2] / r[1] for r in rounds),
        "single_vs_fft": statistics.median(r[1] / r[0] for r in rounds),
    }
    if len(fns) == 4:
        rates["kernel"] = statistics.median(r[3] for r in rounds)
        rates["kernel_vs_fft"] = statistics.median(r[3] / r[0] for r in rounds)
    return rates


def _kernel_runner(
    compiled: BankKernel, ests: list[Estimator], frames: list[np.ndarray], state: dict[str, int]
) -> Callable[[], int]:
    """One frame through a compiled bank's kernel alone per call, from the channels' states
    stacked as :func:`update_bank` stacks them, each call from the states the last returned (as
    update_bank's channels advance: ges-kalman's start covariance, for one, is propagated only
    in its first thousands of samples); returns the samples of every channel."""
    first = ests[0]
    stacked = [np.array([e._state[k] for e in ests]) for k in first._state]
    # channel last, as the lane-major kernels take their states
    stacked = [np.ascontiguousarray(np.moveaxis(a, 0, -1)) for a in stacked]
    inputs = frames

    def run() -> int:
        x = inputs[state["kernel"] % len(inputs)]
        stacked[:] = compiled.kernel(x, *stacked, *first._constants, True)[compiled.n_outputs :]
        state["kernel"] += 1
        return int(x.size)

    return run


def bank_why(name: str, rates: dict[str, float]) -> str:
    """Why ``name``'s bank stays below the target: the estimator's own reason
    (:data:`NO_BANK` or its ``bank_note``), then, for a compiled kernel, the measured split of a
    channel-sample's time between the kernel alone and the Python around it."""
    why = NO_BANK.get(name) or getattr(get(name), "bank_note", None) or "(no reason given)"
    if "kernel" not in rates:
        return why
    k_ns, b_ns = 1e9 / rates["kernel"], 1e9 / rates["bank"]
    return (
        f"{why}. Measured in this run: the kernel alone {k_ns:.1f} ns a channel-sample "
        f"({rates['kernel_vs_fft']:.2f}x the streaming FFT), update_bank {b_ns:.1f} "
        f"(the Python around the call {b_ns - k_ns:.1f})"
    )


def run(args: argparse.Namespace) -> int:
    console = make_console()
    names = args.estimators.split(",") if args.estimators else list(available())
    blocks = args.block or [1024, 4096]
    batch = fft_batch_baseline(args.seconds)
    stream = {block: fft_stream_baseline(block, args.seconds) for block in blocks}
    console.print(
        f"FFT baselines (numpy, {FFT_SIZE}-point Hann rfft, hop {FFT_HOP}): batch "
        f"{batch / 1e6:.1f} M samples/s ({1e9 / batch:.1f} ns/sample); streaming, same blocks: "
        + ", ".join(f"{b}: {r / 1e6:.1f} M ({1e9 / r:.1f} ns/sample)" for b, r in stream.items())
    )
    cpu, bits = host_vector_bits()
    console.print(
        f"Kernels compiled for {cpu}: {bits}-bit vectors ({bits // 64} doubles), a lane-major bank's "
        f"{LANES} lanes {max(1, LANES * 64 // bits)} vector(s) a step"
    )
    results: dict[str, Any] = {
        "host": {"cpu": cpu, "vector_bits": bits},
        "fft_batch_samples_per_s": batch,
        "fft_stream_samples_per_s": {str(b): r for b, r in stream.items()},
        "estimators": {},
    }
    table = Table(title="samples/s per core; ratio = estimator / streaming FFT on the same blocks, same run")
    results["bank_channels"] = args.bank
    bank_ratios: dict[str, list[float]] = {}
    for col in (
        "estimator",
        "block",
        "1 ch, 1 est/block",
        "ratio",
        "vs batch",
        "64 ch, 1 est/block",
        "ratio",
        "1 ch, per-sample track",
        "ns/sample",
        f"bank {args.bank}, 1 est/block",
        "ratio",
        "x 1 ch",
        "ns/sample",
    ):
        table.add_column(col, justify="left" if col == "estimator" else "right")
    for name in names:
        for block in blocks:
            r = estimator_rates(name, block, args.seconds)
            b = bank_rates(name, block, args.bank, 2 * args.seconds)
            r.update({f"bank{args.bank}_{k}": v for k, v in b.items()})
            results["estimators"].setdefault(name, {})[str(block)] = r
            rb = b["bank"]
            bank_ratios.setdefault(name, []).append(b["bank_vs_fft"])
            table.add_row(
                name,
                str(block),
                f"{r['1ch_per_block'] / 1e6:.1f} M",
                f"{r['1ch_per_block'] / stream[block]:.2f}",
                f"{r['1ch_per_block'] / batch:.2f}",
                f"{r['64ch_per_block'] / 1e6:.1f} M",
                f"{r['64ch_per_block'] / stream[block]:.2f}",
                f"{r['1ch_per_sample'] / 1e6:.1f} M",
                f"{1e9 / r['1ch_per_block']:.1f}",
                f"{rb / 1e6:.1f} M",
                f"{b['bank_vs_fft']:.2f}",
                f"{b['bank_vs_single']:.2f}",
                f"{1e9 / rb:.1f}",
            )
    print_table(console, table)
    for name in names:  # an estimator that cannot reach the baseline says why
        note = getattr(get(name), "bench_note", None)
        if note:
            console.print(f"note: {note}")
    for name in names:  # and a bank below the target, why (measured at the first block size)
        if min(bank_ratios[name]) < BANK_TARGET:
            rates = results["estimators"][name][str(blocks[0])]
            why = bank_why(name, {k.removeprefix(f"bank{args.bank}_"): v for k, v in rates.items()})
            results.setdefault("why", {})[name] = why
            console.print(f"bank note: {name}'s bank {args.bank} is below {BANK_TARGET:g}x the streaming FFT: {why}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0
