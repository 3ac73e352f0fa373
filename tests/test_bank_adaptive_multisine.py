"""adaptive-multisine's compiled bank (n = 2 of the automatic mode:
``sinewatch.estimators._adaptive_multisine_bank``) against each channel alone, bit for bit, at
bank sizes 1, 3, 8 and 64 with the channel at every position; through the branches its lanes
take apart (the signal lost and back, a component fading, the re-centring AD8, the guard's
restart), with and without the offset. Other modes have no bank: their channels run one by one."""

from __future__ import annotations

import numpy as np
import pytest
from bank_positions import assert_every_position
from test_adaptive_multisine_small_n import FS, _signal

from sinewatch.estimators import create
from sinewatch.estimators._adaptive_multisine_bank import run_adaptive_multisine_bank
from sinewatch.estimators.bank import update_bank
from sinewatch.estimators.base import Estimator

NAME = "adaptive-multisine"
BLOCK = 750  # 1 s
BLOW_UP_AT = 20 * BLOCK  # the probe's x_1 set to 1e12 before this block: the guard must restart it


def _make(bias: bool) -> Estimator:
    return create(NAME, FS, n_sinusoids=2, band_hz=(5.0, 25.0), bias=bias)


def _fillers(n: int) -> list[np.ndarray]:
    """Five other inputs: tones elsewhere in the band, each with its own noise."""
    t = np.arange(n) / FS
    rng = np.random.default_rng(11)
    return [
        (1.0 + k) * np.sin(2 * np.pi * (6.0 + 3.0 * k) * t) + 0.5 * np.sin(2 * np.pi * (20.0 - k) * t + k)
        + 0.05 * rng.standard_normal(n)
        for k in range(5)
    ]  # fmt: skip


def _blow_up(est: Estimator, i: int) -> None:
    if i == BLOW_UP_AT:
        est._state = {"s": est._state["s"].copy()}
        est._state["s"][1] = 1e12  # zh's x_1 (the output filter's one state comes first)


@pytest.mark.parametrize("bias", [True, False])
def test_bank_matches_each_channel_alone_at_every_position_through_every_branch(bias: bool) -> None:
    probe = _signal(2, bias)  # 40 s: lost from 12 s to 14 s, the 10 Hz tone gone from 26 s
    runs = assert_every_position(lambda: _make(bias), probe, _fillers(probe.size), (1, 3, 8), BLOCK, _blow_up)
    # the branches were taken: the guard restarted the observer, the signal was absent, a
    # component faded, and a moved away from its initial design (AD8's re-centring)
    tracks = [track for track, _ in runs]
    assert tracks[BLOW_UP_AT // BLOCK].extras["observer_reset"].any()
    assert not tracks[13].extras["signal_present"].all()
    assert any(track.extras["component_faded"].any() for track in tracks[21:])  # after the tone stops
    est = _make(bias)
    a0 = est._state["s"][-(2 + 4 + int(bias)) :][:2].copy()
    a_end = np.frombuffer(runs[-1][1]["s"])[-(2 + 4 + int(bias)) :][:2]
    assert not np.array_equal(a0, a_end)


# 64 banks of 64 channels (~45 s on a loaded 2-core VM): the default run has every position at 1, 3
# and 8 here and a bank of 64 with every channel checked (tests/test_estimator_banks.py)
@pytest.mark.slow
def test_bank_of_64_matches_each_channel_alone_at_every_position() -> None:
    probe = _signal(2, True)[: 2 * BLOCK // 3]  # two blocks of 250 samples: 64 banks of 64 are enough to run
    assert_every_position(lambda: _make(True), probe, _fillers(probe.size), (64,), BLOCK // 3)


@pytest.mark.parametrize(
    "params",
    [{"n_sinusoids": 1, "band_hz": (5.0, 25.0)}, {"n_sinusoids": 3, "band_hz": (5.0, 25.0)}, {"n_sinusoids": 2}],
)
def test_other_modes_run_one_by_one_with_the_same_bits(params: dict) -> None:
    ests = [create(NAME, FS, **params) for _ in range(3)]
    x = np.ascontiguousarray(np.stack(_fillers(BLOCK)[:3], axis=1))
    assert run_adaptive_multisine_bank(ests, x, False, None) is None
    alone = [create(NAME, FS, **params) for _ in range(3)]
    got = update_bank(ests, x)
    for c in range(3):
        want = alone[c].update(np.ascontiguousarray(x[:, c]))
        assert want.frequency_hz.tobytes() == got[c].frequency_hz.tobytes()
        assert alone[c]._state["s"].tobytes() == ests[c]._state["s"].tobytes()
