"""The default configuration as a new user meets it: ``sinewatch serve`` with no config file
(only the listen port and recording directory from the environment), fed mains-like channels
by ``sinewatch feed``, publishes estimates that settle within a second on the truth and say so
(``converged`` and ``valid`` true)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from conftest import replay_recording, serve_feed_tail

from sinewatch.clients.session import free_loopback_port
from sinewatch.estimators import create
from sinewatch.schemas.config import DEFAULT_ESTIMATOR, DEFAULT_PARAMS, load_config

# scenario -> (truth Hz, tolerance Hz): 50 Hz at 10 kHz with a 10 % second harmonic; 50.5 Hz
# at 1 kHz with a 0.5 offset at 30 dB SNR (the targets)
TARGETS = {"c37-50hz-harmonic-2": (50.0, 0.01), "tone-snr-30db": (50.5, 0.05)}
BLOCK_S = 0.1  # --block 1000 at the first channel's 10 kHz: 100 ms blocks on both channels


def test_serve_without_config_converges_within_a_second_on_mains_channels(tmp_path):
    ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    env = {
        **os.environ,
        "SINEWATCH__ZENOH__LISTEN": json.dumps([ep]),
        "SINEWATCH__RECORDING__DIRECTORY": str(tmp_path / "rec"),
    }
    env.pop("SINEWATCH_CONFIG", None)
    feed = ["--connect", ep, "--duration", "3", "--block", "1000"]
    for name in TARGETS:
        feed += ["--scenario", name]
    feed_err, estimates, serve_err = serve_feed_tail(
        [], ["--connect", ep, "--count", "60", "--json", "--timeout", "60", "--wait", "60"], feed, serve_env=env
    )
    assert "published 60 blocks" in feed_err
    assert "drained: 60 inputs, 60 estimates, 0 errors" in serve_err
    assert {e["estimator"] for e in estimates} == {DEFAULT_ESTIMATOR}
    for name, (truth, tol) in TARGETS.items():
        mine = sorted((e for e in estimates if f"/{name}/" in f"/{e['channel']}/"), key=lambda e: e["seq"])
        assert len(mine) == 30, name
        first_seq = mine[0]["seq"]
        after_1s = [e for e in mine if (e["seq"] - first_seq + 1) * BLOCK_S >= 1.0 - 1e-9]
        assert len(after_1s) == 21
        errors = [abs(e["frequency_hz"][0] - truth) for e in after_1s]
        assert max(errors) < tol, (name, max(errors))
        assert all(e["diagnostics"]["converged"] and e["diagnostics"]["valid"] for e in after_1s), name
        # before the 200 ms window has seen the signal, nothing claims to be a measurement
        assert not mine[0]["diagnostics"]["valid"] and not mine[0]["diagnostics"]["converged"]
    assert "recorded estimates reproduced bit for bit" in replay_recording(tmp_path / "rec")


def test_the_default_rule_is_ipdft_over_200_ms_whatever_the_rate():
    [rule] = load_config(env={}).rules
    assert (rule.estimator, rule.params) == ("ipdft", {"nominal_frequency_hz": 50.0, "window_cycles": 10.0})
    for fs in (1_000.0, 3_200.0, 10_000.0, 25_600.0, 50_000.0):
        est = create(rule.estimator, fs, **DEFAULT_PARAMS)
        assert est.window_samples == round(0.2 * fs)  # 200 ms: 10 cycles of 50 Hz, 12 of 60 Hz
        assert est.k_lo * fs / est.window_samples <= 45.0 and est.k_hi * fs / est.window_samples >= 65.0


@pytest.mark.parametrize("fs", [1_000.0, 4_000.0, 50_000.0])
@pytest.mark.parametrize("f", [49.5, 50.0, 59.9, 60.0])
def test_the_default_rule_measures_50_and_60_hz_mains_at_any_rate(fs, f):
    """Mains at 50 or 60 Hz with 5 % third and 3 % fifth harmonics and 40 dB SNR: within 0.01 Hz
    and converged one second in, at 1 to 50 kHz, with no nominal-frequency setting."""
    rng = np.random.default_rng(int(fs + 10 * f))
    t = np.arange(int(2.0 * fs)) / fs
    x = np.sin(2 * np.pi * f * t + 0.4) + 0.05 * np.sin(6 * np.pi * f * t) + 0.03 * np.sin(10 * np.pi * f * t + 1)
    x += rng.normal(0.0, np.sqrt(0.5 / 1e4), t.size)
    est = create(DEFAULT_ESTIMATOR, fs, **DEFAULT_PARAMS)
    block = int(0.1 * fs)
    rows = [est.update(x[i : i + block], last_only=True) for i in range(0, x.size, block)]
    late = rows[10:]
    assert max(abs(r.frequency_hz[0, 0] - f) for r in late) < 0.01
    assert all(r.converged[0] for r in late)
