"""The Cramer-Rao bound of a biased real sinusoid (sinewatch.crlb): exact Fisher matrix,
asymptotic closed form, and Monte Carlo of the maximum-likelihood fit reaching it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sinewatch.crlb import crlb, crlb_asymptotic, fisher_information, least_squares_fit

FS = 1000.0


def test_exact_bound_approaches_closed_form_for_large_n():
    for n, tol in ((1_000, 1e-2), (10_000, 1e-3), (200_000, 1e-4)):
        exact = crlb(n, 52.3, 1.3, 0.4, 0.02, FS)
        closed = crlb_asymptotic(n, 1.3, 0.02, FS)
        for p in ("frequency_hz", "amplitude", "phase_rad", "offset"):
            assert getattr(exact, p) / getattr(closed, p) == pytest.approx(1.0, rel=tol), (n, p)


def test_closed_form_frequency_is_twice_the_complex_tone_bound():
    # Real tone: var(w) >= 24 sigma^2 / (A^2 N (N^2 - 1)) rad^2/sample^2; a complex tone
    # A e^{j(wn + phi)} in complex noise of the same total variance has 12 sigma^2 / (...).
    n, a, sigma = 4096, 0.7, 0.05
    b = crlb_asymptotic(n, a, sigma, FS)
    var_w = b.frequency_hz * (2 * math.pi / FS) ** 2
    assert var_w == pytest.approx(24 * sigma**2 / (a**2 * n * (n**2 - 1)), rel=1e-12)
    complex_tone = 12 * sigma**2 / (a**2 * n * (n**2 - 1))
    assert var_w / complex_tone == pytest.approx(2.0)
    # Kay's other bounds, eta = A^2 / (2 sigma^2)
    eta = a**2 / (2 * sigma**2)
    assert b.amplitude == pytest.approx(2 * sigma**2 / n)
    assert b.phase_rad == pytest.approx(2 * (2 * n - 1) / (eta * n * (n + 1)))
    assert b.offset == pytest.approx(sigma**2 / n)


def test_fisher_matrix_equals_jacobian_product():
    # I = J^T J / sigma^2 with J the derivative of the model, taken here by central differences.
    n, f, a, phic, b0, sigma = 50, 87.0, 1.7, -0.9, 0.3, 0.1
    m = np.arange(n) - 0.5 * (n - 1)

    def model(theta):
        w, amp, ph, off = theta
        return off + amp * np.sin(w * m + ph)

    theta = np.array([2 * np.pi * f / FS, a, phic, b0])
    jac = np.empty((n, 4))
    for i in range(4):
        h = np.zeros(4)
        h[i] = 1e-6
        jac[:, i] = (model(theta + h) - model(theta - h)) / 2e-6
    expected = jac.T @ jac / sigma**2
    np.testing.assert_allclose(fisher_information(n, f, a, phic, sigma, FS), expected, rtol=1e-6, atol=1e-3)


def test_phase_bound_depends_on_the_reference_sample():
    n, a, sigma = 2000, 1.0, 0.01
    last = crlb(n, 50.0, a, 0.3, sigma, FS)
    first = crlb(n, 50.0, a, 0.3 - 2 * np.pi * 50.0 / FS * (n - 1), sigma, FS, reference=0)
    centre = crlb(n, 50.0, a, 0.3, sigma, FS, reference=(n - 1) // 2)
    # equal asymptotically; at finite N the cross terms depend on the phase (here 0.4 %)
    assert last.phase_rad == pytest.approx(first.phase_rad, rel=1e-2)
    assert centre.phase_rad == pytest.approx(2 * sigma**2 / (a**2 * n), rel=1e-2)
    assert last.phase_rad / centre.phase_rad == pytest.approx(4.0, rel=1e-2)  # (8N-4)/(2(N+1))
    assert last.frequency_hz == pytest.approx(centre.frequency_hz, rel=1e-12)  # reference-free


def test_bound_scales_with_noise_and_amplitude():
    a = crlb(300, 123.0, 1.0, 0.1, 0.01, FS)
    b = crlb(300, 123.0, 2.0, 0.1, 0.03, FS)
    assert b.frequency_hz / a.frequency_hz == pytest.approx(9 / 4, rel=1e-9)
    assert b.offset / a.offset == pytest.approx(9, rel=1e-9)


def test_rejects_impossible_inputs():
    with pytest.raises(ValueError, match="at least 4"):
        crlb(3, 50.0, 1.0, 0.0, 0.1, FS)
    with pytest.raises(ValueError, match="noise_std"):
        crlb(100, 50.0, 1.0, 0.0, 0.0, FS)
    with pytest.raises(ValueError, match="amplitude"):
        crlb_asymptotic(100, 0.0, 0.1, FS)


def test_least_squares_fit_is_exact_without_noise():
    n = np.arange(200)
    y = 0.4 + 1.5 * np.sin(2 * np.pi * 77.7 / FS * n + 2.0)
    f, a, ph, b = least_squares_fit(y, FS)
    assert f == pytest.approx(77.7, abs=1e-9)
    assert a == pytest.approx(1.5, abs=1e-9)
    assert b == pytest.approx(0.4, abs=1e-9)
    true_last = np.angle(np.exp(1j * (2 * np.pi * 77.7 / FS * 199 + 2.0)))
    assert ph == pytest.approx(true_last, abs=1e-9)


def _monte_carlo(trials: int, n: int, snr_db: float, seed: int):
    rng = np.random.default_rng(seed)
    f, a, b0, phi = 123.4, 1.0, 0.5, 0.7
    sigma = a / math.sqrt(2 * 10 ** (snr_db / 10))
    k = np.arange(n)
    true_last = np.angle(np.exp(1j * (2 * np.pi * f / FS * (n - 1) + phi)))
    est = np.array(
        [
            least_squares_fit(b0 + a * np.sin(2 * np.pi * f / FS * k + phi) + sigma * rng.standard_normal(n), FS)
            for _ in range(trials)
        ]
    )
    err = {
        "frequency_hz": est[:, 0] - f,
        "amplitude": est[:, 1] - a,
        "phase_rad": np.angle(np.exp(1j * (est[:, 2] - true_last))),
        "offset": est[:, 3] - b0,
    }
    bound = crlb(n, f, a, true_last, sigma, FS)
    return {p: float(np.mean(e**2)) / getattr(bound, p) for p, e in err.items()}


def test_maximum_likelihood_reaches_the_bound_at_high_snr():
    # 400 trials: the MSE ratio has a relative standard deviation of sqrt(2/400) = 7 %.
    ratios = _monte_carlo(400, 64, 40.0, seed=11)
    for p, r in ratios.items():
        assert 0.8 < r < 1.25, (p, r)  # measured: 0.93 .. 1.07


@pytest.mark.slow
def test_maximum_likelihood_reaches_the_bound_large_monte_carlo():
    ratios = _monte_carlo(5000, 128, 30.0, seed=5)
    for p, r in ratios.items():
        assert 0.92 < r < 1.08, (p, r)  # 5000 trials: 2 % standard deviation
