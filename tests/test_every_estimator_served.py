"""Every registered estimator is served by the daemon like any other: chosen by a config
rule, fed through real Zenoh on loopback, one estimate per block, recorded, and
replayed bit for bit."""

from __future__ import annotations

import pytest
from conftest import make_config, serve_blocks

from sinewatch.estimators import available, get
from sinewatch.runtime.replay import replay
from sinewatch.schemas.codec import Block
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.messages import Estimate


@pytest.mark.parametrize("name", sorted(available()))
def test_served_recorded_and_replayed(tmp_path, name):
    cls = get(name)
    if cls.reports_on_grid:
        pytest.skip("reports on a time grid, not one estimate per block: tests/test_pmu_served.py")
    rule = EstimatorRule(match="sinewatch/in/x/**", estimator=name, params=dict(cls.example_params))
    config = make_config(tmp_path, rules=[rule])
    fs = cls.example_sample_rate_hz
    x = cls.example_signal(4000, seed=5)
    # contiguous in time (a block whose time jumps starts its channel over: test_continuity.py)
    blocks = [Block("x/one", i, round(i * 400 * 1e9 / fs), fs, x[i * 400 : (i + 1) * 400]) for i in range(10)]

    got, daemon = serve_blocks(config, "x/one", blocks, len(blocks))
    assert [m["seq"] for m in got] == list(range(10))
    for m in got:
        e = Estimate.model_validate({k: v for k, v in m.items() if k != "_key"})
        assert e.estimator == name and len(e.frequency_hz) == cls.example().n_components
    # the same numbers as the estimator run directly on the whole signal
    direct = cls.example().update(x)
    last = got[-1]
    f_direct = direct.frequency_hz[-1, 0]
    assert (last["frequency_hz"][0] is None) == (f_direct != f_direct)
    if last["frequency_hz"][0] is not None:
        assert last["frequency_hz"][0] == f_direct
    result = replay(daemon.recording_paths)
    assert result.ok and result.matched == 10
