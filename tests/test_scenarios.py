"""The scenario library (what the bench, the feed, the demo and the tests read):
registration, truth consistent with the samples (phase is the integral of frequency,
frequency the integral of ROCOF), the papers' signals, the C37.118.1-style tests, gaps and
noise levels, the bench metadata derived for the demo feeds, and the deploy rules that
serve the demo scenarios."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sinewatch import scenarios
from sinewatch.scenarios._library import Component, Composite

LIBRARY = [n for n in scenarios.names() if isinstance(scenarios.get(n), Composite)]


def test_library_is_registered_with_tags():
    names = set(scenarios.names())
    expected = {
        "paper000-tone",
        "paper000-chirp",
        "paper001-tone",
        "paper001-tone-noisy",
        "paper001-fm",
        "paper003-harmonic-10",
        "paper003-harmonic-100",
        "paper003-harmonic-1000",
        "paper004-ex1",
        "paper004-ex1-noisy",
        "paper004-ex2",
        "paper004-ex3",
        "paper004-experiment",
        "tone-snr-00db",
        "tone-snr-60db",
        "tone-nobias-snr-40db",
        "c37-50hz-steady",
        "c37-60hz-off-m5",
        "c37-50hz-harmonic-50",
        "c37-60hz-oob-low",
        "c37-50hz-ramp-down",
        "c37-60hz-am-5hz",
        "c37-50hz-pm-2hz",
        "c37-50hz-step-amp-m10",
        "c37-60hz-step-phase-p10",
        "c37-50hz-dc-offset",
        "c37-60hz-dc-decay",
        "gap-dropout-200ms",
        "gap-dropout-5s",
        "gap-skip-105ms",
        "multitone-2-separated",
        "multitone-2-close",
        "multitone-2-weak",
        "multitone-3",
    }
    assert expected <= names and expected <= set(LIBRARY)
    for name in LIBRARY:
        sc = scenarios.get(name)
        assert sc.name == name and sc.summary and sc.tags, name
    assert all(
        "c37.118" in scenarios.get(n).tags and "phasor" in scenarios.get(n).tags
        for n in LIBRARY
        if n.startswith("c37-")
    )
    assert {"snr", "paper", "gap", "multitone", "quick"} <= {t for n in LIBRARY for t in scenarios.get(n).tags}


@pytest.mark.parametrize("name", LIBRARY)
def test_truth_is_consistent_with_the_samples(name):
    sc = scenarios.get(name, noise_std=0.0)
    sc.uniform_noise = 0.0
    n = min(sc.n_samples, 40_000)
    y, truth = sc.generate(0, n=n)
    k = sc.n_components
    assert y.shape == (n,) and truth.frequency_hz.shape == (n, k) and truth.offset.shape == (n,)
    assert np.isfinite(y).all() and np.isfinite(truth.frequency_hz).all()
    assert len(sc.bench.nominal_frequency_hz) == k
    # samples = offset + sum A sin(phase) + the disturbances the truth leaves out
    model = truth.offset + np.sum(truth.amplitude * np.sin(truth.phase_rad), axis=1)
    t = np.arange(n) / sc.sample_rate_hz
    dist = sum((d.evaluate(sc._time(t))[1] * np.sin(d.evaluate(sc._time(t))[2]) for d in sc.disturbances), np.zeros(n))
    if sc.dropout is not None:
        dist = np.where((t >= sc.dropout[0]) & (t < sc.dropout[1]), 0.0, dist)
    np.testing.assert_allclose(y, model + dist, atol=1e-9)
    # phase advances by the frequency (trapezoid over one sample), ROCOF is d frequency / dt
    fs = sc.sample_rate_hz
    dphase = np.angle(np.exp(1j * np.diff(truth.phase_rad, axis=0)))
    expect = np.pi * (truth.frequency_hz[1:] + truth.frequency_hz[:-1]) / fs
    jumps = np.abs(dphase - np.angle(np.exp(1j * expect)))
    smooth = np.ones(n - 1, dtype=bool)
    for c in sc.components:  # steps and lost samples jump by design
        if math.isfinite(c.t_step):
            smooth &= np.abs(t[1:] - c.t_step) > 1.5 / fs
    if sc.skip is not None:
        smooth &= np.abs(t[1:] - sc.skip[0]) > 1.5 / fs
    assert jumps[smooth].max() < 1e-6 + 1e-3 * np.abs(expect[smooth]).max(), name
    drocof = np.diff(truth.frequency_hz, axis=0) * fs
    mean_rocof = 0.5 * (truth.rocof_hz_per_s[1:] + truth.rocof_hz_per_s[:-1])
    ok = ~smooth[:, None] | (np.abs(drocof - mean_rocof) < 1e-6 + 1e-3 * np.abs(mean_rocof))
    edges = (~ok).sum()  # ramp ends: one sample each
    assert edges <= 2 * k, name


def test_streaming_in_blocks_equals_one_read_with_gaussian_and_uniform_noise():
    for name in ("tone-snr-20db", "paper004-ex1-noisy"):
        sc = scenarios.get(name, duration_s=0.5)
        whole, _ = sc.generate(3)
        s = sc.stream(3)
        parts = [s.read(m)[0] for m in (1, 17, 400, sc.n_samples - 418)]
        np.testing.assert_array_equal(np.concatenate(parts), whole)


def test_snr_definition():
    for snr in (0, 30, 60):
        sc = scenarios.get(f"tone-snr-{snr:02d}db")
        assert 10 * math.log10(1.0 / (2 * sc.noise_std**2)) == pytest.approx(snr)
        y, truth = sc.generate(0)
        assert np.std(y - truth.offset - truth.amplitude[:, 0] * np.sin(truth.phase_rad[:, 0])) == pytest.approx(
            sc.noise_std, rel=0.05
        )


def test_paper000_signals():
    y, tr = scenarios.get("paper000-tone", noise_std=0.0).generate(0, n=1000)
    t = np.arange(1000) / 1000.0
    np.testing.assert_allclose(y, np.sin(2 * np.pi * 100 * t) + 1.0, atol=1e-12)  # s(t) = sin(2 pi 100 t) + 1
    sc = scenarios.get("paper000-chirp")
    assert sc.noise_std == 0.01 and sc.sample_rate_hz == 1000.0
    _, tr = sc.generate(0)
    assert tr.frequency_hz[180_000, 0] == pytest.approx(180.0)  # f(t) = t Hz


def test_paper001_frequency_tracking_signal():
    sc = scenarios.get("paper001-fm")
    _, tr = sc.generate(0)
    t = np.arange(sc.n_samples) / sc.sample_rate_hz
    w = 2 * np.pi * tr.frequency_hz[:, 0]
    np.testing.assert_allclose(w, 1.0 * (1 + 0.5 * np.sin(0.01 * t)), atol=1e-12)  # w0 [1 + 0.5 sin(0.01 w0 t)]
    noisy = scenarios.get("paper001-tone-noisy")
    assert 10 * math.log10(1.0 / (2 * noisy.noise_std**2)) == pytest.approx(5.2, abs=0.05)  # "5.2 dB"


def test_paper003_truth_is_the_fundamental_only():
    sc = scenarios.get("paper003-harmonic-100")
    y, tr = sc.generate(0)
    t = np.arange(sc.n_samples) / sc.sample_rate_hz
    np.testing.assert_allclose(y, 2 * np.sin(3 * t) + 0.2 * np.sin(100 * t), atol=1e-9)
    assert tr.frequency_hz.shape[1] == 1 and tr.amplitude[0, 0] == 2.0
    assert sc.bench.reference["frequency_rad_s_std"] == 0.0142  # Fig. 5 caption


def test_paper004_examples():
    y, tr = scenarios.get("paper004-ex1-noisy").generate(0)
    clean = np.sin(tr.phase_rad[:, 0]) + np.sin(tr.phase_rad[:, 1])
    d = y - clean
    assert np.abs(d).max() <= 0.25 and np.abs(d).max() > 0.249  # uniform in [-0.25, 0.25]
    assert np.std(d) == pytest.approx(0.25 / math.sqrt(3), rel=0.01)
    sc = scenarios.get("paper004-ex2")
    _, tr = sc.generate(0)
    t = np.arange(sc.n_samples) / sc.sample_rate_hz
    assert np.all(tr.amplitude[t < 120, 1] == 3.0) and np.all(tr.amplitude[t >= 120, 1] == 0.0)
    assert np.all(tr.offset == 1.0)
    sc = scenarios.get("paper004-ex3")
    _, tr = sc.generate(0)
    w = 2 * np.pi * tr.frequency_hz
    t = np.arange(sc.n_samples) / sc.sample_rate_hz
    np.testing.assert_allclose(w[t < 70], [[2.0, 5.0]] * int((t < 70).sum()))
    np.testing.assert_allclose(w[t >= 70], [[3.0, 4.5]] * int((t >= 70).sum()))
    assert scenarios.get("paper004-ex1").sample_rate_hz == pytest.approx(1 / 3e-4)


def _spectrum_peak(y: np.ndarray, fs: float, f: float) -> float:
    n = y.size
    win = np.hanning(n)
    spec = np.abs(np.fft.rfft(y * win)) * 2 / win.sum()
    return float(spec[round(f * n / fs)])


def test_c37_harmonic_and_interference_levels():
    for f0 in (50, 60):
        sc = scenarios.get(f"c37-{f0}hz-harmonic-7")
        y, tr = sc.generate(0)
        assert _spectrum_peak(y, sc.sample_rate_hz, 7 * f0) == pytest.approx(0.1, rel=1e-3)
        assert np.all(tr.frequency_hz == f0)
        assert scenarios.get(f"c37-{f0}hz-harmonic-7", harmonic=50).disturbances[0].f0 == 50 * f0
    sc = scenarios.get("c37-50hz-oob-low")
    y, _ = sc.generate(0)
    assert _spectrum_peak(y, sc.sample_rate_hz, 24.0) == pytest.approx(0.1, rel=1e-3)
    with pytest.raises(ValueError):
        scenarios.get("c37-50hz-harmonic-2", harmonic=51)


def test_c37_ramp_modulation_and_steps():
    sc = scenarios.get("c37-60hz-ramp-down")
    _, tr = sc.generate(0)
    t = np.arange(sc.n_samples) / sc.sample_rate_hz
    assert tr.frequency_hz[t < 1, 0] == pytest.approx(65.0)
    assert tr.frequency_hz[t > 11, 0] == pytest.approx(55.0)
    assert np.all(tr.rocof_hz_per_s[(t > 1) & (t < 11), 0] == -1.0)
    _, tr = scenarios.get("c37-50hz-am-2hz").generate(0)
    assert tr.amplitude.max() == pytest.approx(1.1) and tr.amplitude.min() == pytest.approx(0.9, abs=1e-6)
    _, tr = scenarios.get("c37-50hz-pm-5hz").generate(0)
    # phase modulation 0.1 cos(2 pi 5 t - pi): frequency deviation 0.1 * 5 = 0.5 Hz peak
    assert np.abs(tr.frequency_hz - 50.0).max() == pytest.approx(0.5, rel=1e-4)
    sc = scenarios.get("c37-50hz-step-phase-m10")
    _, tr = sc.generate(0)
    i = int(1.5 * sc.sample_rate_hz)
    jump = np.angle(np.exp(1j * (tr.phase_rad[i] - tr.phase_rad[i - 1] - 2 * np.pi * 50 / sc.sample_rate_hz)))
    assert math.degrees(jump[0]) == pytest.approx(-10.0)
    _, tr = scenarios.get("c37-50hz-step-amp-p10").generate(0)
    assert tr.amplitude[0, 0] == 1.0 and tr.amplitude[-1, 0] == pytest.approx(1.1)
    assert scenarios.get("c37-60hz-step-amp-p10").bench.limits["response_time_s"] == pytest.approx(7 / 60)


def test_gaps():
    sc = scenarios.get("gap-dropout-200ms")
    y, tr = sc.generate(0)
    t = np.arange(sc.n_samples) / sc.sample_rate_hz
    gap = (t >= 2.0) & (t < 2.2)
    assert np.std(y[gap]) == pytest.approx(sc.noise_std, rel=0.15)  # noise only
    assert np.all(tr.amplitude[gap] == 0) and np.all(tr.offset[gap] == 0)
    sc = scenarios.get("gap-skip-105ms", noise_std=0.0)
    y, tr = sc.generate(0)
    i = int(2.0 * sc.sample_rate_hz)
    expect = 0.2 + np.sin(2 * np.pi * 50.3 * (2.0 + 0.105) + 0.3)
    assert y[i] == pytest.approx(expect)


def test_multitone_nominal_frequencies_are_off_by_ten_percent():
    sc = scenarios.get("multitone-3")
    _, tr = sc.generate(0, n=1)
    np.testing.assert_allclose(sc.bench.nominal_frequency_hz, [45.0, 121.0, 153.0])
    np.testing.assert_allclose(tr.frequency_hz[0], [50.0, 110.0, 170.0])


def test_component_rejects_step_with_modulation():
    with pytest.raises(ValueError):
        Component(50.0, rocof=1.0, t_step=1.0, f_step_to=51.0)


def test_deploy_rules_serve_each_demo_scenario_with_its_suggested_estimator():
    # deploy/estimators-demo.toml serves `sinewatch feed --scenario NAME`: its rules must
    # say what the scenario library says (as `sinewatch demo` reads it)
    from pathlib import Path

    from sinewatch.schemas.config import load_config

    config = load_config(Path(__file__).parents[1] / "deploy" / "estimators-demo.toml")
    *rules, catch_all = config.rules
    assert catch_all.match == "sinewatch/in/**"
    served = {}
    for rule in rules:
        name = rule.match.removeprefix("sinewatch/in/sim/").removesuffix("/**")
        sc = scenarios.get(name)
        assert (rule.estimator, rule.params) == (sc.suggested_estimator, sc.suggested_params), name
        served[name] = rule.estimator
    assert set(served) == {n for n in scenarios.names() if "demo" in scenarios.get(n).tags}


def test_bench_metadata_is_derived_from_the_truth_for_the_demo_feeds():
    # declared by the library's scenarios; for a feed that declares none, read off its truth
    # at t = 0: the true frequencies as nominal, half the lowest to twice the highest (at
    # most 0.45 fs) as range, the second half as steady window, and no CRLB comparison
    ramp = scenarios.get("demo-ramp", duration_s=4.0)
    info = ramp.bench
    assert info.nominal_frequency_hz == (48.0,) and info.frequency_range_hz == (24.0, 96.0)
    assert info.steady_windows == ((2.0, 4.0),) and info.events == () and not info.crlb
    sc = scenarios.get("grip-section-v")  # a Scenario of its own, not a Composite
    assert sc.bench.nominal_frequency_hz == pytest.approx((1 / (2 * math.pi),))
    assert sc.bench.frequency_range_hz[1] == pytest.approx(2 / (2 * math.pi))
    declared = scenarios.get("tone-snr-40db")
    assert declared.bench.nominal_frequency_hz == (50.0,) and declared.bench.crlb and declared.is_stationary
    # what `sinewatch bench scenarios` lists is the scenario's own description
    row = scenarios.get("multitone-3").describe()
    assert row["components"] == 3 and row["nominal_frequency_hz"] == pytest.approx([45.0, 121.0, 153.0])
