"""differential-rls's compiled bank (``sinewatch.estimators._differential_rls_bank``) against each
channel alone, bit for bit, at bank sizes 1, 3, 8 and 64 with the channel at every position: its
lanes take their decimated steps (the RLS pair, the atan2/hypot of the phase stage, scalar per
lane) at different samples when their histories differ, and a frequency step moves the
reference (the clamp and the re-centring) in the probe alone."""

from __future__ import annotations

import numpy as np
import pytest
from bank_positions import assert_every_position

from sinewatch.estimators import get
from sinewatch.estimators.base import Estimator

NAME = "differential-rls"
BLOCK = 300


def _make() -> Estimator:
    return get(NAME).example()


def _probe(n: int) -> np.ndarray:
    """The example's tone, stepping from 50.3 Hz to 51.5 Hz half-way, with noise."""
    cls = get(NAME)
    fs = cls.example_sample_rate_hz
    f = np.where(np.arange(n) < n // 2, 50.3, 51.5)
    phase = 2 * np.pi * np.cumsum(f) / fs
    return 1.5 * np.sin(phase) + 0.01 * np.random.default_rng(5).standard_normal(n)


def test_bank_matches_each_channel_alone_at_every_position() -> None:
    probe = _probe(6 * BLOCK)
    fillers = [get(NAME).example_signal(probe.size, seed=20 + k) * (1.0 + 0.3 * k) for k in range(5)]
    runs = assert_every_position(_make, probe, fillers, (1, 3, 8), BLOCK)
    assert abs(float(runs[-1][0].frequency_hz[-1, 0]) - 51.5) < 0.5  # it followed the step


# 64 banks of 64 channels (~45 s on a loaded 2-core VM): the default run has every position at 1, 3
# and 8 here and a bank of 64 with every channel checked (tests/test_estimator_banks.py)
@pytest.mark.slow
def test_bank_of_64_matches_each_channel_alone_at_every_position() -> None:
    probe = _probe(2 * BLOCK)
    fillers = [get(NAME).example_signal(probe.size, seed=40 + k) for k in range(5)]
    assert_every_position(_make, probe, fillers, (64,), BLOCK)
