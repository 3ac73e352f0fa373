"""Windowed estimators against the exact finite-window Cramer-Rao bound, by Monte Carlo.

``python -m sinewatch.apps.bench.crlb_window [--trials 1000] [--estimators nls,ipdft]``

Each trial is one window of N samples of ``B + sum_k A_k sin(2 pi f_k t + phi_k) + v``
(v white Gaussian; random phases; frequencies jittered by up to half a DFT bin), fed to a
fresh estimator whose window is exactly those N samples and whose one estimate is at the
window's last sample. Per parameter (frequency, amplitude, phase at the last sample,
offset) the table shows the mean square error over the mean exact bound
(:func:`sinewatch.crlb.crlb` for one tone, :func:`sinewatch.crlb.crlb_tones` for several)
in dB, 0 dB being the physical limit, and, for an estimator that reports standard
deviations (``Track.std``), the calibration: the sd of error / reported sd, 1 when the
reported uncertainty is right.

The bound here is that of the estimator's own window, not of every sample seen since the
start (which ``sinewatch bench accuracy`` uses): a windowed estimator can at best reach
the former.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from sinewatch import crlb
from sinewatch.estimators import create

FS = 1000.0
QUANTITIES = ("frequency_hz", "amplitude", "phase_rad", "offset")


@dataclass(frozen=True)
class Case:
    n: int
    freqs: tuple[float, ...]
    amps: tuple[float, ...]
    snr_db: float  # of the first tone, A^2 / (2 sigma^2)

    @property
    def label(self) -> str:
        if len(self.freqs) == 1:
            return f"1 tone, N={self.n}, {self.snr_db:g} dB"
        bins = (self.freqs[1] - self.freqs[0]) * self.n / FS
        return f"{len(self.freqs)} tones {bins:g} bins apart, N={self.n}, {self.snr_db:g} dB"


def _wrap(p: Any) -> Any:
    return np.pi - np.mod(np.pi - p, 2.0 * np.pi)


def estimator_params(name: str, case: Case) -> dict[str, Any]:
    """Parameters that make the estimator's window the trial's N samples, one estimate."""
    if name == "nls":
        return {"n_components": len(case.freqs), "min_frequency_hz": 20.0, "window_samples": case.n,
                "hop_samples": case.n, "zero_pad": 4}  # fmt: skip
    if name == "ipdft":
        return {"nominal_frequency_hz": case.freqs[0], "window_samples": case.n, "hop_samples": case.n}
    raise ValueError(f"estimator: expected nls or ipdft, got {name!r}")


def monte_carlo(name: str, case: Case, trials: int, seed: int, offset: float = 0.5) -> dict[str, np.ndarray]:
    """``db`` (K, 4): 10 log10(MSE / mean bound); ``calibration`` (K, 4): sd(error / sd)
    (NaN without reported sd); ``converged``: the fraction of trials converged."""
    rng = np.random.default_rng(seed)
    k, n = len(case.freqs), case.n
    sigma = case.amps[0] / math.sqrt(2.0 * 10.0 ** (case.snr_db / 10.0))
    t = np.arange(n) / FS
    amps = np.array(case.amps)
    err = np.zeros((trials, k, 4))
    sd = np.full((trials, k, 4), np.nan)
    bound = np.zeros((trials, k, 4))
    conv = 0
    params = estimator_params(name, case)
    for i in range(trials):
        f = np.array(case.freqs) + rng.uniform(-0.5, 0.5, k) * FS / n
        ph0 = rng.uniform(-np.pi, np.pi, k)
        x = offset + np.sum(amps[:, None] * np.sin(2 * np.pi * f[:, None] * t + ph0[:, None]), axis=0)
        x = x + sigma * rng.standard_normal(n)
        tr = create(name, FS, **params).update(x, last_only=True)
        conv += int(tr.converged[0])
        ph_end = _wrap(2 * np.pi * f * t[-1] + ph0)
        if k == 1:
            bounds = [crlb.crlb(n, f[0], amps[0], ph_end[0], sigma, FS)]
        else:
            bounds = crlb.crlb_tones(n, list(f), list(amps), list(ph_end), sigma, FS)
        for j in range(k):
            err[i, j] = [
                tr.frequency_hz[0, j] - f[j],
                tr.amplitude[0, j] - amps[j],
                _wrap(tr.phase_rad[0, j] - ph_end[j]),
                tr.offset[0] - offset,
            ]
            if tr.std is not None:
                sd[i, j] = [tr.std.frequency_hz[0, j], tr.std.amplitude[0, j], tr.std.phase_rad[0, j], tr.std.offset[0]]
            b = bounds[j]
            bound[i, j] = [b.frequency_hz, b.amplitude, b.phase_rad, b.offset]
    return {
        "db": 10.0 * np.log10(np.mean(err**2, axis=0) / np.mean(bound, axis=0)),
        "calibration": np.std(err / sd, axis=0),
        "converged": np.array(conv / trials),
    }


def default_cases() -> list[Case]:
    cases = [Case(n, (50.0,), (1.0,), snr) for n in (256, 1024) for snr in (10, 20, 30, 40)]
    cases += [Case(512, (50.0, 50.0 + b * FS / 512), (1.0, 0.7), snr) for b in (2, 5) for snr in (10, 20, 30, 40)]
    return cases


def table(name: str, cases: Sequence[Case], trials: int, seed: int) -> str:
    lines = [
        f"`{name}`: dB over the exact bound (frequency / amplitude / phase / offset) and calibration, "
        f"sd(error / reported sd), {trials} trials per row",
        "",
        "| case | tone | dB over CRLB | calibration | converged |",
        "|---|---|---|---|---|",
    ]
    for i, case in enumerate(cases):
        if create(name, FS, **estimator_params(name, case)).n_components < len(case.freqs):
            lines.append(f"| {case.label} | - | n/a (one tone only) | | |")
            continue
        res = monte_carlo(name, case, trials, seed + 1000 * i)
        for j in range(len(case.freqs)):
            db = " / ".join(f"{v:+.2f}" for v in res["db"][j])
            cal = " / ".join("-" if not np.isfinite(v) else f"{v:.3f}" for v in res["calibration"][j])
            lines.append(f"| {case.label} | {j + 1} | {db} | {cal} | {100 * float(res['converged']):.0f} % |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sinewatch.apps.bench.crlb_window", description=__doc__.split("\n")[0])
    ap.add_argument("--estimators", default="nls", help="comma-separated: nls, ipdft (default nls)")
    ap.add_argument("--trials", type=int, default=1000, help="Monte Carlo trials per row (default 1000)")
    ap.add_argument("--seed", type=int, default=0, help="first seed")
    args = ap.parse_args(argv)
    cmd = "python -m sinewatch.apps.bench.crlb_window " + " ".join(argv if argv is not None else sys.argv[1:])
    print(f"Command: `{cmd.strip()}`\n")
    for name in args.estimators.split(","):
        print(table(name.strip(), default_cases(), args.trials, args.seed))
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
