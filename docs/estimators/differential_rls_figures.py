"""Figures quoted in docs/estimators/differential-rls.md.

Run: .venv/bin/python docs/estimators/differential_rls_figures.py

Deterministic (seeded) except the timing section, which depends on the machine and its load
(it also times ges-kalman in the same run, as a yardstick).
"""

from __future__ import annotations

import time

import numpy as np

from sinewatch.estimators import create, get
from sinewatch.estimators.differential_rls import (
    band_limited_iq_noise,
    baseband_estimate,
    cyclic_intervals,
    differential_rls_kernel,
)
from sinewatch.scenarios import get as get_scenario
from sinewatch.scenarios.papers import paper001_baseband

W = 1.0
FS = 1000.0
P50 = {"nominal_frequency_hz": 50.0, "bandwidth_hz": 5.0}


def fig1():
    print("## Fig. 1: noise-free, w = 1 rad/s, n = 4, dt = 0.6 / 0.54 s cyclic, lam = 0.995, LS\n")
    k = 3000
    dt, t, c = paper001_baseband(k, [0.6, 0.54], W)
    opts = {"n_terms": 4, "forgetting_factor": 0.995, "els": False, "p0": 1e4}
    r = baseband_estimate(c, dt, **opts)
    ref = baseband_estimate(c, dt, **{**opts, "p0": 1e12})
    rc = baseband_estimate(c, dt, **opts, recenter_every=10)
    err = np.abs(r["frequency_rad_s"] - W)
    d = np.abs(r["frequency_rad_s"] - ref["frequency_rad_s"])
    errc = np.abs(rc["frequency_rad_s"] - W)
    print("| sample k | t (s) | t / period | relative error | prior share | with re-centring |")
    print("|---|---|---|---|---|---|")
    for kk in (2, 3, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 2999):
        print(f"| {kk} | {t[kk]:.2f} | {t[kk] / (2 * np.pi):.2f} | {err[kk]:.1e} | {d[kk]:.1e} | {errc[kk]:.1e} |")
    s = lambda a, b: np.log(d[b] / d[a]) / (b - a)
    print(f"\nlog-slope of the prior share: k 2-8 {s(2, 8):.3f}, k 8-32 {s(8, 32):.4f}, "
          f"k 1024-2048 {s(1024, 2048):.5f}; ln(lam) = {np.log(0.995):.5f}\n")  # fmt: skip


def fig2():
    print("## Fig. 2: 5.2 dB (sigma^2 = .15 per component), M = 5, n = 2, dt = T_sN / 5 = 0.314 s\n")
    m, k = 5, 6000
    t0 = (np.pi / 2) / m
    dt, _, c = paper001_baseband(k, [t0], W)
    opts = {"n_terms": 2, "forgetting_factor": 0.995, "p0": 1e4}
    free = baseband_estimate(c, dt, els=False, **opts)["frequency_rad_s"]
    rows = {"LS": {"els": False}, "ELS rho=0.9, r1=sinc(1/5)": {"els": True, "els_damping": 0.9,
                                                                       "noise_correlation": np.sinc(1 / m)},
            "ELS rho=0.9, r1=0 (white model)": {"els": True, "els_damping": 0.9}}  # fmt: skip
    print(f"noise-free (truncation of n = 2 at w dt = 0.31): {free[-1] - W:+.4f} rad/s\n")
    print("| algorithm | bias (rad/s) | RMS (rad/s) | RMS error, samples 2-11 |")
    print("|---|---|---|---|")
    noisy = [c + band_limited_iq_noise(k, m, 0.15, s) for s in range(8)]
    for name, kw in rows.items():
        b, r, e10 = [], [], []
        for cn in noisy:
            f = baseband_estimate(cn, dt, **opts, **kw)["frequency_rad_s"]
            b.append(f[1000:].mean() - W)
            r.append(f[1000:].std())
            e10.append(f[2:12] - W)
        print(f"| {name} | {np.mean(b):+.4f} | {np.mean(r):.4f} | {np.sqrt(np.mean(np.square(e10))):.3f} |")
    print(f"\nnoise-free error, samples 2-11: {np.abs(free[2:12] - W).mean():.4f} rad/s")
    dn = np.diff(band_limited_iq_noise(2**18, 10, 1.0, 99).real)
    print(f"eq. (14): E[dn^2]/sigma^2 = 2 (1 - sinc(1/M)): M=10 {2 * (1 - np.sinc(0.1)):.4f} "
          f"(simulated {np.mean(dn**2):.4f}), M=5 {2 * (1 - np.sinc(0.2)):.4f}\n")  # fmt: skip


def white():
    print("## White I/Q noise (the model of eq. 11), sigma^2 = .15, n = 2, dt = 0.2 s, 4 seeds\n")
    k, dt0 = 4000, 0.2
    dt, _, tone = paper001_baseband(k, [dt0], W)
    opts = {"n_terms": 2, "forgetting_factor": 0.995, "p0": 1e4}
    print("| algorithm | bias (rad/s) | RMS (rad/s) |")
    print("|---|---|---|")
    for name, kw in (("LS", {"els": False}), ("ELS rho=0.5", {"els_damping": 0.5}),
                     ("ELS rho=0.9", {"els_damping": 0.9}), ("ELS rho=0.95", {"els_damping": 0.95})):  # fmt: skip
        b, r = [], []
        for seed in range(4):
            rng = np.random.default_rng(seed)
            c = tone + np.sqrt(0.15) * (rng.standard_normal(k) + 1j * rng.standard_normal(k))
            f = baseband_estimate(c, dt, **opts, **kw)["frequency_rad_s"][500:]
            b.append(f.mean() - W)
            r.append(f.std())
        print(f"| {name} | {np.mean(b):+.4f} | {np.mean(r):.4f} |")
    print(f"\ntheory: LS {-0.3 / 1.3 - dt0**2 / 6:+.4f}, truncation floor {-(dt0**2) / 6:+.4f}\n")


def fig3():
    print("## Fig. 3: w(t) = w0 [1 + 0.5 sin(0.01 w0 t)], n = 4, Fig. 1 sampling, noise-free, t > 200 s\n")
    k = 3333
    dt = cyclic_intervals(k, [0.6, 0.54])
    t = np.cumsum(dt)
    c = np.exp(1j * (0.3 + W * t - 50.0 * (np.cos(0.01 * W * t) - 1.0)))
    wt = W * (1 + 0.5 * np.sin(0.01 * W * t))
    rt = 0.005 * W**2 * np.cos(0.01 * W * t)
    sel = t > 200
    print("| lam | derivative model | max abs error (rad/s) | RMS error (rad/s) | ROCOF RMS error (rad/s^2) |")
    print("|---|---|---|---|---|")
    for lam in (0.9, 0.95, 0.98):
        for deriv in (False, True):
            r = baseband_estimate(c, dt, n_terms=4, rocof_model=deriv, forgetting_factor=lam, els=False,
                                  recenter_every=10)  # fmt: skip
            e = r["frequency_rad_s"][sel] - wt[sel]
            re = np.sqrt(np.mean((r["rocof_rad_s2"][sel] - rt[sel]) ** 2)) if deriv else float("nan")
            print(f"| {lam} | {deriv} | {np.abs(e).max():.2e} | {np.sqrt(np.mean(e**2)):.2e} | {re:.1e} |")
    print()


def real_input():
    print("## Real input, 1 kHz, nominal 50 Hz, bandwidth 5 Hz (defaults otherwise)\n")
    n = 20_000
    t = np.arange(n) / FS
    print(
        "| signal | first converged (s) | f error mean (Hz) | f std (Hz) | phase std (rad) | amplitude std | offset std |"
    )
    print("|---|---|---|---|---|---|---|")
    for noise in (0.01, 0.1):
        x = 0.5 + np.sin(2 * np.pi * 50.3 * t + 0.3) + noise * np.random.default_rng(0).standard_normal(n)
        tr = create("differential-rls", FS, **P50).update(x)
        ss = t > 5
        fe = tr.frequency_hz[ss, 0] - 50.3
        pe = np.angle(np.exp(1j * (tr.phase_rad[ss, 0] - (2 * np.pi * 50.3 * t[ss] + 0.3))))
        print(f"| 0.5 + sin(2 pi 50.3 t + 0.3) + {noise} N(0,1) | {np.argmax(tr.converged) / FS:.3f} | "
              f"{fe.mean():+.1e} | {fe.std():.1e} | {pe.std():.1e} | {tr.amplitude[ss, 0].std():.1e} | "
              f"{tr.offset[ss].std():.1e} |")  # fmt: skip
    print()
    sc = get_scenario("rocof-demo")
    x, truth = sc.generate(seed=1)
    print("rocof-demo (50 Hz + 1 Hz/s, 10 kHz, noise 0.01), t > 2 s:\n")
    print("| parameters | ROCOF error (Hz/s) mean +- std | max abs | f error max (Hz) | phase error max (rad) |")
    print("|---|---|---|---|---|")
    ss = np.arange(x.size) / sc.sample_rate_hz > 2.0
    for label, extra in (("suggested", {}), ("forgetting_factor 0.99", {"forgetting_factor": 0.99}),
                         ("els off", {"els": False}), ("recenter_every 25", {"recenter_every": 25}),
                         ("rocof_model off", {"rocof_model": False})):  # fmt: skip
        tr = create(sc.suggested_estimator, sc.sample_rate_hz, **{**sc.suggested_params, **extra}).update(x)
        re = tr.extras["rocof_hz_per_s"][ss] - truth.rocof_hz_per_s[ss, 0]
        fe = np.abs(tr.frequency_hz[ss, 0] - truth.frequency_hz[ss, 0]).max()
        pe = np.abs(np.angle(np.exp(1j * (tr.phase_rad[ss, 0] - truth.phase_rad[ss, 0])))).max()
        rs = (
            f"{np.nanmean(re):+.1e} +- {np.nanstd(re):.1e} | {np.nanmax(np.abs(re)):.1e}"
            if np.isfinite(re).any()
            else "n/a | n/a"
        )
        print(f"| {label} | {rs} | {fe:.1e} | {pe:.1e} |")
    print()
    x = np.sin(2 * np.pi * 54.5 * t[:10_000])
    fixed = create("differential-rls", FS, **P50, recenter_every=0, rocof_model=False, els=False).update(x)
    moved = create("differential-rls", FS, **P50).update(x)
    print(f"54.5 Hz (offset 4.5 Hz): reference fixed {fixed.frequency_hz[-1, 0]:.5f} Hz, "
          f"re-centred {moved.frequency_hz[-1, 0]:.7f} Hz\n")  # fmt: skip
    # step responses
    tt = np.arange(12_000) / FS
    f = np.where(tt < 5, 50.0, 52.0)
    xs = np.sin(2 * np.pi * np.cumsum(f) / FS)
    tr = create("differential-rls", FS, **P50).update(xs)
    print("frequency step 50 -> 52 Hz at 5 s (noise-free): time (s) / estimate (Hz) / converged:",
          ", ".join(f"{s}: {tr.frequency_hz[int(s * FS), 0]:.3f} {bool(tr.converged[int(s * FS)])}"
                    for s in (5.1, 5.3, 5.5, 6.0, 7.0, 8.0, 10.0)))  # fmt: skip
    xa = np.sin(2 * np.pi * 50.1 * tt) * np.where(tt < 5, 1.0, 10.0)
    tr = create("differential-rls", FS, **P50).update(xa)
    print("amplitude step x10 at 5 s: time (s) / amplitude / converged:",
          ", ".join(f"{s}: {tr.amplitude[int(s * FS), 0]:.3f} {bool(tr.converged[int(s * FS)])}"
                    for s in (5.1, 5.2, 5.3, 5.5, 6.0)))  # fmt: skip
    xr = np.sin(2 * np.pi * 50.2 * tt)
    xr[(tt > 5) & (tt < 8)] = 0.0
    tr = create("differential-rls", FS, **P50).update(xr)
    gone = np.argmax(np.isnan(tr.frequency_hz[5000:, 0])) / FS
    back = 8.0 + np.argmax(tr.converged[8000:]) / FS
    print(
        f"signal stopped at 5 s: outputs NaN from {5 + gone:.2f} s; resumed at 8 s: converged again at {back:.2f} s\n"
    )


def timing():
    print("## Speed (the machine this runs on, now; compare estimators with `sinewatch bench kernels`)\n")
    cls = get("differential-rls")
    for label, fs, extra in (("example: fs 1 kHz, decimation 10, p = 5", 1000.0, {}),
                             ("fs 10 kHz, decimation 100, p = 5", 10_000.0, {}),
                             ("fs 1 kHz, n_terms 4, no ROCOF (p = 4, cyclic 20/18)", 1000.0,
                              {"n_terms": 4, "rocof_model": False, "oversampling": 5.0}),
                             ("fs 1 kHz, n_terms 4 with ROCOF (p = 14, cyclic 20/18)", 1000.0,
                              {"n_terms": 4, "oversampling": 5.0})):  # fmt: skip
        est = cls(fs, {**P50, **extra})
        t = np.arange(20_000) / fs
        x = 0.5 + np.sin(2 * np.pi * 50.3 * t + 0.3) + 0.01 * np.random.default_rng(1).standard_normal(t.size)
        est.update(x[:10_000])
        blk = np.ascontiguousarray(x[10_000:11_024])
        args = (*est._state.values(), *est._constants)  # the kernel convention (estimators/base.py)
        differential_rls_kernel(blk, *args, False)
        reps = 2000
        best = []
        for last_only in (False, True):
            runs = []
            for _ in range(5):
                t1 = time.perf_counter()
                for _ in range(reps):
                    differential_rls_kernel(blk, *args, last_only)
                runs.append((time.perf_counter() - t1) / reps / blk.size * 1e9)
            best.append(min(runs))
        print(f"- {label}: {best[0]:.1f} ns/sample full track, {best[1]:.1f} ns/sample last_only "
              f"(kernel, 1024-sample block, best of 5)")  # fmt: skip
    print()


if __name__ == "__main__":
    fig1()
    fig2()
    white()
    fig3()
    real_input()
    timing()
