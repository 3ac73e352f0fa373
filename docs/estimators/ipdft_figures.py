"""Figures quoted in docs/estimators/ipdft.md. Run: .venv/bin/python docs/estimators/ipdft_figures.py

Deterministic (seeded); prints markdown tables. Timing figures depend on the machine and
its load.
"""

from __future__ import annotations

import numpy as np
from _timing import ns_per_sample  # docs/estimators/_timing.py: these scripts run from this folder

from sinewatch.estimators import create
from sinewatch.scenarios import SumOfTones, Tone, wrap_phase

FS = 1000.0


def tone(f, n, fs=FS, a=1.0, b=0.5, phi=0.3, noise=0.0, seed=0):
    t = np.arange(n) / fs
    rng = np.random.default_rng(seed)
    return t, b + a * np.sin(2 * np.pi * f * t + phi) + noise * rng.standard_normal(n)


def bias_table():
    print("| window | interpolation | max abs df (Hz) | max abs dA | max abs dB | max abs dphase (rad) |")
    print("|---|---|---|---|---|---|")
    for cycles in (2, 3, 4, 8):
        for interp in ("3-point", "2-point"):
            ef, ea, eb, ep = [], [], [], []
            for f in np.linspace(45.0, 55.0, 21):
                for phi in np.linspace(0, 2 * np.pi, 6, endpoint=False):
                    n = int(cycles * FS / 50) + 40
                    t, x = tone(f, n, phi=phi)
                    tr = create("ipdft", FS, window_cycles=cycles, interpolation=interp).update(x, last_only=True)
                    ef.append(tr.frequency_hz[0, 0] - f)
                    ea.append(tr.amplitude[0, 0] - 1.0)
                    eb.append(tr.offset[0] - 0.5)
                    ep.append(wrap_phase(tr.phase_rad[0, 0] - (2 * np.pi * f * t[-1] + phi)))
            m = [np.max(np.abs(v)) for v in (ef, ea, eb, ep)]
            print(
                f"| {cycles} cycles ({int(cycles * FS / 50)} samples) | {interp} | "
                + " | ".join(f"{v:.2g}" for v in m)
                + " |"
            )


def crlb(n, fs, f, a, phases, sigma):
    k = np.arange(n)
    inv = []
    for ph in phases:
        arg = 2 * np.pi * f * k / fs + ph
        jac = np.stack([np.sin(arg), a * np.cos(arg) * 2 * np.pi * k / fs, a * np.cos(arg), np.ones(n)], 1)
        inv.append(np.linalg.inv(jac.T @ jac / sigma**2))
    return np.mean(inv, axis=0)


def crlb_table():
    print(
        "| N | interpolation | sqrt CRLB(f) exact / eq. 3.41 (Hz) | var(f)/CRLB | var(A)/CRLB | var(B)/CRLB | mean df (Hz) |"
    )
    print("|---|---|---|---|---|---|---|")
    sigma, f0, m = 0.05, 50.3, 600
    for n in (80, 160):
        for interp in ("3-point", "2-point"):
            _t, x = tone(f0, n * m, noise=sigma, seed=1)
            tr = create("ipdft", FS, window_samples=n, hop_samples=n, interpolation=interp).update(x)
            rows = np.arange(n - 1, n * m, n)
            f, amp, off = tr.frequency_hz[rows, 0], tr.amplitude[rows, 0], tr.offset[rows]
            b = crlb(n, FS, f0, 1.0, 2 * np.pi * f0 * (rows[:60] - n + 1) / FS + 0.3, sigma)
            asym = 24 * sigma**2 * FS**2 / ((2 * np.pi) ** 2 * n * (n * n - 1))
            print(
                f"| {n} | {interp} | {np.sqrt(b[1, 1]):.4f} / {np.sqrt(asym):.4f} | {f.var() / b[1, 1]:.2f} | "
                f"{amp.var() / b[0, 0]:.2f} | {off.var() / b[3, 3]:.2f} | {f.mean() - f0:+.4f} |"
            )


def step_table():
    print(
        "| step (at 0.5 s, 4-cycle window N = 80, hop 20) | last sample off truth (tolerance) | samples after the step | converged during the straddle |"
    )
    print("|---|---|---|---|")
    for label, kw, tol, field in (
        ("frequency 50 -> 52 Hz", dict(f_step_to=52.0), 0.01, "f"),
        ("amplitude x0.5", dict(a_step_factor=0.5), 1e-6, "a"),
        ("phase +1 rad", dict(phase_step_rad=1.0), 1e-6, "p"),
    ):
        sc = SumOfTones(
            "s", "s", [Tone(50.0, 1.0, 0.3, t_step=0.5, **kw)], offset=0.5, sample_rate_hz=FS, duration_s=1.0
        )
        x, truth = sc.generate()
        tr = create("ipdft", FS, window_cycles=4, hop_samples=20).update(x)
        err = {
            "f": tr.frequency_hz[:, 0] - truth.frequency_hz[:, 0],
            "a": tr.amplitude[:, 0] - truth.amplitude[:, 0],
            "p": wrap_phase(tr.phase_rad[:, 0] - truth.phase_rad[:, 0]),
        }[field]
        bad = np.flatnonzero(~(np.abs(err) < tol))
        settle = bad[-1] + 1 - 500
        conv = tr.converged[500 : 500 + 80 + 20]
        print(f"| {label} | {tol:g} | {settle} | {conv.mean():.0%} of rows |")


def timing_table():
    print("| configuration | N | hop | bins | ns/sample, full track | ns/sample, last_only |")
    print("|---|---|---|---|---|---|")
    for fs, params in (
        (1000.0, {}),
        (5000.0, {}),
        (10_000.0, {}),
        (10_000.0, {"hop_samples": 20}),
        (10_000.0, {"min_frequency_hz": 20.0, "max_frequency_hz": 2000.0}),
    ):
        est = create("ipdft", fs, **params)
        _t, x = tone(50.3, 1024 * 40, fs=fs, noise=0.01)
        est.update(x[:-1024])
        block = np.ascontiguousarray(x[-1024:])
        res = ns_per_sample(est, block, reps=200)
        label = f"fs {fs:g} Hz" + ("".join(f", {k}={v}" for k, v in params.items()))
        print(
            f"| {label} | {est.window_samples} | {est.hop_samples} | {est.k_hi - est.k_lo + 3} | "
            f"{res[0]:.0f} | {res[1]:.0f} |"
        )


if __name__ == "__main__":
    bias_table()
    print()
    crlb_table()
    print()
    step_table()
    print()
    timing_table()
