"""A channel that does not continue (a gateway restart, a clock step) starts over: the
estimator and the presence detector are reset, the estimate says so (``reset``, ``gap``,
``restart``) and nothing is valid until the estimator's memory has refilled with the new
stream. Checked on the continuity rule itself and on a live daemon (real Zenoh on 127.0.0.1)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TIMEOUT, clean_estimates, make_config, run_daemon, take

from sinewatch.clients import BlockPublisher, connect, subscribe_estimates
from sinewatch.core.continuity import Continuity, check_continuity
from sinewatch.runtime.replay import replay
from sinewatch.schemas.codec import Block, encode_block_binary
from sinewatch.schemas.config import EstimatorRule
from sinewatch.schemas.errors import InputError

FS = 10_000.0
N = 500  # 50 ms blocks
BLOCK_NS = 50_000_000
T00 = 1_700_000_000 * 1_000_000_000


def test_the_continuity_rule():
    c = lambda seq, t0, v=2: check_continuity(4, 5 * BLOCK_NS, seq, t0, N, FS, rules_version=v)
    assert c(5, 5 * BLOCK_NS) == Continuity()
    assert c(5, 5 * BLOCK_NS + 20_000_000) == Continuity()  # jitter under half a block
    assert c(5, 5 * BLOCK_NS + 30_000_000) == Continuity(time_jump_ns=30_000_000)
    assert c(5, 5 * BLOCK_NS + 30_000_000, v=1) == Continuity()  # earlier builds' rule
    assert c(8, 8 * BLOCK_NS) == Continuity(gap_blocks=3)
    assert c(0, 5 * BLOCK_NS + 45 * 10**9) == Continuity(restart=True)
    assert c(0, 5 * BLOCK_NS).starts_over(2) and not c(0, 5 * BLOCK_NS).starts_over(1)
    with pytest.raises(InputError) as dup:
        c(4, 4 * BLOCK_NS)
    assert dup.value.kind == "duplicate"
    with pytest.raises(InputError) as old:
        c(2, 2 * BLOCK_NS)
    assert old.value.kind == "out_of_order"


def _blocks(seqs_and_starts, f_before=50.0, f_after=50.0, switch_at=None):
    """(seq, t0_ns) -> blocks of a 50 Hz sine (its frequency f_after from block ``switch_at``
    on, with a phase that is not the old one's continuation)."""
    out = []
    for i, (seq, t0) in enumerate(seqs_and_starts):
        f = f_before if switch_at is None or i < switch_at else f_after
        phase = 0.0 if switch_at is None or i < switch_at else 1.9
        t = (t0 - T00) / 1e9 + np.arange(N) / FS
        out.append(Block("gw/a", seq, t0, FS, np.sin(2 * np.pi * f * t + phase)))
    return out


@pytest.mark.parametrize("estimator", ["ges-kalman", "pmu"])
def test_a_gateway_restart_on_a_live_daemon_starts_the_channel_over(tmp_path, estimator):
    """40 blocks (2 s), then the gateway is silent 45 s and comes back counting from 0 with a
    signal at 52 Hz: the first estimates after it say reset and restart and are not valid
    until the estimator's memory is full of the new signal; then valid and right."""
    config = make_config(tmp_path)  # ges-kalman at 10 kHz
    if estimator == "pmu":  # the default rule
        config = make_config(tmp_path, rules=[EstimatorRule(match="sinewatch/in/**")])
    before = [(s, T00 + s * BLOCK_NS) for s in range(40)]
    t_back = T00 + 40 * BLOCK_NS + 45 * 10**9
    after = [(s, t_back + s * BLOCK_NS) for s in range(40)]
    blocks = _blocks(before + after, f_after=52.0, switch_at=40)
    n_expected = len(clean_estimates(config, "sinewatch/in/gw/a", blocks))  # pmu: reports, not blocks

    def client(daemon, ep):
        with connect([ep]) as s:
            est = subscribe_estimates(s)
            pub = BlockPublisher(s, dtype="float64")
            assert pub.wait_for_subscriber("gw/a", TIMEOUT)
            for b in blocks:  # the blocks as made: their own seq and t0 (a restart among them)
                pub.publish_raw("gw/a", encode_block_binary(b))
            return take(est, n_expected)

    estimates, daemon, code = run_daemon(config, client)
    assert code == 0 and len(estimates) == n_expected
    assert all(e["estimator"] == estimator for e in estimates)
    after_restart = [e for e in estimates if e["timestamp_ns"] >= t_back]
    first = after_restart[0]["diagnostics"]
    assert first["restart"] and first["reset"] and first["gap"]
    assert not any(e["diagnostics"]["restart"] for e in after_restart[1:])
    # nothing valid before the estimator's memory has seen only the new stream
    memory_s = daemon.pipeline.channels["gw/a"].estimator.memory_samples / FS
    for e in after_restart:
        age_s = (e["timestamp_ns"] - t_back) / 1e9
        if e["diagnostics"]["valid"]:
            assert age_s >= memory_s - 1e-9, age_s
    valid = [e for e in after_restart if e["diagnostics"]["valid"]]
    assert valid, "valid again once the memory has refilled"
    late = [e for e in valid if (e["timestamp_ns"] - t_back) / 1e9 >= 1.0]
    assert late and max(abs(e["frequency_hz"][0] - 52.0) for e in late) < 0.05
    [path] = daemon.recording_paths
    assert replay([path]).ok
