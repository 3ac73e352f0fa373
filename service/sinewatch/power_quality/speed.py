"""Measurements of the harmonic analyser: its cost per sample against a plain numpy
``rfft`` of the same windows in the same run, and its accuracy beside pqopen-lib's on the
same waveforms (when the optional extra is installed).

    python -m sinewatch.power_quality.speed [--seconds 20] [--rate 10000]
    python -m sinewatch.scenarios.power_quality_iec      # the accuracy table, with pqopen

:func:`measure_speed` and :func:`compare_accuracy` return plain dicts, for a bench to call.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import Any

import numpy as np

from sinewatch.power_quality.harmonics import HarmonicAnalyser
from sinewatch.power_quality.limits import LIMITS, class_i_limit


def _signal(fs: float, seconds: float, f: float, n_phases: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    t = np.arange(round(fs * seconds)) / fs
    cols = []
    for p in range(n_phases):
        shift = -2.0 * np.pi * p / 3.0
        y = math.sqrt(2.0) * np.sin(2 * np.pi * f * t + shift)
        for h in range(2, 51):
            y += math.sqrt(2.0) * 0.02 * np.sin(2 * np.pi * h * f * t + h * shift + 0.1 * h)
        cols.append(y + 1e-3 * rng.standard_normal(t.size))
    return np.stack(cols, axis=1)


def measure_speed(
    sample_rate_hz: float = 10_000.0,
    seconds: float = 20.0,
    frequency_hz: float = 50.3,
    n_phases: int = 1,
    block: int = 1000,
    repeats: int = 3,
) -> dict[str, Any]:
    """Best-of-``repeats`` wall time per input sample of the analyser (blocks of ``block``
    samples, all channels) and of ``numpy.fft.rfft`` over the same windows (same lengths,
    whole samples), and their ratio."""
    x = _signal(sample_rate_hz, seconds, frequency_hz, n_phases)
    n = x.shape[0]
    warm = HarmonicAnalyser(sample_rate_hz, n_channels=n_phases)
    warm.update(x[:5000], 0)  # compile
    best_an = math.inf
    windows = []
    for _ in range(repeats):
        an = HarmonicAnalyser(sample_rate_hz, n_channels=n_phases)
        t0 = time.perf_counter()
        out = []
        for i in range(0, n, block):
            out += an.update(x[i : i + block], round(i * 1e9 / sample_rate_hz))
        best_an = min(best_an, time.perf_counter() - t0)
        windows = out
    spans = [(round((w.start_ns * sample_rate_hz) / 1e9), round((w.end_ns * sample_rate_hz) / 1e9)) for w in windows]
    best_fft = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for a, b in spans:
            np.fft.rfft(x[a:b], axis=0)
        best_fft = min(best_fft, time.perf_counter() - t0)
    return {
        "sample_rate_hz": sample_rate_hz,
        "seconds": seconds,
        "n_phases": n_phases,
        "windows": len(windows),
        "analyser_ns_per_sample": 1e9 * best_an / n,
        "rfft_ns_per_sample": 1e9 * best_fft / n,
        "ratio": best_an / best_fft,
    }


def compare_accuracy(scenarios: list[Any]) -> list[dict[str, Any]]:
    """Worst error of sinewatch and of pqopen-lib (if installed) against the exact truth of
    power-quality scenarios (:class:`sinewatch.scenarios.power_quality_iec.PqScenario`:
    ``pq_truth``, ``generate()``), as a fraction of the IEC limit (<= 1 passes): harmonic
    subgroups (class I), THD over 2..40 (judged like a harmonic reading), u2 (class A,
    0.15 points). The table: ``python -m sinewatch.scenarios.power_quality_iec``."""
    from sinewatch.power_quality import pqopen_reference
    from sinewatch.power_quality.reports import window_sequence

    rows = []
    have_pqopen = pqopen_reference.available()
    for sc in scenarios:
        name = sc.name
        truth = sc.pq_truth
        y, _ = sc.generate()
        fs = sc.sample_rate_hz
        an = HarmonicAnalyser(fs, nominal_frequency_hz=sc.nominal_frequency_hz, n_channels=sc.n_phases)
        ws = []
        x = y.reshape(y.shape[0], -1)
        for i in range(0, x.shape[0], 1000):
            ws += an.update(x[i : i + 1000], round(i * 1e9 / fs))
        lim = class_i_limit(truth.harmonic_rms[:, 1:], float(truth.harmonic_rms[0, 1]))
        thd40 = np.sqrt(np.sum(truth.harmonic_rms[:, 2:41] ** 2, axis=1)) / truth.harmonic_rms[:, 1]
        # THD judged like a harmonic reading: 5 % of it above 1 %, 0.05 % absolute below
        thd_lim = class_i_limit(thd40, 1.0)
        row: dict[str, Any] = {"scenario": name, "windows": len(ws)}
        row["sinewatch_harmonic"] = max(
            float(np.max(np.abs(w.harmonic_subgroup_rms[:, 1:] - truth.harmonic_rms[:, 1:]) / lim)) for w in ws
        )
        thd_sw = [
            np.sqrt(np.sum(w.harmonic_subgroup_rms[:, 2:41] ** 2, axis=1)) / w.harmonic_subgroup_rms[:, 1] for w in ws
        ]
        row["sinewatch_thd40"] = max(float(np.max(np.abs(t - thd40) / thd_lim)) for t in thd_sw)
        if truth.u2 is not None:
            row["sinewatch_u2"] = max(abs(float(window_sequence(w).u2) - truth.u2) / LIMITS["u2_absolute"] for w in ws)
        if have_pqopen:
            r = pqopen_reference.run_pqopen(y, fs, sc.nominal_frequency_hz)
            steady = slice(1, -1)  # pqopen's first window starts at its first zero crossing
            h = r.harmonic_rms[steady]
            top = h.shape[2] - 1  # pqopen's highest order (41 at 60 Hz, 10 kHz)
            row["pqopen_windows"] = int(h.shape[0])
            row["pqopen_max_order"] = top
            err = np.abs(h[:, :, 1:] - truth.harmonic_rms[None, :, 1 : top + 1]) / lim[None, :, :top]
            row["pqopen_harmonic"] = float(np.max(err))
            row["pqopen_thd40"] = float(np.max(np.abs(r.thd[steady] - thd40[None]) / thd_lim[None]))
            if r.u2 is not None and truth.u2 is not None:
                row["pqopen_u2"] = float(np.max(np.abs(r.u2[steady] - truth.u2)) / LIMITS["u2_absolute"])
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="The harmonic analyser's cost per sample against numpy rfft")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rate", type=float, default=10_000.0)
    args = ap.parse_args(argv)
    for phases in (1, 3):
        print(json.dumps(measure_speed(args.rate, args.seconds, n_phases=phases)))


if __name__ == "__main__":
    main()
