"""Reported standard deviations against the actual error, every setting at its default.

The signals and the statistic are those of ``sinewatch bench calibration``
(:mod:`sinewatch.apps.bench.calibration`): one estimate per seeded trial, error / reported std.
The default run uses few trials, so its bounds (sd 0.78-1.28, |mean| <= 0.4) are wider than
the target (sd 0.9-1.1, |mean| <= 0.3), but a std off by a factor of 2 either way (sd 0.64 or
less, 1.56 or more) fails them; the slow run checks the target itself on 300 trials per cell.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sinewatch.apps.bench.calibration import PARAMETERS, normalised_errors, run_calibration, trial_signal
from sinewatch.estimators import create

QUICK_TRIALS = 60
# (estimator, SNR dB): two SNRs each, one low and one high
QUICK_CELLS = [
    ("pmu", 10.0),
    ("pmu", 40.0),
    ("default-rule", 20.0),
    ("ipdft", 10.0),
    ("ipdft", 40.0),
    ("nls", 10.0),
    ("nls", 40.0),
    ("ges-kalman", 40.0),
    ("ges-kalman", 60.0),
]


def _spread(name: str, snr_db: float, trials: int) -> dict[str, tuple[float, float]]:
    z: dict[str, list[float]] = {k: [] for k in PARAMETERS}
    for seed in range(trials):
        for k, v in normalised_errors(name, seed, snr_db).items():
            if math.isfinite(v):
                z[k].append(v)
    return {k: (float(np.std(v)), float(np.mean(v))) for k, v in z.items() if v and k != "tve"}


@pytest.mark.parametrize(("name", "snr_db"), QUICK_CELLS)
def test_reported_std_matches_the_spread_of_the_error(name: str, snr_db: float) -> None:
    spread = _spread(name, snr_db, QUICK_TRIALS)
    assert {"frequency_hz", "amplitude", "phase_rad", "offset"} <= set(spread)
    for k, (sd, mean) in spread.items():
        # 60 trials: the sd of a unit spread is known to about +-9 % (one standard error)
        assert 0.78 <= sd <= 1.28, f"{name} {snr_db} dB {k}: sd(error/std) {sd:.2f}"
        assert abs(mean) <= 0.4, f"{name} {snr_db} dB {k}: mean(error/std) {mean:+.2f}"


def test_ges_kalman_at_its_defaults_is_calibrated_at_10_db() -> None:
    """ges-kalman at its defaults (the paper's Q scaled to the sample rate, R = 1e-2), noise
    read from its innovations: 200 trials at 10 dB (sd known to about +-5 %), where the
    paper's unscaled Q gave sd 1.72 / mean +2.45 for frequency and 1.64 / -1.83 for amplitude."""
    spread = _spread("ges-kalman", 10.0, 200)
    assert {"frequency_hz", "amplitude", "phase_rad", "offset"} <= set(spread)
    for k, (sd, mean) in spread.items():
        assert 0.85 <= sd <= 1.15, f"ges-kalman 10 dB {k}: sd(error/std) {sd:.2f}"
        assert abs(mean) <= 0.3, f"ges-kalman 10 dB {k}: mean(error/std) {mean:+.2f}"


def test_pmu_tve_std_is_the_rms_tve() -> None:
    ratios = []
    for seed in range(QUICK_TRIALS):
        ratios.append(normalised_errors("pmu", seed, 30.0)["tve"])
    rms = math.sqrt(float(np.mean(np.square(ratios))))
    assert 0.8 <= rms <= 1.25


@pytest.mark.parametrize("harmonic", [0.0, 0.1])
def test_pmu_reads_the_noise_from_the_signal_not_from_its_harmonics(harmonic: float) -> None:
    """The noise probes sit between the harmonics: a 10 % third and fifth harmonic do not
    reach the noise estimate (what the std is made of)."""
    fs, sigma = 5000.0, 0.01
    rng = np.random.default_rng(7)
    t = np.arange(round(2.0 * fs)) / fs
    x = np.sin(2 * np.pi * 50.3 * t) + sigma * rng.standard_normal(t.size)
    x += harmonic * (np.sin(2 * np.pi * 150.9 * t + 1.0) + np.sin(2 * np.pi * 251.5 * t))
    est = create("pmu", fs)
    est.update(x, t0_ns=0)
    noise = est.get_state()["state"]["noise"]
    from sinewatch.estimators.base import decode_array

    s, w = decode_array(noise)
    assert 0.8 * sigma**2 <= s / w <= 1.25 * sigma**2


def test_pmu_restores_a_snapshot_from_before_the_noise_average() -> None:
    x, _ = trial_signal(0, 30.0)
    est = create("pmu", 5000.0)
    est.update(x[:5000], t0_ns=0)
    snap = est.get_state()
    del snap["state"]["noise"]
    other = create("pmu", 5000.0)
    other.set_state(snap)
    a = est.update(x[5000:]).reports
    b = other.update(x[5000:]).reports
    assert a is not None and b is not None
    np.testing.assert_array_equal(a.track.frequency_hz, b.track.frequency_hz)  # the estimates are unchanged
    assert b.track.std is not None and np.all(np.isfinite(b.track.std.frequency_hz))


@pytest.mark.slow
def test_ges_kalman_calibration_from_0_to_60_db() -> None:
    """ges-kalman at its defaults (the bias correction, B1-B4, included), 300 trials per cell,
    0 to 60 dB: |mean| <= 0.3 (the frequency's mean at 0 dB: +0.11 measured, +0.43 without the
    correction) and sd 0.9-1.1, 1.12 allowed: an sd over 300 trials is known to +-0.042, and the
    phase at 20 dB reads 1.104 over these 300 signals, 1.04 over 1000 (the test below)."""
    rows = run_calibration(["ges-kalman"], [0.0, 10.0, 20.0, 40.0, 60.0], 300, 0, 2)
    assert not _out_of_band(rows, sd_max=1.12)


@pytest.mark.slow
def test_ges_kalman_calibration_within_target_over_1000_trials() -> None:
    """The cells nearest the edge at 300 trials, over 1000 (sd known to +-0.023): the target
    itself, sd 0.9-1.1 and |mean| <= 0.3 (measured: 0 dB 0.97-1.01, |mean| <= 0.08; 20 dB
    1.00-1.04, |mean| <= 0.06)."""
    rows = run_calibration(["ges-kalman"], [0.0, 20.0], 1000, 0, 2)
    assert not _out_of_band(rows, sd_max=1.1)


def _out_of_band(rows: list[dict], sd_max: float) -> list[tuple]:
    """The cells (SNR, parameter, sd, mean) of a calibration run outside sd 0.9-``sd_max``,
    |mean| <= 0.3."""
    bad = []
    for row in rows:
        for k in ("frequency_hz", "amplitude", "phase_rad", "offset"):
            c = row[k]
            if not (0.9 <= c["sd"] <= sd_max and abs(c["mean"]) <= 0.3):
                bad.append((row["snr_db"], k, round(c["sd"], 3), round(c["mean"], 3)))
    return bad


@pytest.mark.slow
def test_full_calibration_within_target() -> None:
    """1000 trials per cell (the sd known to +-2 %, where 300 leave +-4 %: at 300 a cell at
    1.11 or 0.89 is within sampling of the target), 0 to 60 dB: sd 0.9-1.1 and |mean| <= 0.3
    for every parameter of pmu, the default rule, ipdft and nls (ges-kalman: its own test above)."""
    rows = run_calibration(["pmu", "default-rule", "ipdft", "nls"], [0.0, 10.0, 20.0, 40.0, 60.0], 1000, 0, 2)
    bad = []
    for row in rows:
        for k in PARAMETERS:
            c = row.get(k)
            if c is None:
                continue
            ok = 0.9 <= c["sd"] <= 1.1 and (k == "tve" or abs(c["mean"]) <= 0.3)
            if not ok:
                bad.append((row["estimator"], row["snr_db"], k, round(c["sd"], 3), round(c["mean"], 3)))
    assert not bad
