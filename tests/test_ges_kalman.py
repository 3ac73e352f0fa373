"""ges-kalman against paper 000, Section IV (figures quoted from the paper's text)."""

from __future__ import annotations

import numpy as np
import pytest

from sinewatch.estimators import create

FS = 1000.0  # Section IV: fs = 1 kHz
NOISE = 0.01  # zero-mean Gaussian, std 1e-2
# Q = 1e-6 I, R = 1e-2, a zero initial state, and the paper's x_hat as it is (no bias correction, B4)
PAPER = dict(q=1e-6, r=1e-2, x0=[0.0, 0.0, 0.0, 0.0], bias_correction=False)


def constant_tone(seconds: float, seed: int = 2026):
    t = np.arange(int(seconds * FS)) / FS
    rng = np.random.default_rng(seed)
    y = np.sin(2 * np.pi * 100.0 * t) + 1.0 + NOISE * rng.standard_normal(t.size)  # A=1, f=100, B=1
    return t, y


def test_constant_tone_converges_within_one_period():
    # Paper: "the filter converges very quickly, in less than 0.01 s" (one period).
    _t, y = constant_tone(1.0)
    tr = create("ges-kalman", FS, **PAPER).update(y)
    err = np.abs(tr.frequency_hz[:, 0] - 100.0)
    first_within_1hz_for_good = np.flatnonzero(err >= 1.0).max() + 1
    assert first_within_1hz_for_good / FS <= 0.012  # measured: 0.011 s (seed 2026)
    assert tr.converged[int(0.02 * FS) :].all()


def test_constant_tone_steady_state_matches_paper():
    t, y = constant_tone(20.0)
    tr = create("ges-kalman", FS, **PAPER).update(y)
    ss = t >= 1.0
    f_err = tr.frequency_hz[ss, 0] - 100.0
    b_err = tr.offset[ss] - 1.0
    # Paper: frequency error "0.2 Hz for most of the time"; measured std ~0.06 Hz, |err| p95 ~0.12 Hz.
    assert abs(f_err.mean()) < 0.05
    assert np.percentile(np.abs(f_err), 95) < 0.2
    # Paper: offset error "below 0.05 most of the time"; measured max ~0.01.
    assert np.max(np.abs(b_err)) < 0.05
    # Amplitude and phase (derived in the module, not in the paper): A = 1, phi = 0.
    assert np.mean(np.abs(tr.amplitude[ss, 0] - 1.0)) < 0.01
    phase_err = np.angle(np.exp(1j * (tr.phase_rad[ss, 0] - 2 * np.pi * 100.0 * t[ss])))
    assert abs(phase_err.mean()) < 0.005 and phase_err.std() < 0.02
    # the innovation is noise-sized once converged
    assert tr.residual_rms < 5 * NOISE


def test_chirp_error_about_one_hertz_near_180_hz():
    # Section IV-B: f(t) = t Hz (1 Hz/s), same noise and filter; "at t = 180 s ... estimated
    # with an error of about 1 Hz"; offset error "below 0.01 most of the time".
    t = np.arange(int(185 * FS)) / FS
    rng = np.random.default_rng(2026)
    y = np.sin(2 * np.pi * 0.5 * t**2) + 1.0 + NOISE * rng.standard_normal(t.size)
    tr = create("ges-kalman", FS, **PAPER).update(y)
    near_180 = (t > 179.0) & (t < 181.0)
    lag = np.mean(t[near_180] - tr.frequency_hz[near_180, 0])  # estimate lags the ramp
    assert 0.25 < lag < 1.5  # measured: 0.52 Hz; paper: "about 1 Hz"
    late = t > 100.0
    assert np.percentile(np.abs(tr.offset[late] - 1.0), 95) < 0.01


def test_undefined_estimate_is_nan_and_not_converged():
    est = create("ges-kalman", FS, **PAPER)
    tr = est.update(np.array([0.0, 0.0, 0.0]))  # x3 stays at 0: frequency undefined
    assert np.isnan(tr.frequency_hz).all() and np.isnan(tr.offset).all()
    assert not tr.converged.any()


def test_amplitude_phase_offset_recovered_at_10_khz():
    # Beyond the paper: a 50 Hz mains-like tone at 10 kHz with a tuned Q.
    fs = 10_000.0
    t = np.arange(int(2 * fs)) / fs
    y = 0.3 + 2.0 * np.sin(2 * np.pi * 50.0 * t + 1.0)
    tr = create("ges-kalman", fs, q=[1e-10, 1e-10, 1e-14, 1e-14], r=1e-4).update(y)
    assert tr.frequency_hz[-1, 0] == pytest.approx(50.0, abs=0.01)
    assert tr.amplitude[-1, 0] == pytest.approx(2.0, abs=0.01)
    assert tr.offset[-1] == pytest.approx(0.3, abs=0.01)
    true_phase = np.angle(np.exp(1j * (2 * np.pi * 50.0 * t[-1] + 1.0)))
    assert np.angle(np.exp(1j * (tr.phase_rad[-1, 0] - true_phase))) == pytest.approx(0, abs=0.01)
