"""``ges-kalman``'s reported standard deviations (module docstring, eq. U1-U6).

Calibration: on seeded single biased tones, the normalised error (error / reported sd, at
the last sample of a 2 s run, one per trial) has a standard deviation in [0.9, 1.1] for
frequency, amplitude, phase and offset, at SNR 10 to 40 dB and two frequencies. The
sd of the normalised error is taken about its mean, as the bench's calibration column
does. Also: the uncertainty state leaves the estimates bit for bit unchanged, and a
snapshot without it (an earlier build's) is still accepted.
"""

from __future__ import annotations

import numpy as np
import pytest

from sinewatch.estimators import create
from sinewatch.estimators.base import decode_array, encode_array
from sinewatch.estimators.ges_kalman import UNC_BASE, UNC_SIZE

FS = 1000.0
N = 2000  # 2 s
AMPLITUDE, OFFSET = 1.0, 0.5
FREQUENCIES_HZ = (25.0, 50.5)  # 40 and ~20 samples per cycle
SNR_DB = (10, 20, 30, 40)


def normalised_errors(frequency_hz: float, snr_db: int, trials: int, seed: int = 2026) -> np.ndarray:
    """(trials, 4): error / reported sd of frequency, amplitude, phase, offset at the last
    sample, one independent noise realisation and random phase per trial."""
    rng = np.random.default_rng([seed, int(frequency_hz * 10), snr_db])
    sigma = AMPLITUDE / np.sqrt(2.0 * 10.0 ** (snr_db / 10.0))
    t = np.arange(N) / FS
    z = np.empty((trials, 4))
    for i in range(trials):
        phi = rng.uniform(-np.pi, np.pi)
        y = OFFSET + AMPLITUDE * np.sin(2 * np.pi * frequency_hz * t + phi) + sigma * rng.standard_normal(N)
        # the paper's Q (its setting at 1 kHz): the recursion's calibration under the tuning it
        # was derived for; the defaults' (Q scaled to the rate) is tests/test_calibration.py's
        tr = create("ges-kalman", FS, q=1e-6).update(y, last_only=True)
        assert tr.std is not None
        theta = 2 * np.pi * frequency_hz * t[-1] + phi
        err = np.array(
            [
                tr.frequency_hz[0, 0] - frequency_hz,
                tr.amplitude[0, 0] - AMPLITUDE,
                (tr.phase_rad[0, 0] - theta + np.pi) % (2 * np.pi) - np.pi,
                tr.offset[0] - OFFSET,
            ]
        )
        sd = np.array([tr.std.frequency_hz[0, 0], tr.std.amplitude[0, 0], tr.std.phase_rad[0, 0], tr.std.offset[0]])
        assert np.all(np.isfinite(sd)) and np.all(sd > 0)
        z[i] = err / sd
    return z


def _check(frequency_hz: float, snr_db: int, trials: int) -> None:
    sd = normalised_errors(frequency_hz, snr_db, trials).std(axis=0)
    names = ("frequency", "amplitude", "phase", "offset")
    bad = {n: round(float(v), 3) for n, v in zip(names, sd, strict=True) if not 0.9 <= v <= 1.1}
    assert not bad, f"sd(error / reported sd) at {frequency_hz} Hz, {snr_db} dB: expected in [0.9, 1.1], got {bad}"


@pytest.mark.parametrize("frequency_hz", FREQUENCIES_HZ)
@pytest.mark.parametrize("snr_db", (10, 40))
def test_reported_sd_is_calibrated_fast(frequency_hz: float, snr_db: int) -> None:
    _check(frequency_hz, snr_db, trials=300)


@pytest.mark.slow
@pytest.mark.parametrize("frequency_hz", FREQUENCIES_HZ)
@pytest.mark.parametrize("snr_db", SNR_DB)
def test_reported_sd_is_calibrated(frequency_hz: float, snr_db: int) -> None:
    _check(frequency_hz, snr_db, trials=1000)


def test_the_reported_sd_scales_with_the_noise() -> None:
    """10 dB less noise: every sd about sqrt(10) smaller (first order in the noise)."""
    rng = np.random.default_rng(7)
    t = np.arange(N) / FS
    v = rng.standard_normal(N)
    sds = []
    for sigma in (0.05, 0.05 / np.sqrt(10.0)):
        tr = create("ges-kalman", FS).update(OFFSET + np.sin(2 * np.pi * 50.5 * t + 0.3) + sigma * v, last_only=True)
        assert tr.std is not None
        sds.append(
            np.array([tr.std.frequency_hz[0, 0], tr.std.amplitude[0, 0], tr.std.phase_rad[0, 0], tr.std.offset[0]])
        )
    np.testing.assert_allclose(sds[0] / sds[1], np.sqrt(10.0), rtol=0.1)


@pytest.mark.parametrize("bias_correction", [False, True])
def test_the_uncertainty_does_not_touch_the_filter_and_old_snapshots_load(bias_correction: bool) -> None:
    """From a snapshot without ``unc`` (as an earlier build wrote it) the filter's state and
    residual are bit for bit those of the estimator that kept running; so are the reported
    estimates without the bias correction (B4), which reads ``unc``'s b."""
    rng = np.random.default_rng(11)
    y = 1.0 + np.sin(2 * np.pi * 100.0 * np.arange(3000) / FS) + 0.01 * rng.standard_normal(3000)
    a = create("ges-kalman", FS, bias_correction=bias_correction)
    a.update(y[:1500])
    snap = a.get_state()
    assert set(snap["state"]) == {"xP", "unc"}
    old = {**snap, "state": {"xP": snap["state"]["xP"]}}
    b = create("ges-kalman", FS, bias_correction=bias_correction)
    b.set_state(old)
    assert b.get_state()["state"]["unc"] == encode_array(create("ges-kalman", FS)._initial_state()["unc"])
    ta, tb = a.update(y[1500:]), b.update(y[1500:])
    assert a.get_state()["state"]["xP"] == b.get_state()["state"]["xP"]
    assert ta.residual_rms == tb.residual_rms
    for f in ("frequency_hz", "amplitude", "phase_rad", "offset"):
        if bias_correction:  # b restarts from 0: at 40 dB here the correction is ~1e-6 Hz
            np.testing.assert_allclose(getattr(ta, f)[-1], getattr(tb, f)[-1], rtol=1e-5, atol=1e-7)
        else:
            assert getattr(ta, f).tobytes() == getattr(tb, f).tobytes()


def test_a_snapshot_with_the_former_noise_means_continues_from_their_ratio() -> None:
    """An ``unc`` of 34 values (<e^2>, <1 + C U C^T> at the end, as the previous build
    wrote it) loads: T and U kept, sigma_hat^2 their ratio, so the reported sd carries on."""
    rng = np.random.default_rng(12)
    y = 1.0 + np.sin(2 * np.pi * 100.0 * np.arange(3000) / FS) + 0.01 * rng.standard_normal(3000)
    a = create("ges-kalman", FS)
    a.update(y[:1500])
    snap = a.get_state()
    unc = decode_array(snap["state"]["unc"])
    s2 = unc[32] / unc[33]
    former = np.concatenate([unc[:32], [3.0 * s2, 3.0]])  # the same ratio, another weight
    b = create("ges-kalman", FS)
    b.set_state({**snap, "state": {**snap["state"], "unc": encode_array(former)}})
    loaded = decode_array(b.get_state()["state"]["unc"])
    assert loaded.shape == (UNC_SIZE,) and np.array_equal(loaded[:32], unc[:32])
    assert loaded[32] / loaded[33] == pytest.approx(s2, rel=1e-12)
    assert np.all(loaded[UNC_BASE:] == 0.0)  # the bias recursion (B2)-(B3) starts afresh
    ta, tb = a.update(y[1500:]), b.update(y[1500:])
    assert a.get_state()["state"]["xP"] == b.get_state()["state"]["xP"]  # the filter never depends on unc
    assert np.allclose(tb.std.frequency_hz[-1], ta.std.frequency_hz[-1], rtol=0.05)


def test_the_noise_estimate_forgets_the_start_at_high_snr() -> None:
    """At 60 dB SNR the start's innovations are 10^4 times the noise; sigma_hat^2 (U5, U5a)
    is within 30 % of sigma^2 after 700 samples (the plain exponential mean started at R
    was 88 times too large there, 9 times after 1,000 samples)."""
    fs, n = 1000.0, 700
    sigma = np.sqrt(0.5) * 10 ** (-60 / 20)
    t = np.arange(n) / fs
    ratios = []
    for seed in range(20):
        y = 0.5 + np.sin(2 * np.pi * 50.5 * t + 0.3) + np.random.default_rng(seed).normal(0.0, sigma, n)
        est = create("ges-kalman", fs, q=[2.55e-7, 2.55e-7, 6.5e-8, 6.5e-8], r=1e-3)
        est.update(y)
        unc = decode_array(est.get_state()["state"]["unc"])
        ratios.append(unc[32] / unc[33] / sigma**2)
    assert 0.7 < float(np.median(ratios)) < 1.3


def _recover(x: np.ndarray, ts: float) -> np.ndarray:
    """(f, A, theta, B) from the state, the recovery formulas of the module docstring."""
    x1, x2, x3, x4 = x
    sh, ch = np.sqrt(-x3 / 4), np.sqrt(1 + x3 / 4)
    b = -x4 / x3
    a_s = x1 - b
    a_c = (x2 / (2 * sh) + a_s * sh) / ch
    return np.array([np.arcsin(sh) / (np.pi * ts), np.hypot(a_s, a_c), np.arctan2(a_s, a_c), b])


def test_the_delta_method_uses_the_jacobian_of_the_recovery_formulas() -> None:
    """U6 against central differences of the recovery formulas, for a random covariance."""
    from sinewatch.estimators.ges_kalman import _parameter_std

    ts = 1.0 / FS
    x = np.array([0.9, 0.25, -4 * np.sin(np.pi * 50.5 * ts) ** 2, 4 * 0.5 * np.sin(np.pi * 50.5 * ts) ** 2])
    jac = np.empty((4, 4))
    for i in range(4):
        d = np.zeros(4)
        d[i] = 1e-7
        jac[:, i] = (_recover(x + d, ts) - _recover(x - d, ts)) / 2e-7
    rng = np.random.default_rng(0)
    m = rng.standard_normal((4, 4))
    t_part, u_part, s2 = m @ m.T * 1e-4, np.eye(4) * 1e-5, 2.0
    std = np.empty((1, 4))
    _parameter_std(x[0], x[1], x[2], x[3], t_part, u_part, np.empty((4, 4)), s2, ts, std, 0)
    np.testing.assert_allclose(std[0], np.sqrt(np.diag(jac @ (t_part + s2 * u_part) @ jac.T)), rtol=1e-6)
    _parameter_std(x[0], x[1], 0.5, x[3], t_part, u_part, np.empty((4, 4)), s2, ts, std, 0)  # outside (-4, 0), eq. (20)
    assert np.all(np.isnan(std[0]))
