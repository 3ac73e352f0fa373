"""``sinewatch bench calibration``: are the reported standard deviations right?

Each trial is one seeded signal ``B + A sin(2 pi f t + phi) + v`` (v white Gaussian of
variance ``sigma^2 = A^2 / (2 SNR)``; f within +-0.5 Hz of 50 Hz, phi uniform, A in 0.5..2,
B within +-0.1 A), ``DURATION_S`` long at ``SAMPLE_RATE_HZ``, fed in one call to a fresh
estimator built with every parameter at its documented default (the default rule as the
daemon builds it). The last estimate (the last report, for an estimator that reports on a
time grid, at its report time; otherwise the last sample) is compared with the truth at its
time. Per estimator, parameter and SNR the table gives the sd and the mean of
``error / reported std`` over the trials: 1 and 0 when the reported std is right (the
target: sd within 0.9-1.1, |mean| <= 0.3). For the TVE (always >= 0) it gives the RMS of
``TVE / reported RMS TVE`` in the sd column (1 when right) and its mean (0.89 for a
circular Gaussian error).

Nothing in a trial tells an estimator the noise level: each reads it from the signal.
One estimate per trial, so the trials are independent (consecutive estimates of one
stream share samples and their errors are correlated).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sinewatch.apps.bench.args import CALIBRATION_ESTIMATORS, CALIBRATION_FULL_TRIALS, CALIBRATION_QUICK_TRIALS

if TYPE_CHECKING:  # the estimators (and numba) load when a trial runs, not with the CLI's parser
    from sinewatch.estimators.base import Estimator, Track

SAMPLE_RATE_HZ = 5000.0
DURATION_S = 2.0
SNRS_DB = (0.0, 10.0, 20.0, 40.0, 60.0)
ESTIMATORS = CALIBRATION_ESTIMATORS
PARAMETERS = ("frequency_hz", "amplitude", "phase_rad", "offset", "rocof_hz_per_s", "tve")
FULL_TRIALS = CALIBRATION_FULL_TRIALS
QUICK_TRIALS = CALIBRATION_QUICK_TRIALS
DOCS_BEGIN = "<!-- calibration:begin -->"
DOCS_END = "<!-- calibration:end -->"


def make_estimator(name: str, sample_rate_hz: float = SAMPLE_RATE_HZ) -> Estimator[Any]:
    """The estimator with every parameter at its default (the default rule's own parameters)."""
    from sinewatch.apps.bench.params import default_rule_estimator
    from sinewatch.estimators import create

    if name == "default-rule":
        cls, params, _ = default_rule_estimator()
        return cls(sample_rate_hz, params)
    return create(name, sample_rate_hz)


def trial_signal(seed: int, snr_db: float) -> tuple[np.ndarray, dict[str, float]]:
    """The samples of trial ``seed`` at ``snr_db`` and its truth (f, A, phi, B, sigma)."""
    rng = np.random.default_rng([seed, round(snr_db * 10)])
    f = 50.0 + rng.uniform(-0.5, 0.5)
    amp = float(np.exp(rng.uniform(math.log(0.5), math.log(2.0))))
    phi = rng.uniform(-math.pi, math.pi)
    off = rng.uniform(-0.1, 0.1) * amp
    sigma = amp / math.sqrt(2.0 * 10.0 ** (snr_db / 10.0))
    n = np.arange(round(DURATION_S * SAMPLE_RATE_HZ))
    x = off + amp * np.sin(2.0 * math.pi * f * n / SAMPLE_RATE_HZ + phi) + sigma * rng.standard_normal(n.size)
    return x, {"f": f, "A": amp, "phi": phi, "B": off, "sigma": sigma}


def _wrap(p: float) -> float:
    return math.remainder(p, 2.0 * math.pi)


def normalised_errors(name: str, seed: int, snr_db: float) -> dict[str, float]:
    """error / reported std per parameter for one trial (NaN where the estimator reports none)."""
    x, truth = trial_signal(seed, snr_db)
    est = make_estimator(name)
    track: Track = est.update(x, t0_ns=0)
    if track.reports is not None:
        rows = track.reports.track
        t = float(track.reports.times_s()[-1])
    else:
        rows = track
        t = (x.size - 1) / SAMPLE_RATE_HZ
    out = dict.fromkeys(PARAMETERS, math.nan)
    std = rows.std
    if std is None or rows.offset.size == 0:
        return out
    f, amp, phi, off = truth["f"], truth["A"], truth["phi"], truth["B"]
    theta = 2.0 * math.pi * f * t + phi
    err = {
        "frequency_hz": rows.frequency_hz[-1, 0] - f,
        "amplitude": rows.amplitude[-1, 0] - amp,
        "phase_rad": _wrap(rows.phase_rad[-1, 0] - theta),
        "offset": rows.offset[-1] - off,
    }
    sd = {
        "frequency_hz": std.frequency_hz[-1, 0],
        "amplitude": std.amplitude[-1, 0],
        "phase_rad": std.phase_rad[-1, 0],
        "offset": std.offset[-1],
    }
    if rows.rocof_hz_per_s is not None and "std_rocof_hz_per_s" in rows.extras:
        err["rocof_hz_per_s"] = rows.rocof_hz_per_s[-1, 0]
        sd["rocof_hz_per_s"] = rows.extras["std_rocof_hz_per_s"][-1]
    if "std_tve" in rows.extras:  # the phasor A e^{j theta} against the truth's
        est_x = rows.amplitude[-1, 0] * np.exp(1j * rows.phase_rad[-1, 0])
        err["tve"] = abs(est_x - amp * np.exp(1j * theta)) / amp
        sd["tve"] = rows.extras["std_tve"][-1]
    for k, e in err.items():
        s = float(sd[k])
        out[k] = float(e) / s if s > 0 and math.isfinite(s) else math.nan
    return out


def _cell(args: tuple[str, float, int, int]) -> dict[str, Any]:
    name, snr_db, trials, seed = args
    z = {k: [] for k in PARAMETERS}  # type: dict[str, list[float]]
    for i in range(trials):
        for k, v in normalised_errors(name, seed + i, snr_db).items():
            z[k].append(v)
    row: dict[str, Any] = {"estimator": name, "snr_db": snr_db, "trials": trials}
    for k, vals in z.items():
        a = np.array(vals)
        if np.all(np.isnan(a)):
            continue
        finite = a[np.isfinite(a)]
        if k == "tve":
            row[k] = {"sd": float(np.sqrt(np.mean(finite**2))), "mean": float(np.mean(finite)), "n": int(finite.size)}
        else:
            row[k] = {"sd": float(np.std(finite)), "mean": float(np.mean(finite)), "n": int(finite.size)}
    return row


def run_calibration(
    estimators: tuple[str, ...] | list[str], snrs: tuple[float, ...] | list[float], trials: int, seed: int, jobs: int
) -> list[dict[str, Any]]:
    """One row per (estimator, SNR): per parameter the sd and mean of error / std."""
    cells = [(name, float(snr), trials, seed) for name in estimators for snr in snrs]
    if jobs <= 1:
        return [_cell(c) for c in cells]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        return list(pool.map(_cell, cells))


def out_of_band(row: dict[str, Any], parameter: str) -> bool:
    """Whether a cell misses the target (sd in 0.9-1.1 and |mean| <= 0.3; TVE: RMS in 0.9-1.1)."""
    cell = row.get(parameter)
    if cell is None:
        return False
    if parameter == "tve":
        return not 0.9 <= cell["sd"] <= 1.1
    return not (0.9 <= cell["sd"] <= 1.1 and abs(cell["mean"]) <= 0.3)


def render_markdown(rows: list[dict[str, Any]], command: str, meta: dict[str, Any]) -> str:
    lines = [
        f"Command: `{command}` ({meta['trials']} seeded trials per cell, {meta['elapsed_s']:.0f} s on "
        f"{meta['machine']}; load average {meta['load']}).",
        "",
        "sd / mean of error / reported std (TVE: RMS / mean of TVE / reported RMS TVE); "
        "**bold**: outside sd 0.9-1.1 or |mean| > 0.3; `-`: not reported.",
        "",
        "| estimator | SNR dB | " + " | ".join(PARAMETERS) + " |",
        "|---|---:|" + "---:|" * len(PARAMETERS),
    ]
    for row in rows:
        cells = []
        for k in PARAMETERS:
            c = row.get(k)
            if c is None:
                cells.append("-")
                continue
            text = f"{c['sd']:.2f} / {c['mean']:+.2f}"
            cells.append(f"**{text}**" if out_of_band(row, k) else text)
        lines.append(f"| {row['estimator']} | {row['snr_db']:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _update_docs(path: Path, md: str) -> None:
    text = path.read_text()
    a, b = text.find(DOCS_BEGIN), text.find(DOCS_END)
    if a < 0 or b < a:
        raise SystemExit(f"{path}: expected the markers {DOCS_BEGIN} ... {DOCS_END}")
    path.write_text(text[: a + len(DOCS_BEGIN)] + "\n" + md + "\n" + text[b:])


def run(args: argparse.Namespace) -> int:
    trials = args.trials if args.trials is not None else (QUICK_TRIALS if args.quick else FULL_TRIALS)
    if trials < 1:
        print(f"error: --trials: expected >= 1, got {trials}", file=sys.stderr)
        return 2
    names = tuple(args.estimators or ESTIMATORS)
    unknown = [n for n in names if n not in ESTIMATORS]
    if unknown:
        print(f"error: --estimators: expected some of {list(ESTIMATORS)}, got {unknown}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    rows = run_calibration(names, SNRS_DB, trials, args.seed, max(1, args.jobs))
    parts = ["sinewatch", "bench", "calibration"]
    if args.estimators:
        parts += ["--estimators", *names]
    parts += ["--quick"] if args.quick and args.trials is None else []
    parts += ["--trials", str(args.trials)] if args.trials is not None else []
    parts += ["--seed", str(args.seed)] if args.seed else []
    meta = {
        "trials": trials,
        "elapsed_s": time.perf_counter() - t0,
        "machine": f"{os.cpu_count()} cores, {max(1, args.jobs)} jobs",
        "load": " ".join(f"{v:.1f}" for v in os.getloadavg()),
    }
    md = render_markdown(rows, " ".join(shlex.quote(p) for p in parts), meta)
    print(md)
    if args.json:
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    if args.update_docs:
        _update_docs(args.update_docs, md)
    return 0
