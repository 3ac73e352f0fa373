"""pqopen-lib (the optional extra) on the same waveforms as sinewatch's harmonic analyser:
both run, pqopen's unbalance is within class A, and sinewatch is the more accurate on every
scenario; skipped when pqopen-lib is not installed."""

from __future__ import annotations

import pytest

pytest.importorskip("pqopen.powersystem")

from sinewatch.power_quality.speed import compare_accuracy
from sinewatch.scenarios.power_quality_iec import get_pq


def test_sinewatch_and_pqopen_on_the_same_waveforms():
    rows = compare_accuracy([get_pq("pq-harmonics-50hz-all-p5"), get_pq("pq-unbalance-50hz-u2-2pct-harmonics-m5")])
    for row in rows:
        assert row["pqopen_windows"] >= 6
        # fractions of the IEC limit (<= 1 passes); sinewatch measured <= 6e-4
        assert row["sinewatch_harmonic"] <= 0.01 and row["sinewatch_thd40"] <= 0.01
        assert row["pqopen_harmonic"] > row["sinewatch_harmonic"]
        assert row["pqopen_thd40"] > row["sinewatch_thd40"]
    unb = rows[1]
    assert unb["sinewatch_u2"] <= 0.01 and unb["pqopen_u2"] <= 1.0
