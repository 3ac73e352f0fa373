"""Figures quoted in docs/estimators/sogi-fll.md. Run: .venv/bin/python docs/estimators/sogi_fll_figures.py

Deterministic (seeded); prints markdown tables. Timing figures depend on the machine and
its load.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.signal
from _timing import ns_per_sample  # docs/estimators/_timing.py: these scripts run from this folder

from sinewatch.estimators import create
from sinewatch.scenarios import SumOfTones, Tone, wrap_phase


def scen(fs, tones, offset=0.5, seconds=2.0, noise=0.0):
    return SumOfTones("s", "s", tones, offset=offset, sample_rate_hz=fs, duration_s=seconds, noise_std=noise)


def exactness_table():
    print(
        "| fs (Hz) | f / nominal (Hz) | max abs df (Hz) | max abs dA | max abs dB | max abs dphase (rad) | converged for good from (s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for fs in (1000.0, 5000.0, 50_000.0):
        for f, nom in ((47.0, 50.0), (53.0, 50.0), (62.0, 60.0)):
            x, tr_ = scen(fs, [Tone(f, 1.3, 0.7)], offset=-0.4).generate()
            tr = create("sogi-fll", fs, nominal_frequency_hz=nom).update(x)
            s = slice(int(1.5 * fs), None)
            m = [
                np.abs(tr.frequency_hz[s, 0] - f).max(),
                np.abs(tr.amplitude[s, 0] - 1.3).max(),
                np.abs(tr.offset[s] + 0.4).max(),
                np.abs(wrap_phase(tr.phase_rad[s, 0] - tr_.phase_rad[s, 0])).max(),
            ]
            conv = (np.flatnonzero(~tr.converged)[-1] + 1) / fs
            print(f"| {fs:g} | {f:g} / {nom:g} | " + " | ".join(f"{v:.1e}" for v in m) + f" | {conv:.3f} |")


def step_rate_table():
    print("| nominal (Hz) | fs (Hz) | Gamma (1/s) | step | t63 x Gamma | overshoot |")
    print("|---|---|---|---|---|---|")
    cases = [(50.0, 1000.0, g, df) for g in (20.0, 50.0) for df in (1.0, -3.0)]
    cases += [
        (50.0, 20_000.0, 50.0, 1.0),
        (50.0, 5000.0, 100.0, 1.0),
        (50.0, 5000.0, 150.0, 1.0),
        (50.0, 50_000.0, 200.0, 1.0),
        (1.0, 5.0, 1.0, 0.02),
        (400.0, 40_000.0, 400.0, 8.0),
    ]
    for nom, fs, g, df in cases:
        t_step = 30.0 / nom
        x, _ = scen(fs, [Tone(nom, 1.0, 0.3, t_step=t_step, f_step_to=nom + df)], seconds=45.0 / nom).generate()
        tr = create("sogi-fll", fs, nominal_frequency_hz=nom, gamma=g).update(x)
        frac = (tr.frequency_hz[round(t_step * fs) :, 0] - nom) / df
        t63 = np.flatnonzero(frac >= 1 - math.exp(-1))[0] / fs
        print(f"| {nom:g} | {fs:g} | {g:g} | {df:+g} Hz | {t63 * g:.2f} | {max(frac.max() - 1, 0):.0%} |")


def event_table():
    fs = 5000.0
    print(
        "| event at t = 1 s (50 Hz, fs 5 kHz, defaults) | amplitude within 1 % after | offset within 1e-3 after | max frequency excursion | frequency back within 0.01 Hz after |"
    )
    print("|---|---|---|---|---|")
    events = [
        ("amplitude x0.5", dict(a_step_factor=0.5), 0.0),
        ("amplitude x0.1 (sag)", dict(a_step_factor=0.1), 0.0),
        ("amplitude x2", dict(a_step_factor=2.0), 0.0),
        ("phase +1 rad", dict(phase_step_rad=1.0), 0.0),
        ("frequency +1 Hz", dict(f_step_to=51.0), 0.0),
        ("offset 0 -> 1", {}, 1.0),
    ]
    for label, kw, doff in events:
        t = np.arange(int(1.6 * fs)) / fs
        x, truth = scen(fs, [Tone(50.0, 1.0, 0.3, t_step=1.0, **kw)], offset=0.0, seconds=1.6).generate()
        x = x + np.where(t >= 1.0, doff, 0.0)
        for mem in (0.0, 2.0):
            tr = create("sogi-fll", fs, fll_amplitude_memory_cycles=mem).update(x)
            a = slice(int(fs), None)
            da = np.abs(tr.amplitude[a, 0] - truth.amplitude[a, 0]) / truth.amplitude[a, 0]
            db = np.abs(tr.offset[a] - doff)
            df = np.abs(tr.frequency_hz[a, 0] - truth.frequency_hz[a, 0])
            last = lambda e, tol: (np.flatnonzero(~(e <= tol))[-1] + 1) / fs
            name = f"{label}, fll_amplitude_memory_cycles=2" if mem else label
            print(
                f"| {name} | {last(da, 0.01) * 1e3:.0f} ms | {last(db, 1e-3) * 1e3:.0f} ms | "
                f"{df.max():.2f} Hz | {last(df, 0.01) * 1e3:.0f} ms |"
            )


def prewarped(fs, f, k=1.4142135623730951, kd=0.25):  # k = sqrt(2)
    h = 1.0 / fs
    wc = 2.0 / h * math.tan(math.pi * f * h)
    a = wc * np.array([[-k, -1.0, -k], [1.0, 0.0, 0.0], [-kd, 0.0, -kd]])
    b = wc * np.array([[k], [0.0], [kd]])
    return scipy.signal.cont2discrete((a, b, np.eye(3), np.zeros((3, 1))), h, method="bilinear")[:4]


def noise_table():
    print(
        "| sigma (A = 1) | std(B) measured / predicted | std(A) measured / predicted | std(f) (Hz) | mean df (Hz) | one-step residual / sigma |"
    )
    print("|---|---|---|---|---|---|")
    fs, f = 5000.0, 50.3
    ad, bd, cd, dd = prewarped(fs, f)
    xs = np.zeros(3)
    e = np.zeros(3)
    for i in range(4000):
        u = 1.0 if i == 0 else 0.0
        y = cd @ xs + dd[:, 0] * u
        e += y**2
        xs = ad @ xs + bd[:, 0] * u
    for sigma in (0.001, 0.01, 0.1):
        x, _ = scen(fs, [Tone(f, 1.0, 0.3)], seconds=20.0, noise=sigma).generate(seed=4)
        est = create("sogi-fll", fs)
        tr = est.update(x[: int(fs)])
        tr = est.update(x[int(fs) :])
        pb, pa = sigma * math.sqrt(e[2]), sigma * math.sqrt(0.5 * (e[0] + e[1]))
        print(
            f"| {sigma:g} | {tr.offset.std():.3g} / {pb:.3g} | {tr.amplitude[:, 0].std():.3g} / {pa:.3g} | "
            f"{tr.frequency_hz[:, 0].std():.3g} | {tr.frequency_hz[:, 0].mean() - f:+.1e} | {tr.residual_rms / sigma:.2f} |"
        )


def harmonic_table():
    print("| harmonic (of 50.3 Hz, 5 %) | mean df (Hz) | f ripple p-p (Hz) | A ripple p-p | converged |")
    print("|---|---|---|---|---|")
    fs = 5000.0
    for h in (2, 3, 5, 7):
        x, _ = scen(fs, [Tone(50.3, 1.0, 0.3), Tone(50.3 * h, 0.05, 0.1)], seconds=3.0).generate()
        tr = create("sogi-fll", fs).update(x)
        s = slice(int(fs), None)
        fh = tr.frequency_hz[s, 0]
        print(
            f"| {h} | {fh.mean() - 50.3:+.1e} | {np.ptp(fh):.3f} | {np.ptp(tr.amplitude[s, 0]):.3f} | {tr.converged[s].mean():.0%} |"
        )


def timing_table():
    print("| fs (Hz) | ns/sample, full track | ns/sample, last_only |")
    print("|---|---|---|")
    for fs in (5000.0, 50_000.0):
        est = create("sogi-fll", fs)
        x, _ = scen(fs, [Tone(50.3, 1.0, 0.3)], seconds=1024 * 20 / fs, noise=0.01).generate()
        est.update(x[:-1024])
        block = np.ascontiguousarray(x[-1024:])
        res = ns_per_sample(est, block, reps=500)
        print(f"| {fs:g} | {res[0]:.0f} | {res[1]:.0f} |")


if __name__ == "__main__":
    for table in (exactness_table, step_rate_table, event_table, noise_table, harmonic_table, timing_table):
        table()
        print()
