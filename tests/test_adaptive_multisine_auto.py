"""adaptive-multisine with its automatic design (n and the band given, every other setting at
its default) against paper 004 (B. Chen, G. Pin, W. M. Ng, S. Y. Hui, T. Parisini, "An
adaptive observer-based robust estimator of multi-sinusoidal signals"), Section V.

The paper tunes each example by hand (its Section V gains); here the estimator derives its
own from n, the band and the offset flag (the paper004-* scenarios' suggested parameters:
band 0.5-10 rad/s for Examples 1-3, 1-14 rad/s for the experiment). The extraction lost the
figures: the paper's results are quoted from its text beside what these tests measure
(seeded, at the scenarios' sampling: Ts = 0.3 ms, 10 kHz for the experiment). Print the
figures with ``.venv/bin/python -m pytest -q -s tests/test_adaptive_multisine_auto.py -k section_v``.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from adaptive_multisine_checks import assert_example_1, assert_example_3_step, assert_settles_and_holds, settle_time
from conftest import make_config, replay_recording, serve_feed_tail
from scipy.linalg import eigh
from scipy.signal import place_poles

from sinewatch import scenarios
from sinewatch.estimators import create, get
from sinewatch.estimators._adaptive_multisine_auto import DESIGN, _gen_eig, _place
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.errors import ParameterError

NAME = "adaptive-multisine"


def run_scenario(name: str, seed: int = 1):
    """The scenario's signal through the estimator with the scenario's suggested parameters
    (n, bias and the band only); time (s), track, and the frequencies in rad/s."""
    sc = scenarios.get(name)
    assert sc.suggested_estimator == NAME and set(sc.suggested_params) == {"n_sinusoids", "bias", "band_hz"}
    y, _truth = sc.generate(seed)
    tr = create(NAME, sc.sample_rate_hz, **sc.suggested_params).update(y)
    t = np.arange(y.size) / sc.sample_rate_hz
    return t, tr, tr.frequency_hz * 2.0 * np.pi


# ---- the design's building blocks against independent implementations ----------------------------
@pytest.mark.parametrize("n", [1, 2, 3, 5])
@pytest.mark.parametrize("bias", [False, True])
def test_closed_form_pole_placement_matches_scipy(n, bias):
    rng = np.random.default_rng(n + 10 * bias)
    nx = 2 * n + int(bias)
    a = -(np.sort(rng.uniform(0.5, 4.0, n)) ** 2)
    poles = -np.sort(rng.uniform(0.3, 3.0, nx))
    F, C = np.zeros((nx, nx)), np.zeros(nx)
    for i in range(n):
        F[2 * i, 2 * i + 1], F[2 * i + 1, 2 * i], C[2 * i] = 1.0, a[i], 1.0
    if bias:
        C[-1] = 1.0
    s = np.concatenate([a, np.zeros(nx)])
    _place(s, 0, n, poles, n, int(bias))
    ref = place_poles(F.T, C[:, None], poles).gain_matrix[0]
    np.testing.assert_allclose(s[n:], ref, rtol=1e-4, atol=1e-9)  # scipy iterates: agrees to 1e-5 at n = 5
    # the characteristic polynomial (its roots are ill-conditioned when the poles cluster)
    np.testing.assert_allclose(np.poly(F - np.outer(s[n:], C)), np.poly(poles), rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_generalised_eigen_decomposition_matches_scipy(n):
    # (23): lambda_i of Phi_Psi = M^-1 Phi_Xi, i.e. Phi_Xi v = lambda M v, decreasing
    rng = np.random.default_rng(n)
    for _ in range(50):
        X, Y = rng.standard_normal((n + 2, n)), rng.standard_normal((n + 3, n))
        Phi, M = X.T @ X, Y.T @ Y + 0.1 * np.eye(n)
        G = np.zeros((5, n, n))  # packed: Phi, R, scratch, W, lambda
        G[0] = Phi
        R = np.linalg.cholesky(M)  # M = R R^T
        G[1] = R
        _gen_eig(G, n)
        W, lam = G[3], G[4, 0]
        np.testing.assert_allclose(lam, eigh(Phi, M, eigvals_only=True)[::-1], rtol=1e-9, atol=1e-12)
        V = np.linalg.solve(R.T, W)  # v = R^-T w
        np.testing.assert_allclose(Phi @ V, M @ V * lam, atol=1e-9)
        np.testing.assert_allclose(V.T @ M @ V, np.eye(n), atol=1e-9)


def test_pivot_test_of_25_decides_as_the_eigenvalues():
    # While every psi_i is on, the kernel decides (25) by the sign of the L D L^T pivots of
    # Phi_Xi - delta_low M, not by the eigenvalues; the per-sample track reports the
    # eigenvalues lambda_i of every sample: the decisions must be the hysteresis rule on them.
    # Example 2's signal (the class example) has a direction switching off and on (18 % of
    # the samples partly excited).
    cls = get(NAME)
    est = cls.example()
    tr = est.update(cls.example_signal(20_000, seed=3))
    lam, psi = tr.extras["excitation_level"], tr.extras["adaptation_enabled"]
    d_lo, d_hi = est.params.delta_low, est.params.delta_high
    prev_all = psi[:-1].all(axis=1)
    stays = prev_all & psi[1:].all(axis=1)
    drops = prev_all & ~psi[1:].all(axis=1)
    assert stays.sum() > 1000 and drops.sum() > 10  # both branches exercised
    assert np.all(lam[1:][stays].min(axis=1) >= d_lo)
    assert np.all(lam[1:][drops].min(axis=1) < d_lo)
    # and the partly excited samples follow the rule on lambda itself
    part = ~prev_all
    on_now = psi[1:][part]
    assert np.all(on_now[lam[1:][part] >= d_hi]) and not np.any(on_now[lam[1:][part] < d_lo])


def test_design_comes_from_n_and_the_band_only():
    est = create(NAME, 1000.0, n_sinusoids=3, band_hz=(2.0, 50.0))
    d = est.design
    beta = 2.0 / 50.0
    w0 = [beta ** (1 - (i + 0.5) / 3) for i in range(3)]  # AD1, in units of 2 pi 50 rad/s
    np.testing.assert_allclose(d["omega0"], w0)
    np.testing.assert_allclose(d["a"], [-w * w for w in w0])  # thetah(0) = 0
    assert d["w_ref"] == pytest.approx(2 * math.pi * 50.0)
    assert len(d["poles"]) == 7 and len(set(d["poles"])) == 7 and max(d["poles"]) < 0  # 2n + 1, AD2
    assert len(d["filter_poles"]) == len(d["filter_gains"]) == 2  # n - 1, (12)
    C = np.array([1.0, 0, 1, 0, 1, 0, 1])
    F = np.zeros((7, 7))
    for i in range(3):
        F[2 * i, 2 * i + 1], F[2 * i + 1, 2 * i] = 1.0, d["a"][i]
    np.testing.assert_allclose(
        np.sort(np.linalg.eigvals(F - np.outer(est.L_x, C)).real), np.sort(d["poles"]), rtol=1e-6
    )
    assert est.automatic and est.substeps == 1


@pytest.mark.parametrize(
    "params, match",
    [
        ({"band_hz": (5.0, 2.0)}, "0 < f_lo < f_hi"),
        ({"band_hz": (0.0, 2.0)}, "0 < f_lo < f_hi"),
        ({"band_hz": (1.0, 2.0), "mu": 3.0}, "expected no mu with band_hz"),
        ({"band_hz": (1.0, 2.0), "omega_unit_rad_s": 3.0, "a": [-1.0, -2.0]}, "expected no a, omega_unit_rad_s"),
        ({"band_hz": (1.0, 95.0)}, "sample_rate_hz / 10"),
    ],
)
def test_bad_automatic_parameters_are_clear_errors(params, match):
    with pytest.raises(ParameterError, match=match):
        create(NAME, 1000.0, **params)


# ---- the discretisation: no frequency bias at coarse sampling --------------------------------------
def test_coarse_sampling_reports_the_true_frequency():
    # Symplectic Euler makes the settled observer the exact recursion of a sampled sinusoid at
    # omega_d, 2 sin(omega_d h / 2) = h sqrt(Omegah): the reported omega_d is unbiased at 15
    # samples per period (forward Euler's oscillator would be 0.7 % fast there, atan(w h) / h).
    # Measured: frequency, amplitude and phase exact to 1e-10.
    fs, f, amp, phi0 = 1500.0, 100.0, 2.0, 0.4
    t = np.arange(30_000) / fs
    est = create(NAME, fs, n_sinusoids=1, bias=False, band_hz=(20.0, 120.0))
    tr = est.update(amp * np.sin(2 * np.pi * f * t + phi0))
    np.testing.assert_allclose(tr.frequency_hz[-100:, 0], f, rtol=1e-7)
    np.testing.assert_allclose(tr.amplitude[-100:, 0], amp, rtol=1e-6)
    ph = tr.phase_rad[-100:, 0] - (2 * np.pi * f * t[-100:] + phi0)
    np.testing.assert_allclose(np.angle(np.exp(1j * ph)), 0.0, atol=1e-6)


# ---- Section V -------------------------------------------------------------------------------------
def test_section_v_example_1_noise_free():
    # Paper (Fig. 3, from its text): from omegah(0) = (3, 4) all methods "succeed in detecting
    # the frequencies" of sin 2t + sin 5t "after a similar transient behavior". Here from the
    # design's own (1.06, 4.73) rad/s: measured within 1 % after 9.3 s and 9.0 s, errors below
    # 1e-9 rad/s and amplitudes 1.000 over 60-100 s, converged from 27.5 s.
    t, tr, w = run_scenario("paper004-ex1")
    assert_example_1(t, tr, w, within=12.0, atol_w=1e-4, atol_amp=1e-3, converged_from=30.0)
    print(f"\nEX1: within 1 % after {[settle_time(t, w[:, i], v, 0.01) for i, v in enumerate((2, 5))]} s")


def test_section_v_example_1_uniform_noise():
    # Paper (Figs. 4-5): with d uniform in [-0.25, 0.25] the method keeps "a relatively better
    # noise immunity" than [30], [32]. Measured over 60-100 s: bias 7e-5 / 3.8e-3 rad/s, std
    # 2.7e-3 / 4.1e-3 rad/s (0.14 % / 0.08 %); within 2 % after 8.7 s; amplitudes 1.00 +- 0.006.
    t, tr, w = run_scenario("paper004-ex1-noisy")
    ss = t >= 60.0
    np.testing.assert_allclose(w[ss].mean(axis=0), [2.0, 5.0], atol=5e-3)
    assert np.all(w[ss].std(axis=0) < [0.015, 0.04])
    np.testing.assert_allclose(tr.amplitude[ss].mean(axis=0), [1.0, 1.0], atol=0.01)
    for i, target in enumerate((2.0, 5.0)):
        assert settle_time(t, w[:, i], target, 0.03) < 15.0
    print(f"\nEX1 noisy: bias {w[ss].mean(axis=0) - (2, 5)}, std {w[ss].std(axis=0)} rad/s")


def test_section_v_example_2_bias_and_overparametrisation():
    # Paper (Figs. 7-9): 4 sin 3t + A2 sin 2t + 1 + d, A2 = 3 -> 0 at 120 s: "all the
    # initialized parameters including the offset are successfully estimated"; after 120 s the
    # second amplitude "fades to 0 eventually", the excited component stays "in a neighborhood
    # of the true ones"; Fig. 7 shows lambda_i and psi_i. (The figures are not in the text we
    # have: these are the text's statements.) Measured: within 1 % after 13.7 s and 13.2 s; over
    # 60-120 s errors below 9e-4 rad/s, amplitudes 2.999 / 3.999, offset 1.000. After 120 s the
    # idle component stays below 2.02 rad/s (2.34 before AD5 capped the rates; with rho_rel =
    # 0.1, AD4, it drifted to 2.6 and shared the 3 rad/s tone at 0.1-0.3), its amplitude falls
    # to 0.016 by 170 s and is faded from 123.8 s on (mean 0.015 over 200-240 s); the excited
    # one 3.000 rad/s, 4.000, offset 1.000.
    t, tr, w = run_scenario("paper004-ex2")
    amp = tr.amplitude
    pre, post = (t >= 60) & (t < 120), t >= 200
    for i, target in enumerate((2.0, 3.0)):  # ordered components: 2 rad/s first
        assert settle_time(t[t < 120], w[t < 120, i], target, 0.01) < 15.0
    np.testing.assert_allclose(w[pre].mean(axis=0), [2.0, 3.0], atol=5e-3)
    np.testing.assert_allclose(amp[pre].mean(axis=0), [3.0, 4.0], atol=0.02)
    assert abs(tr.offset[pre].mean() - 1.0) < 0.01
    # the vanished tone's component: held away from the remaining tone, then faded to ~0
    assert np.nanmax(w[t >= 120, 0]) < 2.45
    assert amp[post, 0].mean() < 0.04 and amp[post, 0].max() < 0.08
    assert tr.extras["component_faded"][post, 0].all() and np.isnan(w[post, 0]).all()
    assert not tr.extras["component_faded"][post, 1].any()
    assert abs(np.mean(w[post, 1]) - 3.0) < 0.01 and abs(amp[post, 1].mean() - 4.0) < 0.02
    assert abs(tr.offset[post].mean() - 1.0) < 0.01
    psi, lam = tr.extras["adaptation_enabled"], tr.extras["excitation_level"]
    assert psi.shape == lam.shape == (t.size, 2) and psi.dtype == bool
    assert psi[pre].any(axis=1).all() and np.all(lam >= -1e-12)
    print(
        f"\nEX2: settle {[settle_time(t[t < 120], w[t < 120, i], v, 0.01) for i, v in enumerate((2, 3))]} s, "
        f"pre errors {w[pre].mean(axis=0) - (2, 3)}, A {amp[pre].mean(axis=0)}, offset {tr.offset[pre].mean():.4f}; "
        f"post: w1 {np.mean(w[post, 1]):.4f}, A {np.nanmean(amp[post], axis=0)}"
    )


def test_section_v_example_3_frequency_steps():
    # Paper (Fig. 10): w1: 2 -> 3 rad/s and w2: 5 -> 4.5 rad/s at t = 70 s with d uniform in
    # [-0.25, 0.25]; "succeeded in tracking sudden changes of frequency in a noisy environment".
    # Measured: over 50-70 s and 110-140 s the mean errors are below 0.005 rad/s; within 5 %
    # 13.9 s and 13.1 s after the step (32 s before AD5 capped the rates).
    t, _tr, w = run_scenario("paper004-ex3")
    assert_example_3_step(t, w, pre_from=50, post_from=110, atol_pre=0.02, rel_tol=0.05, within=40.0)


def test_section_v_experiment_at_10_khz():
    # Paper (Figs. 13-14, dSpace at 10 kHz): 4 sin 7t + 2 sin 5t with measurement noise; the
    # estimator gathers "the frequency and amplitude contents with great accuracy". Noise level
    # not given (Gaussian std 0.05 here). Measured: within 1 % after 5.7 s and 8.1 s; over
    # 70-100 s errors 4e-5 / 2.5e-4 rad/s, amplitudes 2.00 / 4.00.
    t, tr, w = run_scenario("paper004-experiment")
    assert_settles_and_holds(t, tr, w, [5.0, 7.0], [2.0, 4.0], within=20.0, hold_from=70.0, atol_w=3e-3, atol_amp=0.01)
    print(f"\nEXP: within 1 % after {[settle_time(t, w[:, i], v, 0.01) for i, v in enumerate((5, 7))]} s")


# ---- any n, no per-case tuning --------------------------------------------------------------------
def _n_tones(n: int, bias: bool, freqs: list[float], seconds: float = 60.0):
    """n tones at ``freqs`` (amplitudes 1 + 0.15 (n - 1 - i), phases 0.3 i), offset 0.7 with
    ``bias`` (none without), Gaussian noise std 0.05, at 2 kHz through the automatic design for
    the 2-20 Hz band: time and track."""
    amps = [1.0 + 0.15 * (n - 1 - i) for i in range(n)]
    fs = 2000.0
    t = np.arange(int(seconds * fs)) / fs
    rng = np.random.default_rng(n)
    y = (0.7 if bias else 0.0) + sum(
        a * np.sin(2 * np.pi * f * t + 0.3 * i) for i, (a, f) in enumerate(zip(amps, freqs, strict=True))
    )
    tr = create(NAME, fs, n_sinusoids=n, bias=bias, band_hz=(2.0, 20.0)).update(y + 0.05 * rng.standard_normal(t.size))
    return t, tr, amps


_N_FREQS = {1: [7.0], 2: [5.0, 9.0], 3: [4.0, 7.0, 12.0], 4: [3.0, 5.0, 8.0, 13.0], 5: [2.5, 4.0, 6.5, 10.0, 15.0]}


@pytest.mark.parametrize("n, bias", [(n, b) for n in (1, 2, 3, 4, 5) for b in (True, False)])
def test_n_sinusoids_from_1_to_5_with_the_band_only(n, bias):
    # n tones spread over 2-20 Hz (unequal amplitudes, noise std 0.05, an offset with bias, none
    # without) at 2 kHz; the same defaults for every n. Measured over the last 10 s of 60 s: the
    # mean frequencies within 0.07 % (n = 1 without offset 0.25 %, n = 5 without 0.14 %), the
    # amplitudes within 0.15 %, the offset within 0.001. n = 5: every frequency within 1 % from
    # 10.7 s on with an offset (2.500, 4.002, 6.501, 10.001, 14.996 Hz), from 23.0 s without
    # (2.500, 4.006, 6.503, 10.000, 15.007 Hz). Without an offset it used to settle at 2.50, 4.04,
    # 7.46, 9.08, 15.01 Hz: the start-up threw it off the truth (AD5 says how; now capped).
    freqs = _N_FREQS[n]
    t, tr, amps = _n_tones(n, bias, freqs)
    last = t >= 50.0
    np.testing.assert_allclose(tr.frequency_hz[last].mean(axis=0), freqs, rtol=5e-3)
    np.testing.assert_allclose(tr.amplitude[last].mean(axis=0), amps, rtol=0.03)
    if bias:
        assert abs(tr.offset[last].mean() - 0.7) < 0.02
    else:
        assert np.all(tr.offset == 0.0)


def test_five_sinusoids_without_offset_started_at_the_truth_come_back_to_it():
    # The cause AD5 measures: n = 5 without an offset, noise-free, the tones exactly at the
    # design's initial frequencies (AD1), so thetah(0) = theta* = 0. As the dwell (AD7) ends the
    # excitation is 20 times its steady level (sum of lambda_i 0.15 against 0.007) while Xi (17)
    # still builds up, and the start-up transient reads as parameter error. Before AD5 capped
    # each direction's rate at kappa |slowest pole|, the estimates were thrown 20-48 % off and
    # were still 1-24 % off after 15-20 s. Measured now: thrown up to 40 % off within 0.2 s
    # (a dwell long enough to avoid it, 8 / |slowest pole|, slows Example 2 beyond its 15 s),
    # back within 1 % by about 10 s, within 0.26 % over 15-20 s; amplitudes within 0.2 %.
    fs = 2000.0
    t = np.arange(int(20.0 * fs)) / fs
    est = create(NAME, fs, n_sinusoids=5, bias=False, band_hz=(2.0, 20.0))
    f0 = np.asarray(est.design["omega0"]) * 20.0  # units of 2 pi f_hi
    amps = [1.0 + 0.15 * (4 - i) for i in range(5)]
    tr = est.update(sum(a * np.sin(2 * np.pi * f * t + 0.3 * i) for i, (a, f) in enumerate(zip(amps, f0, strict=True))))
    last = t >= 15.0
    assert np.max(np.abs(tr.frequency_hz[last] / f0 - 1.0)) < 5e-3
    np.testing.assert_allclose(tr.amplitude[last].mean(axis=0), amps, rtol=5e-3)


def test_five_sinusoids_away_from_the_initial_frequencies():
    # For n = 5 the design's initial frequencies (AD1: 2.52, 3.99, 6.32, 10.0, 15.9 Hz for the
    # 2-20 Hz band) lie within 3 % of the tones of the test above; these tones are 16-37 % from
    # them. Measured over the last 10 s of 60 s: 3.000, 5.006, 7.514, 11.000, 16.984 Hz (0.18 %),
    # amplitudes within 0.17 %, offset 0.7006; every frequency within 1 % from 21.4 s on.
    # Before AD5 capped the rates: 1.88, 4.49, 5.17, 9.48, 17.29 Hz (the start-up kicked the
    # lowest below the band). Not covered: the same tones without an offset still settle wrong
    # (2.59, 3.11, 6.58, 7.58, 18.2 Hz).
    freqs = [3.0, 5.0, 7.5, 11.0, 17.0]
    t, tr, amps = _n_tones(5, True, freqs)
    last = t >= 50.0
    np.testing.assert_allclose(tr.frequency_hz[last].mean(axis=0), freqs, rtol=1e-2)
    np.testing.assert_allclose(tr.amplitude[last].mean(axis=0), amps, rtol=0.03)
    assert abs(tr.offset[last].mean() - 0.7) < 0.02


# ---- outputs --------------------------------------------------------------------------------------
def test_output_conventions_and_extras():
    cls = get(NAME)
    est = cls.example()
    assert est.automatic and est.params.band_hz == (5.0, 25.0)
    x = cls.example_signal(2400)
    tr = est.update(x)
    assert est.n_components == 2 and tr.frequency_hz.shape == (2400, 2)
    assert set(tr.extras) == {
        "excitation_level",
        "adaptation_enabled",
        "component_faded",
        "signal_present",
        "observer_reset",
    }
    for key in ("excitation_level", "adaptation_enabled", "component_faded"):
        assert tr.extras[key].shape == (2400, 2)
    assert tr.converged[-600:].all()
    np.testing.assert_allclose(tr.frequency_hz[-300:].mean(axis=0), [10.0, 15.0], rtol=6e-3)  # ordered
    np.testing.assert_allclose(tr.amplitude[-300:].mean(axis=0), [3.0, 4.0], rtol=0.01)
    assert np.sqrt(np.mean((tr.reconstruct()[-300:] - x[-300:]) ** 2)) < 0.1


def test_design_constants_are_documented():
    # every constant of the automatic design is named in the module docstring's AD list
    import sinewatch.estimators.adaptive_multisine as mod

    assert mod.__doc__ is not None
    for tag in ("AD1", "AD2", "AD3", "AD4", "AD5", "AD6", "AD7", "AD8"):
        assert tag in mod.__doc__
    assert set(DESIGN) >= {"p_min", "p_max", "rho_rel", "kappa", "lambda_typ"}


# ---- served by the daemon, fed by name, replayed bit for bit -------------------------------------
def test_paper_example_2_served_fed_by_name_and_replayed(tmp_path):
    # `sinewatch serve` with a rule that runs the scenario's suggested parameters, `sinewatch
    # feed --scenario paper004-ex2` (30 paper seconds, 100 blocks), `tail`, then `replay` of
    # the MCAP file the daemon recorded.
    sc = scenarios.get("paper004-ex2")
    rule = EstimatorRule(match="sinewatch/in/sim/paper004-ex2", estimator=NAME, params=dict(sc.suggested_params))
    # Estimates published at once: the presence detector's onset latency is a third of a cycle of
    # the band's lowest frequency (0.08 Hz: 4.2 s), so with the hold every estimate of this 30 s
    # run would leave unconfirmed (the hold itself: tests/test_validity.py)
    config = make_config(tmp_path, rules=[rule], hold_estimates=False)
    ep = config.zenoh.listen[0]
    cfg_file = tmp_path / "serve.json"
    cfg_file.write_text(json.dumps(config.model_dump(mode="json")))
    block = 1000
    n_blocks = 100
    feed_err, lines, serve_err = serve_feed_tail(
        ["--config", str(cfg_file)],
        ["--connect", ep, "--count", str(n_blocks), "--json", "--timeout", "120", "--wait", "60"],
        ["--connect", ep, "--scenario", "paper004-ex2", "--duration", str(n_blocks * block / sc.sample_rate_hz),
         "--block", str(block)],
    )  # fmt: skip
    assert f"published {n_blocks} blocks" in feed_err
    assert len(lines) == n_blocks and {m["estimator"] for m in lines} == {NAME}
    assert f"drained: {n_blocks} inputs, {n_blocks} estimates, 0 errors" in serve_err
    last = lines[-1]
    assert last["seq"] == n_blocks - 1 and last["diagnostics"]["converged"]
    w = np.array(last["frequency_hz"]) * 2 * np.pi  # rad/s: the tones at 2 and 3 rad/s
    np.testing.assert_allclose(w, [2.0, 3.0], atol=0.03)
    assert abs(last["offset"] - 1.0) < 0.05
    assert f"all {n_blocks} recorded estimates reproduced bit for bit" in replay_recording(tmp_path / "rec")
