"""The ``sinewatch bench ...`` command line: every bench's arguments, and nothing heavy.

This module imports only the standard library, so that building the CLI parser (which
every ``sinewatch`` command does, ``sinewatch config show`` included) costs nothing; a
bench's own module (numpy, numba, scipy, the estimators, Zenoh) is imported when that bench
runs. Each bench module exposes ``run(args) -> exit code``.
"""

from __future__ import annotations

import argparse
import importlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

DEFAULT_TRIALS = 10  # Monte Carlo trials per noisy scenario (sinewatch bench accuracy)
QUICK_TRIALS = 3  # the same with --quick
STARTUP_RUNS = 15  # runs per command (sinewatch bench startup)


_MODULES = {"pipeline": "pipeline_cost"}  # bench name -> module, where they differ


def _runner(module: str) -> Callable[[argparse.Namespace], int]:
    """``run(args)`` of ``sinewatch.apps.bench.<module>``, imported when the bench runs."""

    def run(args: argparse.Namespace) -> int:
        fn: Callable[[argparse.Namespace], int] = importlib.import_module(f"sinewatch.apps.bench.{module}").run
        return fn(args)

    run.__name__ = f"run_{module}"
    return run


def add_bench_parser(sub: Any) -> argparse.ArgumentParser:
    """Add ``bench`` and its subcommands to ``sub`` (the CLI's subparsers action)."""
    b: argparse.ArgumentParser = sub.add_parser(
        "bench", help="benchmarks (ratios against baselines measured in the same run)"
    )
    bsub = b.add_subparsers(dest="bench_command", required=True, metavar="BENCH")
    # one line a bench: its name, its help, what adds its arguments
    benches: tuple[tuple[str, str, Callable[[argparse.ArgumentParser], None]], ...] = (
        ("kernels", "samples/s per core per estimator vs a numpy FFT baseline", add_kernels_arguments),
        ("e2e", "daemon fed through Zenoh on loopback, recording on", add_e2e_only_arguments),
        ("fanout", "serve --workers' input fan-out: Zenoh to each worker vs shared rings", add_fanout_arguments),
        ("overload", "the daemon offered twice what it sustains, with each queue policy", add_overload_arguments),
        ("soak", "hours of load with recording rotation: RSS, fds, latency every interval", add_soak_arguments),
        ("accuracy", "seeded Monte Carlo of every estimator on every scenario vs the CRLB", add_accuracy_arguments),
        ("calibration", "reported std against the actual error, per estimator, parameter and SNR", _calibration_args),
        ("scenarios", "list the scenario library", add_scenarios_arguments),
        ("startup", "wall time of short CLI commands vs the bare interpreter", add_startup_arguments),
        ("compliance", "IEEE C37.118.1 M-class tests of estimators reporting on a time grid", add_compliance_arguments),
        ("c37118", "the daemon as a C37.118.2 PMU: latency with no, one, a stalled client", add_c37118_arguments),
        ("pmu-reference", "a real PMU's C37.118.2 stream as the reference for a channel", add_pmu_reference_arguments),
        ("pipeline", "in-process CPU cost per block of the pipeline, recording on and off", add_pipeline_arguments),
        ("estimate-puts", "a frame's estimates: a put per channel vs an estimate frame", add_estimate_puts_arguments),
        ("recorder-compression", "the recorder's compressions: CPU per sample and bytes", _compression_args),
        ("gateway", "gateway sv: 9-2LE frames decoded and published per core", add_gateway_arguments),
    )
    for name, help_text, add_arguments in benches:
        p = bsub.add_parser(name, help=help_text)
        add_arguments(p)
        p.set_defaults(fn=_runner(_MODULES.get(name, name.replace("-", "_"))))
    return b


def _compression_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frame-channels", type=int, default=8, help="channels a recorded frame (default 8)")
    parser.add_argument("--chunk-bytes", type=int, default=1 << 20, help="the chunk compressed (default 1 MiB)")
    parser.add_argument("--repeats", type=int, default=9, help="each way's fastest of this many (default 9)")
    parser.add_argument("--json", type=Path, help="also write results as JSON")


CALIBRATION_ESTIMATORS = ("pmu", "default-rule", "ipdft", "nls", "ges-kalman")
CALIBRATION_FULL_TRIALS = 300
CALIBRATION_QUICK_TRIALS = 40


def _calibration_args(parser: argparse.ArgumentParser) -> None:
    # here, not in bench.calibration: building the CLI's parser imports no bench module
    parser.add_argument("--estimators", nargs="+", help=f"some of {', '.join(CALIBRATION_ESTIMATORS)} (default all)")
    parser.add_argument(
        "--trials",
        type=int,
        help=f"trials per cell (default {CALIBRATION_FULL_TRIALS}; --quick {CALIBRATION_QUICK_TRIALS})",
    )
    parser.add_argument("--quick", action="store_true", help=f"{CALIBRATION_QUICK_TRIALS} trials per cell")
    parser.add_argument("--seed", type=int, default=0, help="first trial's seed (default 0)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON")
    parser.add_argument(
        "--update-docs", type=Path, help="replace the table between the calibration markers of this file"
    )


def add_estimate_puts_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--channels", type=int, default=8, help="channels per input frame (default 8)")
    parser.add_argument("--frames", type=int, default=5000, help="input frames' estimates put (default 5000)")
    # 1221 frames/s of 1024 samples on 8 channels: 10 M samples/s
    parser.add_argument("--rate", type=float, default=1221.0, help="input frames a second (default 1221; 0: unpaced)")
    parser.add_argument("--json", type=Path, help="also write results as JSON")


def add_kernels_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--estimators", help="comma-separated names (default all)")
    parser.add_argument("--block", type=int, action="append", help="block size (repeatable; default 1024 and 4096)")
    parser.add_argument("--seconds", type=float, default=0.5, help="time per measurement (default 0.5)")
    # a bank: one compiled call for N channels of a frame
    parser.add_argument("--bank", type=int, default=8, metavar="N", help="channels per bank, beside one (default 8)")
    parser.add_argument("--json", type=Path, help="also write results as JSON")


def add_e2e_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--channels", type=int, default=200)
    parser.add_argument("--rate", type=float, default=10_000.0, help="per-channel sample rate, Hz")
    parser.add_argument("--block", type=int, default=1024)
    parser.add_argument("--duration", type=float, help="seconds (default 60; 20 per point with --sweep)")
    parser.add_argument("--estimator", default="ges-kalman")
    parser.add_argument(
        "--queue-policy", choices=["block", "drop"], default="block", help="the daemon's limits.queue_policy"
    )
    parser.add_argument("--queue-capacity", type=int, default=8192, help="the daemon's limits.queue_capacity")
    parser.add_argument("--workers", type=int, default=1, help="the daemon's worker processes (default 1; 0: per core)")
    parser.add_argument(
        "--foxglove",
        action="store_true",
        help="the daemon serves its live Foxglove view and a client subscribes to every topic (needs the foxglove extra)",
    )
    parser.add_argument("--json", type=Path, help="also write results as JSON")


def add_e2e_only_arguments(parser: argparse.ArgumentParser) -> None:
    add_e2e_arguments(parser)
    parser.add_argument(
        "--sweep",
        action="store_true",
        help="measure at 1, 10, 100, 1000 and 5000 channels, then doubling while the daemon keeps up: a table and a plot",
    )
    parser.add_argument("--sweep-channels", metavar="N,N,...", help="the channel counts of --sweep (exactly these)")
    parser.add_argument(
        "--frame-channels",
        default="1",
        metavar="N[,N...]",
        help="channels per message: 1 (default) sends one SampleBlock per channel, N > 1 SampleFrames of N "
        "channels; several values run one after the other into one table (e.g. 1,8)",
    )
    parser.add_argument("--plot", type=Path, help="with --sweep: the PNG (default: the --json path with .png)")
    parser.add_argument(
        "--no-hold",
        action="store_true",
        help="the daemon's hold_estimates off: each estimate published as made (what the latency is without the hold)",
    )
    parser.add_argument(
        "--report-in-block",
        action="store_true",
        help="the daemon's report_in_block on: each estimate at the sample its block's presence detector has "
        "read its onset latency past, released with its own block (its timestamp that latency before the block's end)",
    )


def add_gateway_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--streams", type=int, default=2, help="SV streams (merging units) at once (default 2)")
    parser.add_argument("--seconds", type=int, default=3, help="seconds of traffic per stream (default 3)")
    parser.add_argument("--rate", type=int, default=4000, help="frames/s per stream (default 4000; 4800 at 60 Hz)")
    parser.add_argument("--samples", type=int, default=80, help="samples per published frame (default 80)")
    parser.add_argument("--json", type=Path, help="also write results as JSON")


def add_fanout_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--channels", type=int, default=1000)
    parser.add_argument("--block", type=int, default=1024, help="float32 samples per block")
    parser.add_argument("--blocks", type=int, default=20_000, help="blocks offered (default 20000)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--rate", type=float, default=10_000.0, help="blocks/s offered (default 10000; 0: as fast as possible)"
    )
    parser.add_argument("--json", type=Path, help="also write results as JSON")


def add_soak_arguments(parser: argparse.ArgumentParser) -> None:
    add_e2e_arguments(parser)
    parser.set_defaults(channels=100, duration=3600.0)  # 100 ch x 10 kHz = 1 M samples/s for an hour
    parser.add_argument("--interval", type=float, default=60.0, help="seconds between report lines (default 60)")
    parser.add_argument("--rotate-seconds", type=float, default=300.0, help="a new recording this often (default 300)")
    parser.add_argument("--plot", type=Path, help="write the RSS curve to this PNG (needs matplotlib)")


def add_c37118_arguments(parser: argparse.ArgumentParser) -> None:
    add_e2e_arguments(parser)
    parser.set_defaults(channels=30, duration=30.0, block=1000, estimator="pmu")
    parser.add_argument(
        "--station-channels", type=int, help="channels in the served station (default all: 266-byte frames at 30)"
    )


def add_pmu_reference_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--c37118", required=True, metavar="HOST:PORT", help="the reference PMU (or PDC)")
    parser.add_argument("--id-code", type=int, required=True, help="its data stream's ID code")
    parser.add_argument("--phasor", help="its phasor to compare with (default its first)")
    parser.add_argument("--channel", required=True, help="the sinewatch channel measuring the same signal")
    parser.add_argument("--connect", action="append", help="Zenoh endpoint of the daemon (repeatable)")
    parser.add_argument("--frames", type=int, default=500, help="data frames to compare (default 500)")
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for a frame or an estimate")
    parser.add_argument("--json", type=Path, help="also write results as JSON")


def add_overload_arguments(parser: argparse.ArgumentParser) -> None:
    add_e2e_arguments(parser)
    parser.set_defaults(channels=600, duration=20.0, queue_capacity=1024)
    parser.add_argument(
        "--sustainable-channels",
        type=int,
        default=300,
        help="channels the daemon sustains at this rate (bench e2e); the offer is --channels (default 600, twice)",
    )


def add_accuracy_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--estimators", nargs="+", metavar="NAME", help="estimator names or globs (default: every registered estimator)"
    )
    parser.add_argument(
        "--scenarios",
        nargs="+",
        metavar="NAME",
        help="scenario names, globs (c37-50hz-*) or tags (c37.118, paper, snr, gap, "
        "multitone, phasor; or tag:NAME); pq: the power-quality families (IEC 61000-4-7/4-30, "
        "pqopen-lib beside when installed; or their names and globs, pq-unbalance-*); "
        "default: all single-channel scenarios (with --quick: tag quick)",
    )
    parser.add_argument(
        "--trials",
        type=int,
        default=None,
        help=f"Monte Carlo trials per noisy scenario (default {DEFAULT_TRIALS}, {QUICK_TRIALS} with --quick)",
    )
    parser.add_argument("--seed", type=int, default=0, help="first seed (trial i uses seed + i)")
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("bench-results/accuracy"),
        help="output directory for accuracy.md, accuracy.json and plots/",
    )
    parser.add_argument("--quick", action="store_true", help="the quick subset and fewer trials")
    parser.add_argument(
        "--jobs",
        type=int,
        default=min(2, os.cpu_count() or 1),
        help="worker processes (default: 2 or the core count if smaller)",
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument(
        "--update-docs",
        type=Path,
        metavar="FILE",
        help="also replace the results block of FILE (e.g. docs/accuracy.md)",
    )


def add_compliance_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--estimator", default="pmu", help="a grid-reporting estimator, or default-rule (the daemon's default rule)"
    )
    parser.add_argument(
        "--rates",
        default=None,
        help="comma-separated f0/Fs pairs (default 50/50,60/60; M-class: 50/10, 50/25, 50/50, 60/10, 60/12, 60/15, "
        "60/20, 60/30, 60/60); default-rule: its own Fs at 50 and 60 Hz",
    )
    parser.add_argument(
        "--sample-rates",
        default="10000",
        help="comma-separated input sample rates, Hz, whole or not (e.g. 10000,9999.33,12800,25600)",
    )
    parser.add_argument("--full", action="store_true", help="the standard's full sweeps (slower)")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON")


def add_scenarios_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("patterns", nargs="*", metavar="NAME", help="names, globs or tags to list (default: all)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")


def add_startup_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=int, default=STARTUP_RUNS, help=f"runs of each command (default {STARTUP_RUNS})")
    parser.add_argument(
        "--config", type=Path, help="config file for `sinewatch config show` (default: built-in defaults)"
    )
    parser.add_argument("--json", type=Path, help="also write results as JSON")


def add_pipeline_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--channels", type=int, default=200)
    parser.add_argument("--rate", type=float, default=10_000.0, help="per-channel sample rate, Hz")
    parser.add_argument("--block", type=int, default=1024)
    parser.add_argument("--estimator", default="ges-kalman")
    parser.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd", help="the recording's")
    parser.add_argument("--rounds", type=int, default=5, help="blocks per channel per repeat (default 5)")
    parser.add_argument("--repeats", type=int, default=12, help="repeats of each measurement (default 12)")
    parser.add_argument(
        "--frame-channels", type=int, default=1, help="channels a SampleFrame (default 1: one SampleBlock a channel)"
    )
    parser.add_argument("--json", type=Path, help="also write results as JSON")
