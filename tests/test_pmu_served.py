"""The ``pmu`` estimator served end to end: a C37.118.1 phase step fed through real Zenoh
on loopback into the daemon, reports on the grid (several per block, none while the
window fills), the same numbers as the estimator run directly, recorded and replayed bit
for bit."""

from __future__ import annotations

import numpy as np
from conftest import make_config, serve_blocks

from sinewatch.estimators import create
from sinewatch.runtime.replay import replay
from sinewatch.scenarios import get as get_scenario
from sinewatch.schemas.codec import Block
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.messages import ESTIMATE_FORMAT_VERSION, Estimate

T0_NS = 1_700_000_000 * 10**9 + 7_300_000  # 7.3 ms after a whole second: off the 20 ms grid
BLOCK = 1000  # 0.1 s at 10 kHz: five reports per block at 50 frames/s


def test_pmu_served_on_the_grid_recorded_and_replayed(tmp_path):
    params = {"nominal_frequency_hz": 50, "reporting_rate_hz": 50}
    rule = EstimatorRule(match="sinewatch/in/pmu/**", estimator="pmu", params=params)
    config = make_config(tmp_path, rules=[rule])
    scenario = get_scenario("c37-50hz-step-phase-p10")  # +10 degrees at t = 1.5 s, 10 kHz
    fs = scenario.sample_rate_hz
    x, _ = scenario.generate(seed=0)
    n_blocks = len(x) // BLOCK
    blocks = [
        Block("pmu/pa", i, T0_NS + round(i * BLOCK * 1e9 / fs), fs, x[i * BLOCK : (i + 1) * BLOCK])
        for i in range(n_blocks)
    ]
    # what the estimator reports when run directly on the same blocks
    direct = create("pmu", fs, **params)
    expected = []
    for blk in blocks:
        rep = direct.update(blk.samples, last_only=True, t0_ns=blk.t0_ns).reports
        assert rep is not None
        expected += [(blk.seq, ts, float(rep.track.frequency_hz[r, 0])) for r, ts in enumerate(rep.timestamps_ns())]
    assert 0 < len(expected) < n_blocks * 5 + 1

    got, daemon = serve_blocks(config, "pmu/pa", blocks, len(expected))
    msgs = [Estimate.model_validate({k: v for k, v in m.items() if k != "_key"}) for m in got]
    assert [(m.seq, m.timestamp_ns, m.frequency_hz[0]) for m in msgs] == expected
    # on the grid: multiples of 20 ms since the epoch, every one from the first to the last
    stamps = [m.timestamp_ns for m in msgs]
    assert all(ts % 20_000_000 == 0 for ts in stamps)
    assert np.all(np.diff(stamps) == 20_000_000)
    # several reports per block, none for the blocks that only fill the window
    per_block = np.bincount([m.seq for m in msgs], minlength=n_blocks)
    assert per_block[0] == 0 and set(per_block[3:].tolist()) == {5}
    # ROCOF first class, the synchrophasor in extras, messages of the current version
    assert all(m.format_version == ESTIMATE_FORMAT_VERSION and m.rocof_hz_per_s is not None for m in msgs)
    angle = [m.diagnostics.extras["synchrophasor_angle_rad"] for m in msgs]
    t_step_ns = T0_NS + 1_500_000_000
    before = [a for a, ts in zip(angle, stamps, strict=True) if ts < t_step_ns - 200_000_000]
    after = [a for a, ts in zip(angle, stamps, strict=True) if ts > t_step_ns + 200_000_000]
    step = np.angle(np.mean(np.exp(1j * np.array(after))) / np.mean(np.exp(1j * np.array(before))))
    assert abs(step - np.radians(10.0)) < 1e-3  # the +10 degree step
    result = replay(daemon.recording_paths)
    assert result.ok and result.matched == len(expected)
