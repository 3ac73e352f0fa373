"""``ges-kalman``'s bias correction (eq. B1-B4 of :mod:`sinewatch.estimators._ges_kalman_kernels`).

The kernel's recursion against the equations written out with plain 4 x 4 matrices; the
filter itself untouched by it (its state bit for bit that of ``bias_correction = false``);
the correction's size against the bias it removes on the calibration bench's signals; and
older recordings replaying with the defaults they were made with.
"""

from __future__ import annotations

import json

import numpy as np
from test_ges_kalman_uncertainty import _recover

from sinewatch.apps.bench.calibration import SAMPLE_RATE_HZ, trial_signal
from sinewatch.estimators import create
from sinewatch.estimators.base import decode_array
from sinewatch.estimators.ges_kalman import PAPER_Q, UNC_BASE
from sinewatch.runtime.replay import recorded_config
from sinewatch.schemas.config import EstimatorRule, SinewatchConfig

FS = 5000.0


def _noisy_tone(n: int, sigma: float, seed: int) -> np.ndarray:
    t = np.arange(n) / FS
    return 0.05 + 1.2 * np.sin(2 * np.pi * 50.3 * t + 0.4) + sigma * np.random.default_rng(seed).standard_normal(n)


def _reference(y: np.ndarray, q: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Kalman filter on eq. (6) and (B1)-(B3) with full matrices: x_hat, M (4, 4, 4), b."""
    x, p = np.zeros(4), np.eye(4)
    m, b = np.zeros((4, 4, 4)), np.zeros(4)
    e12 = np.zeros((4, 4))
    e12[1, 2] = 1.0
    for s in y:
        a = np.eye(4) + np.diag([1.0, 0.0, 0.0], 1)
        a[1, 2], a[1, 3] = s, 1.0
        n = a @ p @ a.T + np.diag(q)
        big_s = n[0, 0] + r
        k = n[:, 0] / big_s
        ikc = np.eye(4) - np.outer(k, [1.0, 0.0, 0.0, 0.0])
        f = ikc @ a
        h = k + np.array([0.0, x[2], 0.0, 0.0])  # (U2)
        mm = m[:, 0, 0] + m[:, 0, 1] + m[:, 1, 0] + m[:, 1, 1]
        b = f @ b - ikc @ a @ mm / big_s + np.array([0.0, (p[0, 2] + p[1, 2]) / big_s, 0.0, 0.0])  # (B3)
        dv = ikc @ (e12 @ p @ a.T + a @ p @ e12.T) @ ikc.T  # (B1)
        m = np.einsum("ai,bj,ck,ijk->abc", f, f, f, m) + np.einsum("ab,c->abc", dv, h)  # (B2)
        xp = a @ x
        x = xp + k * (s - xp[0])
        p = n - np.outer(k, n[0])
    return x, m, b


def test_the_kernel_runs_b1_to_b3_as_written() -> None:
    y = _noisy_tone(1500, 0.5, 3)
    est = create("ges-kalman", FS)
    est.update(y)
    unc = decode_array(est.get_state()["state"]["unc"])
    consts = est._constants[0]
    _x, m, b = _reference(y, consts[:4], float(consts[4]))
    pairs = [(0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 3)]
    m_kernel = unc[UNC_BASE : UNC_BASE + 40].reshape(10, 4)
    for i, (a, c) in enumerate(pairs):
        np.testing.assert_allclose(m_kernel[i], m[a, c], rtol=1e-9, atol=1e-12 * np.abs(m).max())
        np.testing.assert_allclose(m_kernel[i], m[c, a], rtol=1e-9, atol=1e-12 * np.abs(m).max())  # symmetric
    np.testing.assert_allclose(unc[UNC_BASE + 40 :], b, rtol=1e-9)
    assert np.abs(b).max() > 0.0


def test_the_filter_is_the_papers_and_the_report_is_its_state_less_the_bias() -> None:
    y = _noisy_tone(4000, 0.3, 4)
    on, off = create("ges-kalman", FS), create("ges-kalman", FS, bias_correction=False)
    t_on, t_off = on.update(y, last_only=True), off.update(y, last_only=True)
    s_on, s_off = on.get_state()["state"], off.get_state()["state"]
    assert s_on["xP"] == s_off["xP"]  # the filter's state: bit for bit
    x = decode_array(s_on["xP"])[:4]
    unc = decode_array(s_on["unc"])
    s2 = unc[32] / unc[33]  # (U5)
    reported_off = [t_off.frequency_hz[0, 0], t_off.amplitude[0, 0], t_off.phase_rad[0, 0], t_off.offset[0]]
    reported_on = [t_on.frequency_hz[0, 0], t_on.amplitude[0, 0], t_on.phase_rad[0, 0], t_on.offset[0]]
    np.testing.assert_allclose(reported_off, _recover(x, 1 / FS), rtol=1e-12)
    np.testing.assert_allclose(reported_on, _recover(x - s2 * unc[UNC_BASE + 40 :], 1 / FS), rtol=1e-12)
    assert abs(reported_on[0] - reported_off[0]) > 1e-6
    assert np.all(decode_array(off.get_state()["state"]["unc"])[UNC_BASE:] == 0.0)  # off: not run


def _frequency_shift_in_sd(snr_db: float, trials: int) -> tuple[float, float]:
    """Over the calibration bench's trials: the mean of (corrected - uncorrected frequency) /
    reported sd, and the mean of the corrected error / reported sd."""
    shift, z = [], []
    for seed in range(trials):
        x, truth = trial_signal(seed, snr_db)
        on = create("ges-kalman", SAMPLE_RATE_HZ).update(x, last_only=True)
        off = create("ges-kalman", SAMPLE_RATE_HZ, bias_correction=False).update(x, last_only=True)
        assert on.std is not None
        sd = on.std.frequency_hz[0, 0]
        shift.append((on.frequency_hz[0, 0] - off.frequency_hz[0, 0]) / sd)
        z.append((on.frequency_hz[0, 0] - truth["f"]) / sd)
    return float(np.mean(shift)), float(np.mean(z))


def test_the_correction_is_the_bias_at_0_db_and_second_order() -> None:
    """At 0 dB the uncorrected frequency is +0.38 sd high on average over 1000 trials (gains
    from the clean signal: +0.13); the correction moves it by about -0.3 sd (paired: the same
    signals, so 60 trials pin the shift down); at 40 dB (sigma 100 times smaller) it moves by
    ~1/100 of that relative to the sd, as a second-order term over a first-order sd does."""
    shift_0, z_0 = _frequency_shift_in_sd(0.0, 60)
    assert -0.45 <= shift_0 <= -0.2, shift_0
    assert abs(z_0) <= 0.3, z_0
    shift_40, _ = _frequency_shift_in_sd(40.0, 20)
    assert abs(shift_40) <= 0.03 * abs(shift_0), (shift_40, shift_0)


def _config(version: str | None, params: dict[str, object]) -> SinewatchConfig:
    config = SinewatchConfig(rules=[EstimatorRule(match="*", estimator="ges-kalman", params=params)])
    metadata = {"config": config.model_dump_json()}
    if version is not None:
        metadata["estimator_defaults_version"] = version
    return recorded_config(metadata)


def test_older_recordings_replay_with_the_defaults_they_were_made_with() -> None:
    assert _config(None, {}).rules[0].params == {"q": PAPER_Q, "bias_correction": False}  # version 1
    assert _config("2", {}).rules[0].params == {"bias_correction": False}
    assert _config("3", {}).rules[0].params == {}
    assert _config("2", {"bias_correction": True}).rules[0].params == {"bias_correction": True}  # as recorded
    json.dumps(_config("1", {"r": 0.5}).rules[0].params)  # the params stay JSON
    assert _config("1", {"r": 0.5}).rules[0].params == {"q": PAPER_Q, "bias_correction": False, "r": 0.5}
