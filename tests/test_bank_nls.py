"""nls's compiled bank (``sinewatch.estimators._nls_bank``) against each channel alone, bit for bit,
at bank sizes 1, 3, 8 and 64 with the channel at every position: its lanes predict each sample
together (one vector) but fit their windows at different samples when their histories differ
(the ring's fill and hop counters per lane), and write their rings a row at a time only while
they stay in step; a frequency step moves the fit, two tones use the tones' own rows, and a block
shorter than the hop holds the estimate across calls."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from bank_positions import assert_every_position
from test_estimator_banks import assert_states_bitwise, assert_tracks_bitwise

from sinewatch.estimators import get
from sinewatch.estimators.bank import bank_of, update_bank
from sinewatch.estimators.base import Estimator

NAME = "nls"
FS = 1000.0
# a short window and a hop of a quarter of it: several fits a block, each a few microseconds
SMALL = {"min_frequency_hz": 20.0, "window_samples": 96, "hop_samples": 24, "zero_pad": 2}
TWO_TONES = {**SMALL, "n_components": 2, "window_samples": 128, "hop_samples": 40}


def _probe(n: int, tones: int = 1) -> np.ndarray:
    """A tone stepping from 50 Hz to 57 Hz half-way (and a second at 130 Hz), with noise."""
    t = np.arange(n) / FS
    f = np.where(np.arange(n) < n // 2, 50.0, 57.0)
    x = 1.5 * np.sin(2 * np.pi * np.cumsum(f) / FS) + 0.01 * np.random.default_rng(5).standard_normal(n)
    if tones == 2:
        x += 0.7 * np.sin(2 * np.pi * 130.0 * t + 0.3)
    return x


def _fillers(n: int, tones: int = 1) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    t = np.arange(n) / FS
    out = []
    for k in range(5):
        x = (1.0 + 0.3 * k) * np.sin(2 * np.pi * (45.0 + 4.0 * k) * t + k) + 0.05 * rng.standard_normal(n)
        if tones == 2:
            x += 0.5 * np.cos(2 * np.pi * (110.0 + 7.0 * k) * t)
        out.append(x)
    return out


def _maker(params: dict[str, Any]) -> Callable[[], Estimator]:
    return lambda: get(NAME)(FS, params)


def test_nls_has_a_compiled_bank() -> None:
    assert bank_of(get(NAME)) is not None


@pytest.mark.parametrize("block", [70, 1000])  # fits inside a block, and a block shorter than the hop
def test_bank_matches_each_channel_alone_at_every_position(block: int) -> None:
    probe = _probe(1400)
    runs = assert_every_position(_maker(SMALL), probe, _fillers(probe.size), (1, 3, 8), block)
    assert abs(float(runs[-1][0].frequency_hz[-1, 0]) - 57.0) < 0.5  # it followed the step


def test_two_tones_at_every_position() -> None:
    probe = _probe(900, tones=2)
    runs = assert_every_position(_maker(TWO_TONES), probe, _fillers(probe.size, tones=2), (1, 3), 110)
    found = np.sort(runs[-1][0].frequency_hz[-1])
    assert abs(found[0] - 57.0) < 1.0 and abs(found[1] - 130.0) < 1.0


def test_channels_started_together_and_every_row() -> None:
    """Eight channels from the same start (their rings written a row at a time), every row of the
    track (``last_only=False``), then one channel restarted (out of step from there on)."""
    x = np.ascontiguousarray(np.stack([_probe(600), *_fillers(600), _probe(600)[::-1], _fillers(600)[0] * 0.5], axis=1))
    make = _maker(SMALL)
    singles, banked = [make() for _ in range(8)], [make() for _ in range(8)]
    for a in range(0, 600, 100):
        if a == 300:  # channel 5 starts afresh: its ring's position leaves the others'
            singles[5], banked[5] = make(), make()
        got = update_bank(banked, x[a : a + 100], last_only=False)
        for c in range(8):
            where = f"channel {c}, block at {a}"
            assert_tracks_bitwise(
                singles[c].update(np.ascontiguousarray(x[a : a + 100, c]), last_only=False), got[c], where
            )
            assert_states_bitwise(singles[c], banked[c], where)


def test_the_example_at_every_position() -> None:
    """The example's 1024-sample window and hop (the bench's setting), one fit a block."""
    cls = get(NAME)
    probe = cls.example_signal(3 * 1024, seed=3)
    fillers = [cls.example_signal(probe.size, seed=20 + k) * (1.0 + 0.3 * k) for k in range(3)]
    assert_every_position(cls.example, probe, fillers, (3,), 1024)


@pytest.mark.slow
def test_bank_of_64_matches_each_channel_alone_at_every_position() -> None:
    probe = _probe(500)
    assert_every_position(_maker(SMALL), probe, _fillers(probe.size), (64,), 120)
