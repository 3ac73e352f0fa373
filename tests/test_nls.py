"""``nls``: the windowed maximum-likelihood fit of K tones against the exact finite-window
Cramer-Rao bound (``sinewatch.crlb``), its reported standard deviations against the errors
they describe, and its choice of the number of tones on the multitone scenarios and on the
multi-sine examples of Chen, Pin, Ng, Hui and Parisini (paper 004).

Monte Carlo trials (``sinewatch.apps.bench.crlb_window``, which also prints the table) are
seeded; each trial is one window of fresh noise, random phases and frequencies jittered by
up to half a DFT bin, and one estimate at the window's last sample.
"""

from __future__ import annotations

import numpy as np
import pytest

from sinewatch import crlb
from sinewatch import scenarios as sc_registry
from sinewatch.apps.bench import crlb_window
from sinewatch.estimators import create

FS = 1000.0
PARAMS = ("frequency_hz", "amplitude", "phase_rad")


def _wrap(p: np.ndarray) -> np.ndarray:
    return np.pi - np.mod(np.pi - p, 2.0 * np.pi)


def _check(res: dict[str, np.ndarray], max_db: float, what: str) -> None:
    db, cal = res["db"], res["calibration"]
    assert float(res["converged"]) == 1.0, f"{what}: converged in {float(res['converged']):.0%} of trials"
    for j in range(db.shape[0]):
        for p, name in enumerate((*PARAMS, "offset")):
            assert abs(db[j, p]) <= max_db, f"{what} tone {j} {name}: {db[j, p]:+.2f} dB from the CRLB"
            assert 0.9 <= cal[j, p] <= 1.1, f"{what} tone {j} {name}: sd(error / reported sd) = {cal[j, p]:.3f}"


def test_crlb_tones_of_one_tone_is_crlb():
    one = crlb.crlb(300, 50.3, 1.2, 0.7, 0.1, FS)
    (k1,) = crlb.crlb_tones(300, [50.3], [1.2], [0.7], 0.1, FS)
    for q in ("frequency_hz", "amplitude", "phase_rad", "offset"):
        assert getattr(k1, q) == pytest.approx(getattr(one, q), rel=1e-10)
    # a second tone two bins away costs the first a little, never nothing
    two = crlb.crlb_tones(300, [50.3, 50.3 + 2 * FS / 300], [1.2, 1.0], [0.7, 0.1], 0.1, FS)
    assert two[0].frequency_hz > one.frequency_hz


def monte_carlo(n: int, freqs: list[float], amps: list[float], snr_db: float, trials: int, seed: int):
    return crlb_window.monte_carlo("nls", crlb_window.Case(n, tuple(freqs), tuple(amps), snr_db), trials, seed)


# ---- at the bound -------------------------------------------------------------------------------


@pytest.mark.parametrize("snr_db", [10, 25, 40])
def test_single_tone_within_1_db_of_the_crlb_and_calibrated(snr_db):
    res = monte_carlo(512, [50.0], [1.0], snr_db, trials=300, seed=snr_db)
    _check(res, 1.0, f"{snr_db} dB")


@pytest.mark.slow
@pytest.mark.parametrize("n", [256, 1024])
@pytest.mark.parametrize("snr_db", [10, 15, 20, 25, 30, 35, 40])
def test_single_tone_within_1_db_of_the_crlb_and_calibrated_1000_trials(snr_db, n):
    res = monte_carlo(n, [50.0], [1.0], snr_db, trials=1000, seed=1000 + snr_db + n)
    _check(res, 1.0, f"N={n}, {snr_db} dB")


@pytest.mark.parametrize("snr_db", [20, 40])
def test_two_tones_two_bins_apart_within_1_5_db_and_calibrated(snr_db):
    n = 512
    res = monte_carlo(n, [50.0, 50.0 + 2.0 * FS / n], [1.0, 0.7], snr_db, trials=300, seed=100 + snr_db)
    _check(res, 1.5, f"{snr_db} dB")


@pytest.mark.slow
@pytest.mark.parametrize("bins", [2, 3, 5])
@pytest.mark.parametrize("snr_db", [10, 20, 30, 40])
def test_two_tones_within_1_5_db_and_calibrated_1000_trials(snr_db, bins):
    n = 512
    res = monte_carlo(n, [50.0, 50.0 + bins * FS / n], [1.0, 0.7], snr_db, trials=1000, seed=200 + snr_db + bins)
    _check(res, 1.5, f"{bins} bins, {snr_db} dB")


def test_reported_std_is_the_crlb_at_the_estimate():
    """With sigma estimated from the residual, the reported sd of each parameter is the
    exact bound's (within the ~2 % of the sigma estimate on 2048 samples)."""
    rng = np.random.default_rng(5)
    n, sigma = 2048, 0.05
    t = np.arange(n) / FS
    f, a = [61.3, 143.9], [1.0, 0.3]
    x = 0.2 + a[0] * np.sin(2 * np.pi * f[0] * t + 0.4) + a[1] * np.sin(2 * np.pi * f[1] * t - 1.0)
    x = x + sigma * rng.standard_normal(n)
    tr = create("nls", FS, n_components=2, min_frequency_hz=20.0, window_samples=n).update(x, last_only=True)
    ph = _wrap(2 * np.pi * np.array(f) * t[-1] + np.array([0.4, -1.0]))
    bounds = crlb.crlb_tones(n, f, a, list(ph), sigma, FS)
    for j, b in enumerate(bounds):
        np.testing.assert_allclose(tr.std.frequency_hz[0, j], b.frequency_hz_std, rtol=0.05)
        np.testing.assert_allclose(tr.std.amplitude[0, j], b.amplitude_std, rtol=0.05)
        np.testing.assert_allclose(tr.std.phase_rad[0, j], b.phase_rad_std, rtol=0.05)
    np.testing.assert_allclose(tr.std.offset[0], bounds[0].offset_std, rtol=0.05)


def test_phase_std_grows_while_the_estimate_is_held():
    """Between hops the phase advances at the held frequency; its sd grows as
    var(phi) + m^2 var(w) + 2 m cov(w, phi), and the errors stay calibrated."""
    rng = np.random.default_rng(9)
    n, hop, sigma, trials = 256, 256, 0.1, 300
    t = np.arange(n + hop) / FS
    z = []
    sds = []
    for _ in range(trials):
        f, ph0 = 50.0 + rng.uniform(-1, 1), rng.uniform(-np.pi, np.pi)
        x = np.sin(2 * np.pi * f * t + ph0) + sigma * rng.standard_normal(t.size)
        tr = create("nls", FS, min_frequency_hz=20.0, window_samples=n, hop_samples=hop).update(x)
        held = n + hop - 2  # the last sample before the next hop: m = hop - 1
        err = _wrap(np.array(tr.phase_rad[held, 0] - (2 * np.pi * f * t[held] + ph0)))
        z.append(err / tr.std.phase_rad[held, 0])
        sds.append(tr.std.phase_rad[held, 0] / tr.std.phase_rad[n - 1, 0])
    assert 0.9 <= np.std(z) <= 1.1
    assert min(sds) > 2.0  # 255 samples past a 256-sample window: the frequency error dominates


# ---- the number of tones ------------------------------------------------------------------------


def _tones_present(truth_amp: np.ndarray) -> np.ndarray:
    return np.sum(truth_amp > 0.0, axis=1)


def _check_order(name: str, windows: list[tuple[float, float]], freq_tol_hz: float, **params) -> None:
    sc = sc_registry.get(name)
    x, truth = sc.generate(0)
    fs = sc.sample_rate_hz
    est = create("nls", fs, n_components=None, k_max=4, **params)
    tr = est.update(x)
    n_window = est.window_samples
    t = np.arange(x.shape[0]) / fs
    for lo, hi in windows:
        # estimates whose whole window lies in [lo, hi]
        sel = (t >= lo + n_window / fs) & (t < hi)
        assert sel.any(), (name, lo, hi)
        want = _tones_present(truth.amplitude[sel])
        got = tr.extras["n_tones"][sel]
        assert np.all(got == want), f"{name} {lo}-{hi} s: tones found {np.unique(got)}, expected {np.unique(want)}"
        k = int(want[0])
        true_f = np.sort(truth.frequency_hz[sel][:, truth.amplitude[sel][0] > 0], axis=1)
        err = np.abs(tr.frequency_hz[sel][:, :k] - true_f)
        assert np.max(err) < freq_tol_hz, f"{name}: frequency error {np.max(err):.3g} Hz"
        assert np.all(np.isnan(tr.frequency_hz[sel][:, k:]))


@pytest.mark.parametrize("name", ["multitone-2-separated", "multitone-2-close", "multitone-2-weak", "multitone-3"])
def test_k_unknown_finds_the_tones_of_the_multitone_scenarios(name):
    # 4 cycles of 10 Hz: 400 samples; the close pair (5 Hz) is two DFT bins apart
    _check_order(name, [(5.0, 10.0)], 0.05, min_frequency_hz=10.0, max_frequency_hz=250.0, window_cycles=4.0)


PAPER004 = {
    # name: steady segments (s), each judged on the windows that lie inside it
    "paper004-ex1": [(0.0, 100.0)],
    "paper004-ex1-noisy": [(0.0, 100.0)],
    "paper004-ex2": [(0.0, 120.0), (120.0, 240.0)],  # 4 sin 3t + 3 sin 2t + 1; the 2 rad/s tone off at 120 s
    "paper004-ex3": [(0.0, 70.0), (70.0, 140.0)],  # frequency steps at 70 s
    "paper004-experiment": [(0.0, 100.0)],
}


def _paper004_params(name: str) -> dict[str, float]:
    fs = sc_registry.get(name).sample_rate_hz
    # the lowest expected frequency 0.2 Hz (1.26 rad/s, below the examples' 2 rad/s), 15 s
    # windows (2.4 DFT bins between 2 and 3 rad/s), an estimate every 5 s
    return {"min_frequency_hz": 0.2, "max_frequency_hz": 3.0, "window_s": 15.0, "hop_samples": int(5 * fs)}


@pytest.mark.parametrize("name", ["paper004-ex1-noisy", "paper004-ex3"])
def test_k_unknown_finds_the_tones_of_paper004(name):
    _check_order(name, PAPER004[name], 0.01, **_paper004_params(name))


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(PAPER004))
def test_k_unknown_finds_the_tones_of_every_paper004_example(name):
    _check_order(name, PAPER004[name], 0.01, **_paper004_params(name))


def test_mdl_keeps_pure_noise_empty_where_aic_overfits():
    """The documented choice: MDL (Djuric's penalty) finds no tone in white noise in
    nearly every window; AIC finds spurious ones more often."""
    rng = np.random.default_rng(3)
    n = 512
    found = {"mdl": 0, "aic": 0}
    windows = 100
    x = 0.3 + rng.standard_normal(n * windows)
    for crit in found:
        est = create("nls", FS, n_components=None, k_max=4, criterion=crit, min_frequency_hz=20.0,
                     window_samples=n, hop_samples=n)  # fmt: skip
        tr = est.update(x)
        found[crit] = int(np.sum(tr.extras["n_tones"][n - 1 :: n] > 0))
    assert found["mdl"] <= 5
    assert found["aic"] > found["mdl"]


# ---- options and parameters ----------------------------------------------------------------------


def test_trend_follows_a_drifting_offset():
    rng = np.random.default_rng(4)
    n, sigma = 1000, 0.01
    t = np.arange(n) / FS
    drift = 0.5 + 0.8 * t  # 0.8 per second
    x = drift + np.sin(2 * np.pi * 50.3 * t + 0.2) + sigma * rng.standard_normal(n)
    with_trend = create("nls", FS, min_frequency_hz=20.0, window_samples=n, trend=True).update(x, last_only=True)
    without = create("nls", FS, min_frequency_hz=20.0, window_samples=n).update(x, last_only=True)
    err = with_trend.offset[0] - drift[-1]
    assert abs(err) < 4 * with_trend.std.offset[0]
    assert abs(without.offset[0] - drift[-1]) > 0.3  # the window's mean, 0.4 below the end
    assert abs(with_trend.frequency_hz[0, 0] - 50.3) < 4 * with_trend.std.frequency_hz[0, 0]


def test_warm_start_ends_where_the_periodogram_start_does():
    """On a steady stream the warm start (previous window's frequencies) and the periodogram
    start reach the same least-squares minimum: same estimates to far below their sd."""
    rng = np.random.default_rng(11)
    t = np.arange(20 * 512) / FS
    x = (
        0.5
        + np.sin(2 * np.pi * 50.7 * t + 0.3)
        + 0.4 * np.sin(2 * np.pi * 91.0 * t)
        + 0.05 * rng.standard_normal(t.size)
    )
    common = {"n_components": 2, "min_frequency_hz": 20.0, "window_samples": 512, "hop_samples": 512}
    warm = create("nls", FS, **common).update(x)
    cold = create("nls", FS, warm_start=False, **common).update(x)
    assert warm.converged[-1] and cold.converged[-1]
    for q in ("frequency_hz", "amplitude", "phase_rad"):
        diff = np.abs(getattr(warm, q) - getattr(cold, q))[511:]
        sd = getattr(warm.std, q)[511:]
        assert np.max(diff / sd) < 0.01, q
    # and the warm path was taken: another start leaves round-off-level differences
    assert np.any(warm.frequency_hz[511:] != cold.frequency_hz[511:])


def test_warm_start_follows_a_frequency_jump():
    """A tone that jumps by 30 Hz leaves the warm fit with a large residual: the window is
    refitted from the periodogram and the new frequency is found in the first window after
    the jump."""
    rng = np.random.default_rng(12)
    n = 256
    t = np.arange(12 * n) / FS
    f = np.where(t < 6 * n / FS, 50.0, 80.0)
    x = np.sin(2 * np.pi * np.cumsum(f) / FS) + 0.01 * rng.standard_normal(t.size)
    tr = create("nls", FS, min_frequency_hz=20.0, window_samples=n, hop_samples=n).update(x)
    after = 7 * n - 1  # the first window entirely after the jump
    assert abs(tr.frequency_hz[after, 0] - 80.0) < 5 * tr.std.frequency_hz[after, 0]
    assert tr.converged[after]


def test_accuracy_bench_reports_own_window_crlb_and_calibration():
    """``sinewatch bench accuracy`` records, for a windowed estimator, the dB over its own
    window's bound and, for one that reports sd, the calibration; none for the others."""
    from sinewatch.apps.bench.report import render_markdown
    from sinewatch.apps.bench.runner import evaluate

    rec = evaluate("nls", "tone-snr-40db", trials=4, seed=0)
    m = rec["metrics"]
    own = m["crlb_own_window"]
    assert own["window_samples"] > 0
    for q in ("frequency_hz", "amplitude", "phase_rad", "offset"):
        assert abs(own[q]["over_crlb_db"]) < 1.5, q
        assert 0.8 < m["calibration"][q] < 1.25, q
        # the record-length bound is far tighter than the window's: the first is much larger
        assert m["crlb"][q]["over_crlb_db"] > own[q]["over_crlb_db"] + 3.0, q
    other = evaluate("sogi-fll", "tone-snr-40db", trials=1, seed=0)["metrics"]  # reports no sd
    assert "calibration" not in other and "crlb_own_window" not in other
    kalman = evaluate("ges-kalman", "tone-snr-40db", trials=1, seed=0)["metrics"]  # an sd, no window
    assert "calibration" in kalman and "crlb_own_window" not in kalman
    md = render_markdown([rec], "cmd", {"trials": 4, "seed": 0})
    assert "own window" in md and "### Calibration of the reported standard deviations" in md
